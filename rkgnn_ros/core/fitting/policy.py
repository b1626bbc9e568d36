# Copyright 2026 rkgnn_ros maintainers
#
# Licensed under the Apache License, Version 2.0 (the "License");
# you may not use this file except in compliance with the License.
# You may obtain a copy of the License at
#
#     http://www.apache.org/licenses/LICENSE-2.0
#
# Unless required by applicable law or agreed to in writing, software
# distributed under the License is distributed on an "AS IS" BASIS,
# WITHOUT WARRANTIES OR CONDITIONS OF ANY KIND, either express or implied.
# See the License for the specific language governing permissions and
# limitations under the License.

"""
The online policy's tunables, in one table, and the rules the policy's parts share.

Every time constant and threshold with which the online identification decides what to do
and when (:mod:`.online` and the keepers it runs: :mod:`.case_one`, :mod:`.case_three`,
:mod:`.rigid_online`, the change detectors, the search's starts, the excitation memory's
feed) is a row of :data:`TABLE`: its name, value, unit and why. The modules import the
names from here; nothing else defines one. Times are seconds of the policy's clock unless
the unit says otherwise; "share" is a fraction of what the row names.

The settings a user changes (the window, the validation share, the case ...) are not here:
they are the identifier's parameters (:mod:`rkgnn_ros.identification.parameters`), handed
to the policy as :class:`~.online_records.OnlineSettings`.
"""

from typing import List, NamedTuple

__all__ = ['TABLE', 'Tunable', 'retry_wait', 'still_holds']


class Tunable(NamedTuple):
    """One row of the table."""

    name: str
    value: float
    unit: str
    why: str


#: Every tunable of the online policy, in the order below.
TABLE: List[Tunable] = []


def _tunable(name: str, value, unit: str, why: str):
    TABLE.append(Tunable(name, value, unit, why))
    return value


# -- the search's schedule (online.py)
DATA_REFRESH_S = _tunable(
    'DATA_REFRESH_S', 1.0, 's', 'the buffered window is taken again at most this often')
WAITING_REFRESH_S = _tunable(
    'WAITING_REFRESH_S', 0.25, 's', 'while too little is buffered, look again this often')
VALIDATION_EVERY = _tunable(
    'VALIDATION_EVERY', 5, 'generations', 'between two validations of a changed best')
EVOLUTION_MIN_PERIOD = _tunable(
    'EVOLUTION_MIN_PERIOD', 0.05, 's', 'generation statistics are reported at most this often')
MAX_CONSECUTIVE_ERRORS = _tunable(
    'MAX_CONSECUTIVE_ERRORS', 3, 'steps', 'failed steps in a row after which the search '
    'restarts')
LOG_THROTTLE_S = _tunable(
    'LOG_THROTTLE_S', 1.0, 's', 'a repeating warning is logged at most this often')
YOUNG_DATA_S = _tunable(
    'YOUNG_DATA_S', 15.0, 's of data', 'below this span the data are young: trigonometric '
    'fits that do not hold are retried every second without doubling waits, and the '
    "search's equation-error fits are kept short (YOUNG_WARM_START_S) so they do not hold "
    'those retries back')
YOUNG_WARM_START_S = _tunable(
    'YOUNG_WARM_START_S', 1.0, 'real s', 'budget of one equation-error fit of the search '
    'while the data are young; it runs in the worker thread between the trigonometric fits, '
    'which wait for it')

# -- where a search starts (search_starts.py)
WARM_START_S = _tunable(
    'WARM_START_S', 5.0, 'real s', 'budget of one equation-error fit (the warm start)')
WARM_START_NFEV = _tunable(
    'WARM_START_NFEV', 300, 'evaluations', 'of the equation-error fit, at most')
WARM_START_SIGMA = _tunable(
    'WARM_START_SIGMA', 0.05, 'genome units', 'search spread around the warm start')
REWARM_GROWTH = _tunable(
    'REWARM_GROWTH', 1.5, 'ratio', 'the equation-error fit runs again when the window grew '
    'this much since it last ran ...')
REWARM_PERIOD_S = _tunable(
    'REWARM_PERIOD_S', 10.0, 's', '... or when this long passed since it last ran')

# -- what a fit must show on the newest data (shared by the laws and the gains)
MIN_SEGMENT_SAMPLES = _tunable(
    'MIN_SEGMENT_SAMPLES', 10, 'samples', 'shorter segments (training or validation) are '
    'left out')
NEWEST_SHARE = _tunable(
    'NEWEST_SHARE', 0.5, 'share of the data', 'a law or gains fitted on the data are used '
    'only when this newest share of the data gives the same ones (the data determine them)')
KD_AGREEMENT_S = _tunable(
    'KD_AGREEMENT_S', 0.1, 's', 'two Kd agree within rtol * (|Kd| + this * |Kp|): a small '
    'derivative gain is noisy relative to itself but matters little against Kp')
KI_AGREEMENT_PER_S = _tunable(
    'KI_AGREEMENT_PER_S', 0.1, '1/s', 'two Ki agree within rtol * (|Ki| + this * |Kp|)')

# -- case 1: the servo law learned from torque (case_one.py)
MIN_LAW_SAMPLES = _tunable(
    'MIN_LAW_SAMPLES', 50, 'filtered rows', 'before a law is fitted')
MAX_LAW_FIT_RATIO = _tunable(
    'MAX_LAW_FIT_RATIO', 0.1, 'share of the torque', 'a law explains the torque when its '
    'RMS residual is below this')
LAW_AGREEMENT_RTOL = _tunable(
    'LAW_AGREEMENT_RTOL', 0.1, 'relative', 'the law fitted on the whole data and on its '
    'newest share must have these gains in common: with many θ-terms a few seconds of '
    'encoder noise fit almost any gains, and the residual alone does not show it')
LAW_GAIN_RTOL = _tunable(
    'LAW_GAIN_RTOL', 0.02, 'relative', 'a refit moving the gains more than this moves the '
    'law (the running search restarts on it)')
LAW_KI_ZERO = _tunable(
    'LAW_KI_ZERO', 1e-3, '1/s (Ki / Kp)', 'a learned integral gain below this share of Kp '
    'is a fitted zero')
INTEGRAL_MIN_RESIDUAL = _tunable(
    'INTEGRAL_MIN_RESIDUAL', 1e-3, 'share of the torque', 'a richer law (an integral, '
    'θ-terms) is considered only where the simpler one leaves more than this ...')
LAW_FORM_GAIN = _tunable(
    'LAW_FORM_GAIN', 0.5, 'ratio', '... and kept only where it leaves at most this share '
    'of what the simpler one leaves')
LAW_THETA_SAMPLES = _tunable(
    'LAW_THETA_SAMPLES', 2000, 'samples', "θ kept to project a law's θ-terms on a model's "
    'units')
TRIG_MIN_SAMPLES = _tunable(
    'TRIG_MIN_SAMPLES', 200, 'samples', 'training samples with torque before the '
    'trigonometric arm is tried')
TRIG_MAX_TORQUE_ERROR = _tunable(
    'TRIG_MAX_TORQUE_ERROR', 0.1, 'RMSE / std', 'the trigonometric arm predicts while its '
    'held-out torque error (worst joint) is at most this')
TRIG_FIRST_RETRY_S = _tunable(
    'TRIG_FIRST_RETRY_S', 1.0, 's', 'a trigonometric arm that did not hold is fitted '
    'again after this; once the data are not young the wait doubles with each failure ...')
TRIG_RETRY_S = _tunable(
    'TRIG_RETRY_S', 10.0, 's', '... up to this: an arm the planar basis does not hold '
    'would pay the fit at every refresh for nothing')

# -- case 3: the linear closed loop and the gains (case_three.py, trig_loop.py)
GAIN_AGREEMENT_RTOL = _tunable(
    'GAIN_AGREEMENT_RTOL', 0.15, 'relative', 'the gains of the whole data and of its newest '
    "share must agree this well (the share's are the noisier)")
MIN_GAIN_SAMPLES = _tunable(
    'MIN_GAIN_SAMPLES', 51, 'samples', "shorter segments are left out of the gains' fit")
MAX_GAIN_FEATURES = _tunable(
    'MAX_GAIN_FEATURES', 200, 'features', "the gains' fit uses the general trigonometric "
    'basis up to this many features and the tied planar one beyond (the general basis '
    'grows combinatorially with the joints, and its normal equations with it)')
MAX_LOOP_ERROR = _tunable(
    'MAX_LOOP_ERROR', 0.1, 'share of the servo torque', 'the linear closed loop predicts '
    'while its held-out equation error (worst joint) is at most this')
MIN_LOOP_SAMPLES = _tunable(
    'MIN_LOOP_SAMPLES', 200, 'samples', 'training samples before the linear closed loop is '
    'tried')
REFIT_S = _tunable(
    'REFIT_S', 5.0, 's', 'between fits while the linear closed loop holds (it is global: the '
    'newest data change it little, and each fit holds the search back)')
RETRY_S = _tunable(
    'RETRY_S', 1.0, 's', 'a linear closed loop that did not hold is fitted again after '
    'this; once the data are not young the wait doubles with each failure ...')
RETRY_MAX_S = _tunable(
    'RETRY_MAX_S', 30.0, 's', '... up to this')
LOOP_KI_ZERO = _tunable(
    'LOOP_KI_ZERO', 0.01, '1/s (Ki / Kp)', "the closed loop's integral gain below this share "
    "of Kp, or negative, is a fitted zero (a PD servo's data give a small positive one)")
INTEGRAL_GAIN = _tunable(
    'INTEGRAL_GAIN', 2.0, 'ratio', "the closed loop's PID form is kept when its held-out "
    "error is this many times smaller than the PD form's ...")
INTEGRAL_MIN_ERROR = _tunable(
    'INTEGRAL_MIN_ERROR', 0.01, 'share of the servo torque', "... and the PD form's is "
    'above this')

# -- a robot description's rigid body (rigid_online.py, rigid_fit.py)
RIGID_MIN_DATA_S = _tunable(
    'RIGID_MIN_DATA_S', 2.0, 's of data', 'before the first fit (gaps left out)')
RIGID_REFRESH_S = _tunable(
    'RIGID_REFRESH_S', 1.0, 's', 'between two refits, at least')
RIGID_MAX_ERROR = _tunable(
    'RIGID_MAX_ERROR', 0.5, 'RMSE / std', 'a fit predicts while its held-out error (worst '
    'joint) is at most this; it is published either way')
FORMS_EVERY_S = _tunable(
    'FORMS_EVERY_S', 10.0, 's', "between two choices of the closed loop's form (integral, "
    'gravity compensation); in between only the chosen form is refitted')
FORM_GAIN = _tunable(
    'FORM_GAIN', 0.5, 'ratio', 'a richer closed-loop form is kept when its held-out error is '
    "at most this share of the simpler one's ...")
FORM_MIN_ERROR = _tunable(
    'FORM_MIN_ERROR', 0.01, 'RMSE / std', '... and the simpler form leaves more than this '
    '(worst joint)')

# -- changes of the dynamics (change.py, rigid_online.py, rigid_change.py, trig_change.py)
DETECT_MIN_S = _tunable(
    'DETECT_MIN_S', 6.0, 's of data', "a fit needs this much before its residual's level "
    'judges changes')
CHECK_EVERY_S = _tunable(
    'CHECK_EVERY_S', 0.25, 's', 'between two checks for a change, at least')
CHECK_S = _tunable(
    'CHECK_S', 1.0, 's of data', 'the newest stretch a check judges')
CHANGE_ALARM = _tunable(
    'CHANGE_ALARM', 25.0, 'mean squared normalised residual', "a block's level at or above "
    'which the dynamics changed')
CHANGE_MIN_ROWS = _tunable(
    'CHANGE_MIN_ROWS', 5, 'samples', 'fewest new samples a block is judged on')
CHANGE_ONSET = _tunable(
    'CHANGE_ONSET', 3.0, 'normalised residual', 'above this marks where the change began')
CHANGE_RELATIVE_FLOOR = _tunable(
    'CHANGE_RELATIVE_FLOOR', 0.01, "share of the joint's torque std", 'smallest normal '
    'residual level')
CHANGE_MARGIN_SIGMAS = _tunable(
    'CHANGE_MARGIN_SIGMAS', 2.0, "filter widths (the fit's sigma, s)", 'the data after a '
    'change detected on a rigid body count from this far after its onset, clear of the '
    "filter's reach back")
TRIG_CHANGE_MARGIN_S = _tunable(
    'TRIG_CHANGE_MARGIN_S', 0.05, 's', 'the data after a change detected on the '
    'trigonometric arm count from this far after its onset')
PAYLOAD_MIN_S = _tunable(
    'PAYLOAD_MIN_S', 1.0, 's of data', 'after a change before the last body is refitted ...')
FULL_REFIT_S = _tunable(
    'FULL_REFIT_S', 8.0, 's of data', '... and before the whole model is (from then on, only '
    'on data after the change)')
BODY_RIDGE = _tunable(
    'BODY_RIDGE', 1e-3, 'relative, per row', "the last body's refit after a change is pulled "
    "towards the body before it by this ridge, relative to each column's scale")

# -- the excitation memory's feed (memory.py)
OFFER_EVERY = _tunable(
    'OFFER_EVERY', 5, 'samples', 'one new sample in this many is offered to the memory '
    '(neighbouring samples say nearly the same)')
MEMORY_CAPACITY = _tunable(
    'MEMORY_CAPACITY', 500, 'samples', "the identifier's memory keeps")


def retry_wait(failures: int, young: bool, first_s: float, longest_s: float) -> float:
    """
    Return the wait (s) before a fit that did not hold is tried again.

    ``first_s`` while the data are young (:data:`YOUNG_DATA_S`) or after the first failure;
    then doubling with each further failure in a row, up to ``longest_s``.
    """
    return first_s if young else min(longest_s, first_s * 2.0 ** max(0, failures - 1))


def still_holds(error: float, limit: float) -> bool:
    """
    Return whether a fitted model in use stays although a refit did not hold.

    It stays while it explains the newest data as well as a new fit must (``error`` at most
    ``limit``, the new fit's own bar): a refit on a short, weakly exciting stretch can miss
    what the model in use still holds.
    """
    return error <= limit

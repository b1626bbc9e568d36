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
feed) is a row of the table below (:func:`table`): a module constant under a comment that
says its unit and why. The modules import the names from here; nothing else defines one.
Times are seconds of the policy's clock unless the unit says otherwise; "share" is a
fraction of what the row names.

The settings a user changes (the window, the validation share, the case ...) are not here:
they are the identifier's parameters (:mod:`rkgnn_ros.identification.parameters`), handed
to the policy as :class:`~.online_records.OnlineSettings`.
"""

import re
from typing import List, NamedTuple

__all__ = ['Tunable', 'retry_wait', 'still_holds', 'table']


class Tunable(NamedTuple):
    """One row of the table."""

    name: str
    value: float
    unit: str
    why: str


def table() -> List[Tunable]:
    """
    Return the table: the tunables of this module in order, each with its comment.

    A tunable is an UPPER_CASE name bound to a number, its ``#:`` comment above it reads
    ``[unit] why``.
    """
    with open(__file__, encoding='utf-8') as f:
        lines = f.read().splitlines()
    rows, comment = [], []
    for line in lines:
        if line.startswith('#: '):
            comment.append(line[3:])
            continue
        name = re.match(r'([A-Z][A-Z0-9_]*) = ', line)
        if name and comment:
            unit, why = re.match(r'\[([^]]+)\] (.*)', ' '.join(comment)).groups()
            rows.append(Tunable(name.group(1), globals()[name.group(1)], unit, why))
        comment = []
    return rows


# -- the search's schedule (online.py)
#: [s] The buffered window is taken again at most this often.
DATA_REFRESH_S = 1.0
#: [s] While too little is buffered, look again this often.
WAITING_REFRESH_S = 0.25
#: [generations] Between two validations of a changed best.
VALIDATION_EVERY = 5
#: [s] Generation statistics are reported at most this often.
EVOLUTION_MIN_PERIOD = 0.05
#: [steps] Failed steps in a row after which the search restarts.
MAX_CONSECUTIVE_ERRORS = 3
#: [s] A repeating warning is logged at most this often.
LOG_THROTTLE_S = 1.0
#: [s of data] Below this span the data are young: trigonometric fits that do not hold are retried
#: every second without doubling waits, and the search's equation-error fits are kept short
#: (YOUNG_WARM_START_S) so they do not hold those retries back.
YOUNG_DATA_S = 15.0
#: [real s] Budget of one equation-error fit of the search while the data are young; it runs in the
#: worker thread between the trigonometric fits, which wait for it.
YOUNG_WARM_START_S = 1.0

# -- where a search starts (search_starts.py)
#: [real s] Budget of one equation-error fit (the warm start).
WARM_START_S = 5.0
#: [evaluations] Of the equation-error fit, at most.
WARM_START_NFEV = 300
#: [genome units] Search spread around the warm start.
WARM_START_SIGMA = 0.05
#: [ratio] The equation-error fit runs again when the window grew this much since it last ran ...
REWARM_GROWTH = 1.5
#: [s] ... or when this long passed since it last ran.
REWARM_PERIOD_S = 10.0

# -- what a fit must show on the newest data (shared by the laws and the gains)
#: [samples] Shorter segments (training or validation) are left out.
MIN_SEGMENT_SAMPLES = 10
#: [share of the data] A law or gains fitted on the data are used only when this newest share of
#: the data gives the same ones (the data determine them).
NEWEST_SHARE = 0.5
#: [s] Two Kd agree within rtol * (|Kd| + this * |Kp|): a small derivative gain is noisy relative
#: to itself but matters little against Kp.
KD_AGREEMENT_S = 0.1
#: [1/s] Two Ki agree within rtol * (|Ki| + this * |Kp|).
KI_AGREEMENT_PER_S = 0.1

# -- case 1: the servo law learned from torque (case_one.py)
#: [filtered rows] Before a law is fitted.
MIN_LAW_SAMPLES = 50
#: [share of the torque] A law explains the torque when its RMS residual is below this.
MAX_LAW_FIT_RATIO = 0.1
#: [relative] The law fitted on the whole data and on its newest share must have these gains in
#: common: with many θ-terms a few seconds of encoder noise fit almost any gains, and the residual
#: alone does not show it.
LAW_AGREEMENT_RTOL = 0.1
#: [relative] A refit moving the gains more than this moves the law (the running search restarts on
#: it).
LAW_GAIN_RTOL = 0.02
#: [1/s (Ki / Kp)] A learned integral gain below this share of Kp is a fitted zero.
LAW_KI_ZERO = 0.001
#: [share of the torque] A richer law (an integral, θ-terms) is considered only where the simpler
#: one leaves more than this ...
INTEGRAL_MIN_RESIDUAL = 0.001
#: [ratio] ... and kept only where it leaves at most this share of what the simpler one leaves.
LAW_FORM_GAIN = 0.5
#: [samples] Θ kept to project a law's θ-terms on a model's units.
LAW_THETA_SAMPLES = 2000
#: [samples] Training samples with torque before the trigonometric arm is tried.
TRIG_MIN_SAMPLES = 200
#: [RMSE / std] The trigonometric arm predicts while its held-out torque error (worst joint) is at
#: most this.
TRIG_MAX_TORQUE_ERROR = 0.1
#: [s] A trigonometric arm that did not hold is fitted again after this; once the data are not
#: young the wait doubles with each failure ...
TRIG_FIRST_RETRY_S = 1.0
#: [s] ... up to this: an arm the planar basis does not hold would pay the fit at every refresh for
#: nothing.
TRIG_RETRY_S = 10.0

# -- case 3: the linear closed loop and the gains (case_three.py, trig_loop.py)
#: [relative] The gains of the whole data and of its newest share must agree this well (the share's
#: are the noisier).
GAIN_AGREEMENT_RTOL = 0.15
#: [samples] Shorter segments are left out of the gains' fit.
MIN_GAIN_SAMPLES = 51
#: [features] The gains' fit uses the general trigonometric basis up to this many features and the
#: tied planar one beyond (the general basis grows combinatorially with the joints, and its normal
#: equations with it).
MAX_GAIN_FEATURES = 200
#: [share of the servo torque] The linear closed loop predicts while its held-out equation error
#: (worst joint) is at most this.
MAX_LOOP_ERROR = 0.1
#: [samples] Training samples before the linear closed loop is tried.
MIN_LOOP_SAMPLES = 200
#: [s] Between fits while the linear closed loop holds (it is global: the newest data change it
#: little, and each fit holds the search back).
REFIT_S = 5.0
#: [s] A linear closed loop that did not hold is fitted again after this; once the data are not
#: young the wait doubles with each failure ...
RETRY_S = 1.0
#: [s] ... up to this.
RETRY_MAX_S = 30.0
#: [1/s (Ki / Kp)] The closed loop's integral gain below this share of Kp, or negative, is a fitted
#: zero (a PD servo's data give a small positive one).
LOOP_KI_ZERO = 0.01
#: [ratio] The closed loop's PID form is kept when its held-out error is this many times smaller
#: than the PD form's ...
INTEGRAL_GAIN = 2.0
#: [share of the servo torque] ... and the PD form's is above this.
INTEGRAL_MIN_ERROR = 0.01

# -- a robot description's rigid body (rigid_online.py, rigid_fit.py)
#: [s of data] Before the first fit (gaps left out).
RIGID_MIN_DATA_S = 2.0
#: [s] Between two refits, at least.
RIGID_REFRESH_S = 1.0
#: [RMSE / std] A fit predicts while its held-out error (worst joint) is at most this; it is
#: published either way.
RIGID_MAX_ERROR = 0.5
#: [s] Between two choices of the closed loop's form (integral, gravity compensation); in between
#: only the chosen form is refitted.
FORMS_EVERY_S = 10.0
#: [ratio] ... and sooner, whenever the data have grown by this factor since the last choice (a
#: form chosen on the first 2 s is chosen again on 4 s, 8 s, ...).
FORMS_DATA_GROWTH = 2.0
#: [ratio] A richer closed-loop form is kept when its held-out error is at most this share of the
#: simpler one's ...
FORM_GAIN = 0.5
#: [RMSE / std] ... and the simpler form leaves more than this (worst joint).
FORM_MIN_ERROR = 0.01
#: [solver evaluations] Of a form's consistent fit while the forms are compared ...
SELECT_EVALUATIONS = 40
#: [solver evaluations] ... and of the chosen form's fit when it had not converged within them.
FULL_EVALUATIONS = 200

# -- changes of the dynamics (change.py, rigid_online.py, rigid_change.py, trig_change.py)
#: [s of data] A fit needs this much before its residual's level judges changes.
DETECT_MIN_S = 6.0
#: [s] Between two checks for a change, at least.
CHECK_EVERY_S = 0.25
#: [s of data] The newest stretch a check judges, at least (the samples not judged yet, up to
#: :data:`CHECK_MAX_S`, always) ...
CHECK_S = 1.0
#: [s of data] ... and at most.
CHECK_MAX_S = 10.0
#: [s] A check's new samples are judged in blocks of this length.
CHANGE_BLOCK_S = 0.25
#: [mean squared normalised residual] A block at or above this on a joint opens or continues a
#: suspect run of blocks ...
CHANGE_ALARM = 25.0
#: [product of (statistic / CHANGE_ALARM) over a joint's run] ... which is a change of the
#: dynamics once it holds this much evidence over at least two blocks ...
CHANGE_EVIDENCE = 100.0
#: [statistic / CHANGE_ALARM] ... or one block alone this much.
CHANGE_EVIDENCE_AT_ONCE = 1000.0
#: [samples] Fewest new samples a block is judged on.
CHANGE_MIN_ROWS = 5
#: [normalised residual] Above this marks where the change began.
CHANGE_ONSET = 3.0
#: [share of the joint's torque std] Smallest normal residual level.
CHANGE_RELATIVE_FLOOR = 0.01
#: [ratio] A normal residual level rises by at most this at each new fit's level; a rigid-body
#: refit whose held-out error is above this times the armed fit's on a joint does not arm the
#: detector.
CHANGE_LEVEL_GROWTH = 2.0
#: [filter widths (the fit's sigma, s)] The data after a change detected on a rigid body count from
#: this far after its onset: the onset is found on filtered rows, which rise up to the filter's
#: reach (FILTER_REACH_SIGMAS) before the change, and each row reaches back as far.
CHANGE_MARGIN_SIGMAS = 8.0
#: [centred-derivative windows (CENTRED_WINDOW samples)] The data after a change detected on the
#: trigonometric arm count from this far after its onset: the onset is found on rows whose θ̈ is
#: a centred derivative over that window, which rise up to half of it before the change.
TRIG_CHANGE_MARGIN_WINDOWS = 1.0
#: [filter widths (the fit's sigma, s)] The last body's refit after a change takes this much from
#: before its data as the filter's support (its rows are all after the change's margin).
FILTER_REACH_SIGMAS = 4.0
#: [s of data] After a change before the last body is refitted (more where the filter of noisy
#: data needs them: the fit waits for its rows) ...
PAYLOAD_MIN_S = 0.5
#: [s of data] ... and before the whole model is (from then on, only on data after the change).
FULL_REFIT_S = 8.0
#: [relative, per row] The last body's refit after a change is pulled towards the body before it by
#: this ridge, relative to each column's scale.
BODY_RIDGE = 1e-4
#: [relative, per row] ... and the change of its inertia towards a point mass's of the change's
#: mass and first moment by this one ...
POINT_MASS_RIDGE = 0.1
#: [solves] ... that point mass computed again this many times from the refit before.
POINT_MASS_PASSES = 2

# -- the excitation memory's feed (memory.py)
#: [samples] One new sample in this many is offered to the memory (neighbouring samples say nearly
#: the same).
OFFER_EVERY = 5
#: [samples] The identifier's memory keeps.
MEMORY_CAPACITY = 500


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

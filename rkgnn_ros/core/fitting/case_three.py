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
Case 3 online: the closed loop's linear fit predicts, and its gains start the search.

Without torque, the arm and its servo scale together: only the closed loop
M θ̈ + V + G + F = Kp e + Kd ė is identifiable, up to one common factor. That equation is
linear in the arm's coefficients on the trigonometric basis and in the gains
(:class:`~rkgnn_ros.core.fitting.linear.LinearDynamics`, case 'unknown'), so the gains'
ratios come out of one least-squares fit in well under a second. The case-3 search's own
start (the equation-error fit of the whole network, gauge fixed by the mean inertia)
lands far from them: on the paper's arm its closed loop predicted 2 s ahead at 183 % of the
θ range, while the arm fitted with the linearly identified gains gave 1.5 % (16 s of exact
data; following the reference: 10 %).

:func:`start_genome` therefore places the case-3 search's start: the gains, normalised so
the torque they give along the data has an RMS of 1 (the case-3 network's own unit,
``Scales.torque``), then the equation-error fit of the arm with those gains (a case-2 fit,
a few seconds at most), assembled into a case-3 genome whose torque network is that linear
PD (its RBF units start at zero weight). The gains are used only when the data determine
them: the newest half of the data must give the same ratios within
:data:`~.policy.GAIN_AGREEMENT_RTOL` (the half's estimate is the noisier). A PID servo's
data do not fit this PD closed loop; the two halves then disagree and the search keeps its
old start. When the window has grown, :func:`start_genome` is tried again, and where the
gains are still not determined (a spatial arm such as the UR5, whose closed loop the
trigonometric fit does not hold), with the search's own linear PD gains
(:func:`search_gains`): the arm fitted again under them, kept if its rollout cost is lower.

:class:`ArmKeeper` keeps that linear fit (with an integral term, on the trigonometric basis:
:func:`~rkgnn_ros.core.fitting.trig_loop.fit_closed_trig_loop`) as the predictor while it
explains held-out data: at most :data:`MAX_LOOP_ERROR` of the servo's torque unexplained.
On the paper's arm (``bench/online_servos.py``) the search's RBF model with a PD torque
network stayed no better than following the reference for a minute with encoder noise or a
PID servo; the linear fit predicts those 2 s ahead to 0.06-0.08 % of the range after 20 s.
"""

from dataclasses import replace
import math
import time
from typing import NamedTuple, Optional, Sequence, Tuple

import numpy as np

from .controller_laws import gains_agree
from .global_fit import is_global
from .identify import Evolution
from .linear import LinearDynamics
from .online_records import ClosedLoop as PredictionLoop
from .policy import (GAIN_AGREEMENT_RTOL, MAX_GAIN_FEATURES, MAX_LOOP_ERROR, MIN_GAIN_SAMPLES,
                     MIN_LOOP_SAMPLES, NEWEST_SHARE, REFIT_S, RETRY_MAX_S, RETRY_S, retry_wait,
                     still_holds, YOUNG_DATA_S)
from .refine import refine_equation_error
from .trig_loop import closed_loop_error, data_span, fit_closed_trig_loop, TrigLoop
from .validation import newest_share
from ..data import Dataset
from ..differentiate import centred_derivative
from ..model.params import decode
from ..model.trig import TrigBasis
from ..servo_law import pd_torque

__all__ = ['ArmKeeper', 'Start', 'fit_gains', 'search_gains', 'start_genome']


def _gain_basis(n_joints: int) -> TrigBasis:
    basis = TrigBasis(n_joints)
    return basis if basis.n_features <= MAX_GAIN_FEATURES else TrigBasis(
        n_joints, planar=True, tied=True)


def _usable(kp: np.ndarray, kd: np.ndarray) -> Optional[Tuple[np.ndarray, np.ndarray]]:
    """Return ``(kp, max(kd, 0))`` if both are finite and every Kp positive, else None."""
    if not (np.all(np.isfinite(kp)) and np.all(np.isfinite(kd)) and np.all(kp > 0.0)):
        return None
    return kp, np.maximum(kd, 0.0)


def _linear_gains(segments: Sequence[Dataset]) -> Optional[Tuple[np.ndarray, np.ndarray]]:
    """Return the gains (mean Kp 1) of the linear closed-loop fit, or None if it fails."""
    # θ̇ from θ (the lag-free centred derivative): a differenced velocity's noise would
    # reach θ̈ amplified, and the fit with it
    smooth = [replace(seg, theta_dot=centred_derivative(seg.theta, seg.dt)) for seg in segments]
    try:
        fit = LinearDynamics(_gain_basis(segments[0].n_joints), certify=False, windows=(0.14,),
                             ridges=(1e-8, 1e-6, 1e-4)).fit(smooth, case='unknown')
    except (ValueError, np.linalg.LinAlgError):
        return None
    kp, kd = np.asarray(fit.kp_, dtype=float), np.asarray(fit.kd_, dtype=float)
    return _usable(kp, kd)


def fit_gains(segments: Sequence[Dataset]) -> Optional[Tuple[np.ndarray, np.ndarray]]:
    """
    Return the servo's gains ``(kp, kd)`` (n,) up to the common factor, or None.

    Normalised so that Kp e + Kd ė along ``segments`` (with ``theta_d``) has an RMS of 1,
    averaged over the joints. None when the fit fails, a Kp is not positive, or the newest
    share of the data (:data:`~.policy.NEWEST_SHARE`) gives other gains
    (:func:`~.controller_laws.gains_agree` within :data:`~.policy.GAIN_AGREEMENT_RTOL`).
    Both fits use only segments (and parts of the newest share) of at least
    :data:`~.policy.MIN_GAIN_SAMPLES` samples.
    """
    segments = [seg for seg in segments
                if seg.theta_d is not None and seg.n_samples >= MIN_GAIN_SAMPLES]
    half = newest_share(segments, NEWEST_SHARE, MIN_GAIN_SAMPLES)
    if not half:
        return None
    whole, half = _linear_gains(segments), _linear_gains(half)
    if whole is None or half is None:
        return None
    (kp, kd), (kp_h, kd_h) = whole, half
    if not gains_agree(kp, kd, kp_h, kd_h, GAIN_AGREEMENT_RTOL):
        return None
    e = np.vstack([seg.theta_d - seg.theta for seg in segments])
    de = np.vstack([seg.theta_d_dot - seg.theta_dot for seg in segments])
    rms = float(np.mean(np.sqrt(np.mean(pd_torque(kp, kd, e, de) ** 2, axis=0))))
    if not rms > 0.0:
        return None
    return kp / rms, kd / rms


class Start(NamedTuple):
    """A start genome of a case-3 search, its rollout cost J and what it is."""

    genome: np.ndarray
    cost: float
    origin: str


def search_gains(evo: Evolution) -> Optional[Tuple[np.ndarray, np.ndarray]]:
    """
    Return the linear PD gains ``(kp, kd)`` of the best genome of a case-3 search, or None.

    None when the search has no linear torque network or a Kp is not positive and finite.
    """
    spec = evo.spec
    if spec.case != 'unknown' or not spec.torque_linear:
        return None
    params = decode(spec, np.asarray(evo.optimizer.best_x, dtype=float)[None], evo.scales)
    return _usable(params.kp[0], params.kd[0])


def start_genome(evo: Evolution, train: Sequence[Dataset], budget_s: float,
                 nfev: int, gains=None) -> Optional[Start]:
    """
    Return a case-3 start genome for ``evo`` (a case-3 search), or None.

    ``gains`` ``(kp, kd)`` (default: those of :func:`fit_gains`), the arm's blocks by the
    equation-error fit of the case-2 network with them (within ``budget_s`` real seconds
    and ``nfev`` evaluations), the torque network's linear gains set to them and its RBF
    units to zero weight. None also when its rollout on ``train`` diverges.
    """
    spec = evo.spec
    if is_global(spec):  # its own start is the closed-form fit of arm and servo together
        return None
    what = 'the linearly identified gains' if gains is None else "the search's gains"
    if gains is None:
        gains = fit_gains(train) if spec.case == 'unknown' and spec.torque_linear else None
    if gains is None:
        return None
    kp, kd = gains
    arm = replace(spec, case='pd_gains')
    shared = {b.name: b for b in arm.blocks()}
    start = np.zeros(arm.genome_size)
    blocks = {b.name: b for b in spec.blocks()}
    for name, block in shared.items():
        start[block.start:block.stop] = evo.optimizer.best_x[
            blocks[name].start:blocks[name].stop]
    t0 = time.perf_counter()
    fitted, _ = refine_equation_error(arm, list(train), evo.scales, start, kp, kd,
                                      max_nfev=nfev, deadline=t0 + budget_s)
    genome = spec.initial_genome()
    for name, block in shared.items():
        genome[blocks[name].start:blocks[name].stop] = fitted[block.start:block.stop]
    for name in ('p_net', 'd_net'):
        if name in blocks:
            net = genome[blocks[name].start:blocks[name].stop].reshape(blocks[name].shape)
            net[2] = 0.0  # the RBF units start at zero weight
    s = evo.scales
    linear = genome[blocks['pd_linear'].start:blocks['pd_linear'].stop].reshape(2, -1)
    linear[0] = kp * s.error / s.torque
    linear[1] = kd * s.error_rate / s.torque
    cost = float(evo.problem.cost(genome[None])[0])
    if not np.isfinite(cost):
        return None
    return Start(genome, cost, f'{what} and the equation-error fit '
                               f'({time.perf_counter() - t0:.1f} s, J {cost:.4g}; Kp ratios '
                               f'{np.round(kp / kp.mean(), 3).tolist()})')


class ArmKeeper:
    """
    Case 3's linear closed loop over the refreshes of the data (module docstring).

    ``loop`` is the :class:`~rkgnn_ros.core.fitting.trig_loop.TrigLoop` that predicts (None:
    the search's model predicts) and ``time`` the stamp (s) its law's integral term refers
    to: moved on to the newest data at every call, so a prediction only adds the error
    integral of the last moments (the self-check's record reaches back only so far).
    """

    def __init__(self):
        self.loop: Optional[TrigLoop] = None
        self.time = math.nan
        self._tried = -math.inf
        self._failures = 0  # fits in a row that did not hold

    @property
    def tried(self) -> bool:
        """Return True once a fit was attempted; it holds when :attr:`loop` is set."""
        return self._tried > -math.inf

    def fit(self, segments: Sequence[Dataset], validation_fraction: float, origin: float,
            now: float, prior=None) -> Tuple[bool, Optional[Tuple[str, str]]]:
        """
        Fit on ``segments`` (``origin``: the stamp of their t = 0) if due at clock ``now``.

        Due :data:`REFIT_S` after the last fit while the loop holds, :data:`RETRY_S` after a
        fit that did not hold (once the data span :data:`YOUNG_DATA_S`, doubling with each
        further one, at most :data:`RETRY_MAX_S`), and at every call while the data are too
        few to try. Between
        fits the law's integral term is moved on to the data's end. Returns whether the loop
        changed (fitted or moved on), and the (level, text) to log when whether it predicts
        changed. ``prior``: the excitation memory's samples of the closed loop, fitted beside
        the window (:func:`~rkgnn_ros.core.fitting.trig_loop.fit_closed_trig_loop`).
        """
        segments = [seg for seg in segments if seg.theta_d is not None]
        if not segments:
            return False, None
        young = data_span(segments) < YOUNG_DATA_S
        wait = REFIT_S if self.loop is not None else retry_wait(
            self._failures, young, RETRY_S, RETRY_MAX_S)
        if now - self._tried < wait:
            return self._advance(segments, origin), None
        samples = sum(seg.n_samples for seg in segments) * (1.0 - validation_fraction)
        if self.loop is None and samples < MIN_LOOP_SAMPLES:
            return False, None
        self._tried = now
        before = self.loop is not None
        loop = fit_closed_trig_loop(segments, validation_fraction, MIN_LOOP_SAMPLES, prior)
        why = 'too few samples or a failed fit'
        if loop is not None and not loop.torque_error <= MAX_LOOP_ERROR:
            why = f'held-out equation error {loop.torque_error:.1%}'
            loop = None
        if loop is None and before:
            error = closed_loop_error(self.loop, segments, validation_fraction)
            if still_holds(error, MAX_LOOP_ERROR):
                self._failures = 0
                return self._advance(segments, origin), None
            why += f'; the loop in use {error:.1%}'
        self.loop = loop
        self._failures = 0 if loop is not None else self._failures + 1
        if loop is not None:
            self.time = origin + float(segments[-1].t[-1])
            if not before:
                law = loop.law
                return True, ('info', 'predictions roll out the closed loop fitted linearly on '
                              'the trigonometric basis (held-out equation error '
                              f'{loop.torque_error:.2%}; servo Kp ratios '
                              f'{np.round(law.kp / law.kp.mean(), 3).tolist()}, Ki/Kp '
                              f'{np.round(law.ki / law.kp, 3).tolist()} 1/s); ~/model stays '
                              "the search's model")
        elif before:
            return True, ('info', f"predictions go back to the search's model ({why} of the "
                          'linear closed loop)')
        return True, None

    def _advance(self, segments: Sequence[Dataset], origin: float) -> bool:
        """Move the law's integral term on to the end of ``segments``; return whether it did."""
        end = origin + float(segments[-1].t[-1])
        if self.loop is None or not end > self.time:
            return False
        law = self.loop.law
        if np.any(law.ki != 0.0):
            for seg in segments:
                t = origin + seg.t
                keep = (t > self.time) & (t <= end)
                if np.any(keep):
                    law = law.advance_integral(seg.theta[keep], seg.theta_d[keep], seg.dt)
            self.loop = self.loop.with_law(law)
        self.time = end
        return True

    def close(self, model) -> Optional[PredictionLoop]:
        """
        Return ``model`` with the linear closed loop for prediction (None: there is none).

        ``model`` may be None: the loop predicts before the search has published a model.
        """
        if self.loop is None or (model is not None and model.n_joints != self.loop.n_joints):
            return None
        return PredictionLoop(model, self.loop, self.time)

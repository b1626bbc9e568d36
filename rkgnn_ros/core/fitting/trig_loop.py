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
The global predictor of cases 1 and 3: the arm on the trigonometric basis, closed loop.

The RBF model the online search evolves holds near the path it was fitted on and needs
many generations to get there; on a servo with noisy encoders it stayed worse than
following the reference for a whole minute (``bench/online_servos.py``). With the torque
measured, the arm's M, V, G, F on the tied trigonometric basis of a planar arm
(:class:`~rkgnn_ros.core.fitting.linear.LinearDynamics`, what the feed-forward uses) are
one least-squares fit of the buffered samples, a tenth of a second, and global.
:func:`fit_trig_loop` fits it and closes it with the servo law learned from the same data;
:class:`TrigLoop` rolls that loop out with the compiled Runge-Kutta-Gill stage update
(:func:`~rkgnn_ros.core.integration.rkg.gill_stage`), so a 2 s prediction costs well
under a millisecond instead of the ~80 ms of the numpy model.

Case 3 (no torque, :func:`fit_closed_trig_loop`) has no torque to fit the arm to, but
the closed loop M θ̈ + V + G + F = Kp e + Kd ė + Ki ∫e + c is linear in the arm's
coefficients and the servo's gains together, up to one common factor
(:class:`LinearDynamics`, case 'unknown' with ``integral``): one least-squares fit gives
the arm and its servo (a PID or, with Ki fitted to zero, a PD; a gravity compensation is
absorbed by G), globally. θ̇ in that fit is the centred derivative of θ, so a differenced
velocity's noise does not reach θ̈.

The law's command-only terms shift θd (:meth:`ControllerLaw.shift`). Its θ-terms on the
measured θ (a gravity compensation, on :class:`TrigFeatures`) are evaluated in the compiled
rollout at every stage. Its integral term depends on the motion and is found by Picard
iteration: each pass rolls out with it grown along the previous pass (the first along the
plan), as :class:`~rkgnn_ros.core.fitting.controller.ClosedLoop` does; so are θ-terms on
another basis. It has the interface of that class (``law`` and ``simulate``), so
the predictor rolls either out alike.
"""

import copy
import dataclasses
import math
from typing import Optional, Sequence

from numba import njit
import numpy as np

from .controller_laws import ControllerLaw, TrigFeatures
from .law_loop import LawLoop, MAX_SUBSTEPS, PASSES
from .linear import LinearDynamics, Samples, samples_from_datasets
from .policy import INTEGRAL_GAIN, INTEGRAL_MIN_ERROR, LOOP_KI_ZERO, MIN_SEGMENT_SAMPLES
from .torque_check import paired_torques, torque_error
from .validation import split_validation
from ..data import Dataset
from ..differentiate import centred_derivative
from ..integration.rkg import gill_node, gill_stage
from ..model.trig import TrigBasis
from ..model.trig_dynamics import regressor
from ..servo_law import compiled_pd_torque, pd_torque

__all__ = ['MAX_SUBSTEPS', 'PASSES', 'TrigLoop', 'closed_loop_error', 'data_span',
           'fit_closed_trig_loop', 'fit_trig_loop', 'precompile_trig_loop', 'trig_torque_error']

#: A state component beyond this magnitude ends a rollout as diverged.
DIVERGED = 1e6


@njit(cache=True, nogil=True)
def _rates(x, u, n, freq, kinds, w_mass, w_pot, viscous, coulomb, vc, kp, kd, law_codes,
           law_w, phi, grad, law_phi, m, dm, trig, rate):
    """
    Write ẋ of the closed loop into ``rate``; return False where M is not positive.

    ``w_mass`` (n, n, F) and ``grad`` (n, F) have the features last, so the sums over them
    run along contiguous memory.
    """
    nf = kinds.shape[0]
    for j in range(n):
        trig[0, j] = math.cos(x[j])
        trig[1, j] = math.sin(x[j])
    for f in range(nf):
        # cos and sin of Σ_j k_j θ_j from those of θ_j (the basis' k_j are integers): a
        # product of unit complex numbers, no further cos or sin
        re, im = 1.0, 0.0
        for j in range(n):
            k = freq[f, j]
            c, s = trig[0, j], (trig[1, j] if k > 0.0 else -trig[1, j])
            for _ in range(int(abs(k))):
                re, im = re * c - im * s, re * s + im * c
        if kinds[f] == 1:
            value, slope = im, re
        else:
            value, slope = re, -im
        phi[f] = value
        for k in range(n):
            grad[k, f] = slope * freq[f, k]
    # M and ∂M/∂θ_k are symmetric (so are the weights): the upper triangle, mirrored
    for i in range(n):
        for j in range(i, n):
            acc = 0.0
            for f in range(nf):
                acc += phi[f] * w_mass[i, j, f]
            m[i, j] = acc
            m[j, i] = acc
            for k in range(n):
                acc = 0.0
                for f in range(nf):
                    acc += grad[k, f] * w_mass[i, j, f]
                dm[k, i, j] = acc
                dm[k, j, i] = acc
    # the law's θ-terms on the measured θ: W φ(θ), φ products of (1, cos θ_j, sin θ_j)
    nl = law_codes.shape[0]
    for f in range(nl):
        product = 1.0
        for j in range(n):
            code = law_codes[f, j]
            if code:
                product *= trig[code - 1, j]
        law_phi[f] = product
    for i in range(n):
        qd = x[n + i]
        v = 0.0
        for j in range(n):
            for k in range(n):
                v += (dm[k, i, j] - 0.5 * dm[i, j, k]) * x[n + k] * x[n + j]
        g = 0.0
        for f in range(nf):
            g += grad[i, f] * w_pot[f]
        tau = compiled_pd_torque(kp[i], kd[i], u[i] - x[i], u[n + i] - qd)
        for f in range(nl):
            tau += law_w[i, f] * law_phi[f]
        rate[n + i] = tau - v - g - viscous[i] * qd - coulomb[i] * math.tanh(qd / vc)
        rate[i] = qd
    # solve M a = rhs in place by Cholesky (M symmetric positive definite, else stop)
    for j in range(n):
        s = m[j, j]
        for k in range(j):
            s -= m[j, k] * m[j, k]
        if not s > 0.0:
            return False
        m[j, j] = math.sqrt(s)
        for i in range(j + 1, n):
            s = m[i, j]
            for k in range(j):
                s -= m[i, k] * m[j, k]
            m[i, j] = s / m[j, j]
    for i in range(n):
        s = rate[n + i]
        for k in range(i):
            s -= m[i, k] * rate[n + k]
        rate[n + i] = s / m[i, i]
    for i in range(n - 1, -1, -1):
        s = rate[n + i]
        for k in range(i + 1, n):
            s -= m[k, i] * rate[n + k]
        rate[n + i] = s / m[i, i]
    return True


@njit(cache=True, nogil=True)
def _rollout(x0, u, h, n, freq, kinds, w_mass, w_pot, viscous, coulomb, vc, kp, kd,
             law_codes, law_w, out):
    """Roll out over ``u`` (K-1, substeps, 3, 2n) into ``out`` (K, 2n); NaN after divergence."""
    nf = kinds.shape[0]
    phi, grad = np.empty(nf), np.empty((n, nf))
    law_phi = np.empty(law_codes.shape[0])
    m, dm, trig = np.empty((n, n)), np.empty((n, n, n)), np.empty((2, n))
    x, xs = x0.copy(), np.empty(2 * n)
    rate, q = np.empty(2 * n), np.zeros(2 * n)
    out[0] = x
    for i in range(u.shape[0]):
        for stages in u[i]:             # the substeps of interval i
            xs[:] = x
            for stage in range(4):
                if not _rates(xs, stages[gill_node(stage)], n, freq, kinds, w_mass, w_pot,
                              viscous, coulomb, vc, kp, kd, law_codes, law_w, phi, grad,
                              law_phi, m, dm, trig, rate):
                    return
                gill_stage(stage, h, x, xs, rate, q)
        for j in range(2 * n):
            if not abs(x[j]) <= DIVERGED:
                return
        out[i + 1] = x


def _law_terms(law: ControllerLaw, n: int):
    """
    Return the law's θ-terms on the measured θ as the kernel takes them, or None.

    ``codes`` (F, n): per feature and joint 0 (no factor), 1 (cos θ_j) or 2 (sin θ_j);
    ``weights`` (n, F): W. None when the law has such terms on another basis (rolled out by
    passes along the previous pass instead); empty arrays when it has none.
    """
    if law.theta_input != 'measured' or not law.theta_weights.size:
        return np.zeros((0, n), dtype=np.int64), np.zeros((n, 0))
    if not isinstance(law.features, TrigFeatures):
        return None
    codes = np.zeros((len(law.features.terms), n), dtype=np.int64)
    for f, term in enumerate(law.features.terms):
        for joint, kind in term:
            codes[f, joint] = 1 + kind
    return codes, np.ascontiguousarray(law.theta_weights, dtype=float)


class TrigLoop(LawLoop):
    """
    A fitted :class:`LinearDynamics` arm closed with a :class:`ControllerLaw`.

    Attributes
    ----------
    arm : LinearDynamics
        The arm (case 'torque': M, V, G, F in N m).
    law : ControllerLaw
        The servo's law (Kp > 0 on every joint).
    substeps : int or None
        RKG steps per sampling interval of a rollout; None (default): from the closed
        loop's stiffness at each rollout's start (half the stability limit), at most
        :data:`MAX_SUBSTEPS`.

    """

    def __init__(self, arm: LinearDynamics, law: ControllerLaw,
                 substeps: Optional[int] = None):
        super().__init__(arm, law, substeps)
        self._stiff = copy.copy(arm)          # the arm with the law's gains: its stiffness
        self._stiff.kp_, self._stiff.kd_ = np.asarray(law.kp), np.asarray(law.kd)
        basis = arm.basis
        self._freq = np.ascontiguousarray(basis.frequencies, dtype=float)
        self._kinds = np.ascontiguousarray(basis.kinds, dtype=np.int64)
        # (n, n, F): the features last, as the kernel sums over them
        self._w_mass = np.ascontiguousarray(np.transpose(arm._w_mass, (1, 2, 0)), dtype=float)
        self._w_pot = np.ascontiguousarray(arm._w_pot, dtype=float)
        self._viscous = np.asarray(arm.viscous_, dtype=float)
        self._coulomb = np.asarray(arm.coulomb_, dtype=float)
        self._kp = np.asarray(law.kp, dtype=float)
        self._kd = np.asarray(law.kd, dtype=float)
        self._set_law_terms()

    def _set_law_terms(self) -> None:
        terms = _law_terms(self.law, self.arm.n_joints)
        #: whether the law's θ-terms on θ are in the compiled rollout (else by passes)
        self._terms_compiled = terms is not None
        n = self.arm.n_joints
        self._law_codes, self._law_w = terms if terms is not None else (
            np.zeros((0, n), dtype=np.int64), np.zeros((n, 0)))

    def _once(self, x0, t, theta_d, theta_d_dot) -> np.ndarray:
        n, dt, substeps, u = self._inputs(x0, t, theta_d, theta_d_dot)
        out = np.full((t.size, 2 * n), np.nan)
        h = dt / substeps
        _rollout(np.asarray(x0, dtype=float), np.ascontiguousarray(u), h, n, self._freq,
                 self._kinds, self._w_mass, self._w_pot, self._viscous, self._coulomb,
                 float(self.arm.coulomb_velocity), self._kp, self._kd, self._law_codes,
                 self._law_w, out)
        return out

    def _stiffness_at(self, theta) -> float:
        return self._stiff.stiffness(theta)


def fit_trig_loop(train: Sequence[Dataset], validation: Sequence[Dataset],
                  law: ControllerLaw, min_samples: int = 200,
                  prior: Optional[Samples] = None) -> Optional[TrigLoop]:
    """
    Return the trigonometric arm fitted on ``train`` (case 1) closed with ``law``.

    The arm's held-out torque error (:func:`trig_torque_error`: the
    :func:`~rkgnn_ros.core.fitting.torque_check.torque_error` of its inverse dynamics on
    ``validation``, worst joint; inf without validation samples, or when it cannot be
    computed) is kept in :attr:`TrigLoop.torque_error`: the caller decides
    whether the basis holds this arm (it is a planar arm's). ``prior``: samples fitted
    beside ``train`` (the excitation memory's). None when ``train`` holds fewer than
    ``min_samples`` samples or the fit fails.
    """
    if law is None or not np.all(law.kp > 0.0):
        return None
    train = [seg for seg in train if seg.n_samples >= 5 and seg.tau is not None]
    if sum(seg.n_samples for seg in train) < min_samples:
        return None
    basis = TrigBasis(train[0].n_joints, planar=True, tied=True)
    try:
        arm = LinearDynamics(basis, certify=False).fit(train, 'torque', prior=prior)
    except (ValueError, np.linalg.LinAlgError):
        return None
    loop = TrigLoop(arm, law)
    loop.torque_error = trig_torque_error(loop, validation)
    return loop


def trig_torque_error(loop: TrigLoop, validation: Sequence[Dataset]) -> float:
    """
    Return ``loop``'s arm's torque error on ``validation`` (worst joint; inf: no samples).

    The figure :func:`fit_trig_loop` keeps in :attr:`TrigLoop.torque_error`; the keepers
    score a loop in use on newer data with it. Inf too when it cannot be computed or is not
    finite.
    """
    try:
        predicted, reference = paired_torques(loop.arm, [seg for seg in validation
                                                         if seg.tau is not None])
    except (ValueError, np.linalg.LinAlgError):
        return math.inf
    if not predicted.shape[0]:
        return math.inf
    error = float(np.max(torque_error(predicted, reference)))
    return error if math.isfinite(error) else math.inf


def fit_closed_trig_loop(segments: Sequence[Dataset], validation_fraction: float,
                         min_samples: int = 200,
                         prior: Optional[Samples] = None) -> Optional[TrigLoop]:
    """
    Return case 3's arm and servo fitted together on ``segments`` (module docstring).

    ``segments`` (oldest first, with ``theta_d``, ``theta_d_dot``) are split as the search's
    data (:func:`~rkgnn_ros.core.fitting.validation.split_validation`); the fit uses the
    older part and :attr:`TrigLoop.torque_error` is the newer part's closed-loop equation
    error: RMS of M θ̈ + V + G + F minus the servo's torque over the servo torque's standard
    deviation, worst joint. Two forms are fitted, a PD servo and a PID with a constant
    (Ki ∫e + c); the PID is kept only where it explains the held-out data clearly better
    (:data:`~.policy.INTEGRAL_GAIN` times smaller error, from a PD error above
    :data:`~.policy.INTEGRAL_MIN_ERROR`): over a limited range of motion c trades with the slow
    gravity terms, which would leave the closed loop right and the arm's torque wrong. The
    law's integral term holds at the end of ``segments``; ∫e runs on from one segment to the
    next (a gap adds nothing to it). ``prior``: older samples of the closed loop (the
    excitation memory's, with θ̇ the centred derivative and the tracking errors) fitted
    beside the PD form's training data; the PID form, whose ∫e they lack, fits without.
    None with fewer than ``min_samples`` training samples or when both fits fail or give a
    Kp <= 0.
    """
    segments = [_centred_velocity(seg) for seg in segments
                if seg.theta_d is not None and seg.theta_d_dot is not None and seg.n_samples >= 5]
    train, validation, _ = split_validation(segments, validation_fraction, MIN_SEGMENT_SAMPLES)
    if sum(seg.n_samples for seg in train) < min_samples:
        return None
    pd = _closed_form(train, validation, integral=False, prior=prior)
    if pd is not None and not pd.torque_error > INTEGRAL_MIN_ERROR:
        return pd
    pid = _closed_form(train, validation, integral=True)
    if pd is None or (pid is not None and pid.torque_error < pd.torque_error / INTEGRAL_GAIN):
        return pid
    return pd


def _closed_form(train, validation, integral: bool, prior=None) -> Optional[TrigLoop]:
    """Return the PD (or PID: ``integral``) closed loop fitted on ``train``, scored after."""
    n, n_train = train[0].n_joints, sum(seg.n_samples for seg in train)
    basis = TrigBasis(n, planar=True, tied=True)
    try:
        arm = LinearDynamics(basis, certify=False, integral=integral).fit(
            train, 'unknown', prior=None if integral else prior)
        every = samples_from_datasets(train + validation, 'unknown', window=arm.window_,
                                      integral=integral)
    except (ValueError, np.linalg.LinAlgError):
        return None
    kp, kd = arm.kp_, arm.kd_
    if not (np.all(np.isfinite(arm._full_coef)) and np.all(kp > 0.0)):
        return None
    ki = bias = grown = np.zeros(n)
    if integral:
        ki, bias, grown = arm.ki_, arm.bias_, every.error_integral[-1]
    zero = ki < LOOP_KI_ZERO * kp
    law_ki = np.where(zero, 0.0, ki)
    law = ControllerLaw(
        kp=kp, kd=kd, ki=law_ki, bias=bias + np.where(zero, ki * grown, 0.0),
        integral_term=law_ki * grown, feedforward=np.zeros(n),
        theta_weights=np.zeros((n, 0)), theta_input='desired', features=None,
        fit_ratio=np.zeros(n), samples=n_train)
    loop = TrigLoop(arm, law)
    loop.torque_error = _equation_error(arm, every.take(slice(n_train, None)), integral)
    return loop


def _equation_error(arm: LinearDynamics, held: Samples, integral: bool) -> float:
    """Return the closed loop's equation error on ``held`` (worst joint; inf: no samples)."""
    if not held.n_samples:
        return math.inf
    residual = regressor(arm.basis, held.theta, held.theta_dot, held.theta_ddot,
                         arm.coulomb_velocity, held.error, held.error_rate,
                         held.error_integral) @ arm._full_coef
    servo = pd_torque(arm.kp_, arm.kd_, held.error, held.error_rate)
    if integral:
        servo = servo + arm.ki_ * held.error_integral + arm.bias_
    spread = np.maximum(servo.std(axis=0), 1e-12)
    error = float(np.max(np.sqrt(np.mean(residual ** 2, axis=0)) / spread))
    return error if math.isfinite(error) else math.inf


def closed_loop_error(loop: TrigLoop, segments: Sequence[Dataset],
                      validation_fraction: float) -> float:
    """
    Return case 3's ``loop`` scored on the newest part of ``segments`` (inf: none there).

    The figure :func:`fit_closed_trig_loop` keeps in :attr:`TrigLoop.torque_error`, for a
    loop fitted on other data: ``segments`` are split as there, and the newest part scored.
    """
    segments = [_centred_velocity(seg) for seg in segments
                if seg.theta_d is not None and seg.theta_d_dot is not None and seg.n_samples >= 5]
    train, validation, _ = split_validation(segments, validation_fraction, MIN_SEGMENT_SAMPLES)
    arm = loop.arm
    integral = arm.integral
    try:
        every = samples_from_datasets(train + validation, 'unknown', window=arm.window_,
                                      integral=integral)
    except (ValueError, np.linalg.LinAlgError):
        return math.inf
    n_train = sum(seg.n_samples for seg in train)
    return _equation_error(arm, every.take(slice(n_train, None)), integral)


def data_span(segments: Sequence[Dataset]) -> float:
    """Return the seconds the segments cover together (their gaps left out)."""
    return sum(float(seg.t[-1] - seg.t[0]) for seg in segments if seg.n_samples)


def _centred_velocity(seg: Dataset) -> Dataset:
    """Return ``seg`` with θ̇ the centred derivative of θ (lag-free; see the module)."""
    return dataclasses.replace(seg, theta_dot=centred_derivative(seg.theta, seg.dt))


def precompile_trig_loop(n_joints: int = 3) -> None:
    """Compile (or load from numba's cache) the rollout kernel, on a zero arm."""
    n = int(n_joints)
    basis = TrigBasis(n, planar=True, tied=True)
    nf = basis.n_features
    w_mass = np.zeros((n, n, nf))
    w_mass[:, :, basis.constant] = np.eye(n)
    out = np.full((3, 2 * n), np.nan)
    _rollout(np.zeros(2 * n), np.zeros((2, 1, 3, 2 * n)), 0.01, n,
             np.ascontiguousarray(basis.frequencies, dtype=float),
             np.ascontiguousarray(basis.kinds, dtype=np.int64), w_mass, np.zeros(nf),
             np.zeros(n), np.zeros(n), 0.05, np.ones(n), np.ones(n),
             np.ones((1, n), dtype=np.int64), np.zeros((n, 1)), out)

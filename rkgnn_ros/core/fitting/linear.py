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
Inverse dynamics linear in the trigonometric basis: a closed-form, global fit.

In the trigonometric basis M θ̈ + V + G + F = τ is linear in the coefficients of M, U and
the friction, τ = Y(θ, θ̇, θ̈) w (:mod:`rkgnn_ros.core.model.trig_dynamics`, which also holds
the model the coefficients make). This module fits w by least squares on measured samples.

The fit (:class:`LinearDynamics`)
---------------------------------
- θ̈ is a centred Savitzky-Golay derivative (local cubic) of the measured θ̇. Its window
  is chosen with the ridge weight on the held-out samples among 0.06-0.3 s: on clean data
  the narrowest wins (its bias on sub-hertz motion is negligible), on encoder noise of
  1e-3 rad/s a wide one (a 7-sample window puts about 0.05 rad/s² of noise on θ̈, a
  31-sample one ten times less).
- Each joint's equations are divided by that joint's RMS torque, so every joint counts
  alike; the normal equations are assembled in chunks of samples (the regressor of 20 s of
  a 6-joint arm need not be in memory at once) and solved by Cholesky.
- Ridge regularisation, per coefficient group (each M entry, or all of M when tied, U,
  each friction kind) scaled
  by the group's mean squared column, so it is a flat prior within a group whatever the
  units. The weight is chosen on held-out samples, never on the training fit: the newest
  ``validation_fraction`` of the samples is held out, every weight of ``ridges`` is fitted
  on the rest and scored there, and the best one is refitted on everything.
- Friction coefficients are constrained non-negative (the dual of the constrained least
  squares is a small non-negative least squares: exact).
- M positive definite on the whole joint range, not only along the data. With S =
  diag(M̄)^(-1/2) (M̄ the mean of M on the data) the floor is λ_min(S M S) >= ε, i.e.
  M ⪰ ε diag(M̄). Three layers: (1) a constrained refit: wherever λ_min(S M S) < ε at
  ``check_points`` random configurations over the range, the linear constraint
  vᵀ S M(θ) S v >= 2ε (v the eigenvector found there) joins the least squares, for a few
  rounds; (2) :func:`certify_inertia` proves the floor on the whole range by adaptive
  cells when their number allows (3 joints: a few hundred cells; a planar 4-joint arm
  some 10^4); it is not attempted when M depends on more than 4 joints (6-joint arms),
  where the cells needed are beyond any budget, and ``certificate_`` is then None;
  (3) the model's M (:meth:`LinearDynamics.mass_matrix`, used by the inverse and forward
  dynamics) is the fitted one raised to the floor wherever it falls short, so no
  configuration can make it singular or indefinite (``floor_active_``: the share of the
  check configurations where that guard acts).
  A global diagonal shift by the certificate's deficit was tried and rejected: where the
  certificate fails its bound is far below the true minimum, and the shift ruins M.

Case 3 (no torque, unknown PD or, with ``integral``, PID controller with a constant c):
M, V, G, F and the servo scale together, so only the ratios are identifiable. The gains
join the unknowns, Y w = Kp e + Kd ė [+ Ki ∫e + c], and one linear normalisation fixes
the scale: the mean of Kp is ``gain_normalisation`` (1 by default: every term is in "N m
per unit mean Kp"). The least squares with one linear equality stays closed form; what
the model predicts (θ, θ̇ under its own controller) does not depend on the scale, and a
known mean gain (or any one known physical quantity) gives the physical model.
"""

import time
from typing import NamedTuple, Optional, Sequence

import numpy as np
from scipy.linalg import cho_factor, LinAlgError

from .qp import solve_qp
from .warmstart import estimate_acceleration
from ..model.trig_certificate import certify_inertia
from ..model.trig_dynamics import Layout, regressor, TrigDynamics
from ..scoring import nrmse

CASES = ('torque', 'pd_gains', 'unknown')

#: Rounds of cuts that keep M positive on the check set, and cuts per round, at most.
CUT_ROUNDS, CUTS_PER_ROUND = 20, 48


# ----------------------------------------------------------------------------- samples

class Samples(NamedTuple):
    """
    Joint samples an equation-error fit uses, in time order (arrays of shape (N, n)).

    ``tau`` is the torque to explain (measured in case 1, computed from the known gains in
    case 2, None in case 3); ``error`` and ``error_rate`` are θd - θ and θ̇d - θ̇ (case 3),
    ``error_integral`` ∫(θd - θ) dt from the first sample on (case 3 with an integral).
    """

    theta: np.ndarray
    theta_dot: np.ndarray
    theta_ddot: np.ndarray
    tau: Optional[np.ndarray] = None
    error: Optional[np.ndarray] = None
    error_rate: Optional[np.ndarray] = None
    error_integral: Optional[np.ndarray] = None

    @property
    def n_samples(self) -> int:
        """Return the number of samples N."""
        return self.theta.shape[0]

    def take(self, index) -> 'Samples':
        """Return the samples at ``index`` (a slice, mask or integer array)."""
        return Samples(*(None if a is None else a[index] for a in self))

    @staticmethod
    def concatenate(parts: Sequence['Samples']) -> 'Samples':
        """Join samples end to end (the fields must be present in all parts or none)."""
        fields = []
        for k in range(len(Samples._fields)):
            arrays = [p[k] for p in parts]
            fields.append(None if any(a is None for a in arrays) else np.vstack(arrays))
        return Samples(*fields)


def default_window(dt: float) -> int:
    """Return the Savitzky-Golay window for θ̈: odd, about 0.06 s, at least 5 samples."""
    return max(5, 2 * int(round(0.03 / dt)) + 1)


def samples_from_datasets(datasets, case: str, kp=None, kd=None,
                          window: Optional[int] = None, integral: bool = False) -> Samples:
    """
    Return the :class:`Samples` of one or more datasets, θ̈ by Savitzky-Golay.

    Parameters
    ----------
    datasets : Dataset or sequence of Dataset
        Time-ordered segments.
    case : {'torque', 'pd_gains', 'unknown'}
        What is known about the torque.
    kp, kd : array_like, shape (n,), optional
        The known diagonal gains (case 'pd_gains').
    window : int, optional
        Savitzky-Golay window (samples); :func:`default_window` by default.
    integral : bool
        Case 'unknown': add ∫(θd - θ) dt (trapezoid), running on from one dataset to the
        next (a gap adds nothing to it).

    """
    if case not in CASES:
        raise ValueError(f'case must be one of {CASES}, got {case!r}')
    if not isinstance(datasets, (list, tuple)):
        datasets = [datasets]
    parts = []
    carried = 0.0
    for d in datasets:
        acc = estimate_acceleration(d.theta_dot, d.dt, window or default_window(d.dt), 3)
        tau = err = derr = None
        if case == 'torque':
            if d.tau is None:
                raise ValueError("case 'torque' needs measured torque (Dataset.tau)")
            tau = d.tau
        else:
            if d.theta_d is None or d.theta_d_dot is None:
                raise ValueError(f'case {case!r} needs the desired trajectory')
            err, derr = d.theta_d - d.theta, d.theta_d_dot - d.theta_dot
            if case == 'pd_gains':
                if kp is None or kd is None:
                    raise ValueError("case 'pd_gains' needs kp and kd")
                tau = np.asarray(kp, dtype=float) * err + np.asarray(kd, dtype=float) * derr
                err = derr = None
        grown = None
        if integral and case == 'unknown':
            grown = np.zeros_like(err)
            grown[1:] = np.cumsum(0.5 * (err[1:] + err[:-1]), axis=0) * d.dt
            grown += carried
            carried = grown[-1]
        parts.append(Samples(d.theta, d.theta_dot, acc, tau, err, derr, grown))
    return Samples.concatenate(parts)


# ----------------------------------------------------------------------------- solving

class _Normal(NamedTuple):
    """Normal equations of a weighted least-squares problem: G = AᵀA, b = Aᵀy, c = yᵀy."""

    gram: np.ndarray
    rhs: np.ndarray
    energy: float
    rows: int


def _normal_equations(basis, samples: Samples, weights, coulomb_velocity, stride=1,
                      chunk_bytes=48e6) -> _Normal:
    """Assemble the weighted normal equations of ``samples`` chunk by chunk."""
    n = basis.n_joints
    controller = samples.tau is None
    p = Layout.of(basis, controller, samples.error_integral is not None).size
    gram = np.zeros((p, p))
    rhs = np.zeros(p)
    energy, rows = 0.0, 0
    index = np.arange(0, samples.n_samples, stride)
    step = max(1, int(chunk_bytes // (8 * n * p)))
    for s in range(0, index.size, step):
        part = samples.take(index[s:s + step])
        y = regressor(basis, part.theta, part.theta_dot, part.theta_ddot, coulomb_velocity,
                      part.error, part.error_rate, part.error_integral)
        y *= weights[None, :, None]
        a = y.reshape(-1, p)
        gram += a.T @ a
        if not controller:
            target = (part.tau * weights).reshape(-1)
            rhs += a.T @ target
            energy += float(target @ target)
        rows += a.shape[0]
    return _Normal(gram, rhs, energy, rows)


def _spread(points, order, count, distance=0.3):
    """
    Return up to ``count`` of ``points[order]``, in that order, at least ``distance`` apart.

    Distances are the largest wrapped angle difference over the joints, so cuts at nearly
    the same configuration (which add nothing but work) are skipped.
    """
    chosen = []
    for k in order:
        if chosen:
            diff = np.abs(points[chosen] - points[k])
            diff = np.minimum(diff, 2.0 * np.pi - diff).max(axis=1)
            if diff.min() < distance:
                continue
        chosen.append(k)
        if len(chosen) == count:
            break
    return chosen


class LinearSettings(NamedTuple):
    """The settings of :class:`LinearDynamics` beyond its basis (see there)."""

    ridges: Sequence[float] = tuple(10.0 ** np.arange(-12, 0))
    validation_fraction: float = 0.2
    windows: Sequence[float] = (0.06, 0.1, 0.14, 0.2, 0.3)
    window: Optional[int] = None
    stride: int = 1
    min_eigenvalue: Optional[float] = None
    joint_lower: object = None
    joint_upper: object = None
    certify: bool = True
    check_points: int = 20_000
    max_cells: int = 50_000
    max_certified_joints: int = 4
    gain_normalisation: float = 1.0
    integral: bool = False


class LinearDynamics(TrigDynamics):
    """
    M, V, G, F of an n-joint arm in the trigonometric basis, fitted by linear least squares.

    The estimator pattern: the constructor stores settings, :meth:`fit` learns the
    coefficients and returns ``self``; the model methods (those of
    :class:`~rkgnn_ros.core.model.trig_dynamics.TrigDynamics`) refuse before a fit. See the
    module docstring for the method.

    Parameters
    ----------
    basis, coulomb_velocity
        As for :class:`~rkgnn_ros.core.model.trig_dynamics.TrigDynamics`.
    ridges : sequence of float
        Candidate ridge weights (relative to each group's mean squared column).
    validation_fraction : float
        Newest share of the samples held out to choose the ridge weight.
    windows : sequence of float
        Candidate Savitzky-Golay windows for θ̈ (s); the one with the smallest held-out
        error is kept (wider ones average encoder noise out, narrower ones follow fast
        motion).
    window : int, optional
        A fixed window (samples) instead of choosing among ``windows``.
    stride : int
        Use every ``stride``-th sample (thinning: neighbouring samples at 100 Hz carry
        nearly the same information).
    min_eigenvalue : float, optional
        The floor ε enforced for λ_min(S M S) over the joint range, S = diag(M̄)^(-1/2)
        (M̄ the mean of M on the data), i.e. M ⪰ ε diag(M̄); default a tenth of the
        smallest λ_min(S M S) on the training samples.
    joint_lower, joint_upper : array_like, shape (n,), optional
        The joint range M must be positive on (default: the whole torus).
    certify : bool
        Enforce M's positive definiteness on the range after the fit (constrained refit
        on ``check_points`` random configurations, then :func:`certify_inertia`).
    check_points : int
        Random configurations over the range where the floor is enforced.
    max_cells : int
        Cell budget of the certificate (0: no certificate).
    max_certified_joints : int
        Attempt the certificate only when M depends on at most this many joints (the cells
        it needs grow like (1/r)^d: about 10^4 for d = 3 and beyond any budget for d = 5).
    gain_normalisation : float
        Case 3: the mean of the identified Kp (fixes the unidentifiable scale).
    integral : bool
        Case 3: the controller is a PID, Kp e + Kd ė + Ki ∫e + c (``ki_``, ``bias_``).

    """

    def __init__(self, basis, coulomb_velocity: float = 0.05, **options):
        settings = LinearSettings(**options)
        ridges, validation_fraction = settings.ridges, settings.validation_fraction
        super().__init__(basis, coulomb_velocity)
        self.ridges = tuple(float(r) for r in ridges)
        if not self.ridges or min(self.ridges) < 0.0:
            raise ValueError('ridges must be non-negative and not empty')
        if not 0.0 < validation_fraction < 1.0:
            raise ValueError(f'validation_fraction must be in (0, 1), got {validation_fraction}')
        self.validation_fraction = float(validation_fraction)
        self.windows = tuple(float(w) for w in settings.windows)
        self.window = settings.window
        self.stride = int(settings.stride)
        self.min_eigenvalue = settings.min_eigenvalue
        self.joint_lower = settings.joint_lower
        self.joint_upper = settings.joint_upper
        self.certify = bool(settings.certify)
        self.gain_normalisation = float(settings.gain_normalisation)
        self.integral = bool(settings.integral)
        self.check_points = int(settings.check_points)
        self.max_cells = int(settings.max_cells)
        self.max_certified_joints = int(settings.max_certified_joints)

    @classmethod
    def from_coefficients(cls, basis, coefficients, coulomb_velocity: float = 0.05, kp=None,
                          kd=None, **settings) -> 'LinearDynamics':
        """
        Return a model with given coefficients (no fit, no floor on M).

        Parameters
        ----------
        basis : TrigBasis or int
            The basis.
        coefficients : array_like, shape (P,)
            [M entries | U | f_v | f_c] in the order of :class:`Layout`.
        coulomb_velocity : float
            v_c of the Coulomb friction.
        kp, kd : array_like, shape (n,), optional
            Gains of a known PD controller (closed-loop rollouts).
        **settings
            Other constructor settings.

        """
        model = cls(basis, coulomb_velocity, **settings)
        lay = Layout.of(model.basis)
        coef = np.asarray(coefficients, dtype=float)
        if coef.shape != (lay.size,):
            raise ValueError(f'coefficients must have shape ({lay.size},), got {coef.shape}')
        model._set(coef, lay, 'torque' if kp is None else 'pd_gains', kp, kd)
        model.inertia_scale_, model.min_eigenvalue_ = None, 0.0
        model.certificate_, model.cuts_, model.floor_active_ = None, 0, None
        return model

    # ----- fitting
    def fit(self, datasets, case: str = 'torque', kp=None, kd=None,
            prior: Optional[Samples] = None,
            deadline: Optional[float] = None) -> 'LinearDynamics':
        """
        Fit to one or more datasets (see :func:`samples_from_datasets`); returns ``self``.

        Case 'pd_gains' keeps ``kp``, ``kd`` for closed-loop rollouts; case 'unknown'
        identifies them (normalised, see the module docstring). The Savitzky-Golay window
        of θ̈ is chosen with the ridge weight on the held-out samples, among ``windows``
        (or fixed by ``window``). ``prior``: samples with θ̈ already estimated (an
        :class:`~.memory.ExcitationMemory`'s) fitted beside the datasets, as older ones.
        Past ``deadline`` (a ``time.perf_counter()`` value) no further window is tried and
        the rounds that keep M positive stop (``late_`` True, no certificate).
        """
        self._deadline = deadline
        if not isinstance(datasets, (list, tuple)):
            datasets = [datasets]
        if self.window is not None:
            windows = [int(self.window)]
        else:
            dt = datasets[0].dt
            windows = sorted({max(5, 2 * int(round(0.5 * w / dt)) + 1) for w in self.windows})
        candidates = [samples_from_datasets(datasets, case, kp, kd, w, self.integral)
                      for w in windows]
        if prior is not None:  # older samples (a memory's): never among the held-out newest
            candidates = [Samples.concatenate([prior, c]) for c in candidates]
        self._fit(candidates, windows, case, kp, kd)
        return self

    def fit_samples(self, samples: Samples, case: str = 'torque', kp=None,
                    kd=None) -> 'LinearDynamics':
        """Fit to :class:`Samples` (θ̈ already estimated); returns ``self``."""
        self._deadline = None
        self._fit([samples], [None], case, kp, kd)
        return self

    def _fit(self, candidates, windows, case, kp, kd):
        """Choose (window, ridge) on the newest samples, refit on all, enforce M > 0."""
        if case not in CASES:
            raise ValueError(f'case must be one of {CASES}, got {case!r}')
        n = self.n_joints
        first = candidates[0]
        if first.theta.shape[1] != n:
            raise ValueError(f'samples have {first.theta.shape[1]} joints, the basis {n}')
        controller = case == 'unknown'
        if controller and (first.error is None or first.error_rate is None):
            raise ValueError("case 'unknown' needs the tracking errors (Samples.error)")
        if not controller and first.tau is None:
            raise ValueError(f'case {case!r} needs the torque to explain (Samples.tau)')
        if controller:
            candidates = [c._replace(tau=None) for c in candidates]
        lay = Layout.of(self.basis, controller, first.error_integral is not None)
        n_val = int(round(self.validation_fraction * first.n_samples))
        if n_val < 1 or first.n_samples - n_val < 1:
            raise ValueError(f'too few samples ({first.n_samples}) to hold some out')

        def split(samples):
            cut = samples.n_samples - n_val
            return samples.take(slice(0, cut)), samples.take(slice(cut, None))

        if controller:
            # the joints' equations are weighted by their torque, which is not measured:
            # a first thinned fit with unit weights estimates it
            guess = self._solve_path(*split(candidates[len(candidates) // 2]), np.ones(n),
                                     lay, stride=4)
            weights = 1.0 / self._controller_rms(first, guess[0], lay)
        else:
            rms = np.sqrt(np.mean(np.square(first.tau), axis=0))
            weights = 1.0 / np.maximum(rms, 1e-6 * max(rms.max(), 1e-300))
        best = None
        for samples, window in zip(candidates, windows):
            if best is not None and self._late():
                break
            path = self._solve_path(*split(samples), weights, lay, self.stride)
            score = min(e for _, e in path[2])
            if best is None or score < best[0]:
                best = (score, window, samples, path)
        _, window, samples, (coef, ridge, scores, normal, scale, chol) = best
        self.weights_ = weights
        self.window_ = window
        self.ridge_ = ridge
        self.validation_ = scores
        self._scaled_gram = (normal, scale)
        self._set(coef, lay, case, kp, kd)
        self.inertia_scale_ = None
        self.min_eigenvalue_ = 0.0
        self.certificate_ = None
        self.cuts_ = 0
        self.late_ = False
        self.floor_active_ = None
        if self.certify:
            self._enforce_positive(samples, chol, normal, scale, lay, case, kp, kd)

    def _controller_rms(self, samples, coef, lay):
        tau = coef[lay.kp] * samples.error + coef[lay.kd] * samples.error_rate
        if lay.ki is not None:
            tau = tau + coef[lay.ki] * samples.error_integral + coef[lay.bias]
        rms = np.sqrt(np.mean(np.square(tau), axis=0))
        return np.maximum(rms, 1e-6 * max(float(rms.max()), 1e-300))

    def _constraints(self, lay, scale, cuts):
        """Rows (scaled) and right-hand sides: friction >= 0, cuts, case 3 normalisation."""
        n = self.n_joints
        rows, rhs = [], []
        for block in (lay.viscous, lay.coulomb):
            r = np.zeros((n, lay.size))
            r[np.arange(n), block.start + np.arange(n)] = 1.0
            rows.append(r)
            rhs.append(np.zeros(n))
        for row, level in cuts:
            rows.append(row[None])
            rhs.append(np.array([level]))
        equalities = 0
        if lay.kp is not None:
            r = np.zeros((1, lay.size))
            r[0, lay.kp] = 1.0 / n
            rows.append(r)
            rhs.append(np.array([self.gain_normalisation]))
            equalities = 1
        a = np.vstack(rows) / scale[None, :]
        return a, np.concatenate(rhs), equalities

    def _constrained(self, chol, normal, scale, lay, cuts):
        rows, rhs, eq = self._constraints(lay, scale, cuts)
        coef = solve_qp(chol, normal.rhs / scale, rows, rhs, eq) / scale
        for block in (lay.viscous, lay.coulomb):        # the dual is exact up to rounding
            coef[block] = np.maximum(coef[block], 0.0)
        return coef

    def _solve_path(self, train, held, weights, lay, stride):
        """Fit every ridge weight on ``train``, score on ``held``; refit the best on both."""
        cv = self.coulomb_velocity
        nt = _normal_equations(self.basis, train, weights, cv, stride)
        nh = _normal_equations(self.basis, held, weights, cv, stride)
        diag = np.diag(nt.gram) + np.diag(nh.gram)
        scale = np.ones(lay.size)
        for g in lay.groups(self.basis):
            level = np.mean(diag[g])
            scale[g] = np.sqrt(level) if level > 0 else 1.0
        gt = nt.gram / np.outer(scale, scale)
        eye = np.eye(lay.size)
        scores = []
        for ridge in self.ridges:
            try:
                chol = cho_factor(gt + ridge * (nt.rows / (nt.rows + nh.rows)) * eye)
            except LinAlgError:
                scores.append((ridge, np.inf))
                continue
            coef = self._constrained(chol, nt, scale, lay, [])
            err = float(coef @ nh.gram @ coef - 2.0 * coef @ nh.rhs + nh.energy)
            if lay.kp is not None:
                # relative to the identified controller's torque on the held-out samples
                ctrl = np.zeros_like(coef)
                for part in (lay.kp, lay.kd, lay.ki, lay.bias):
                    if part is not None:
                        ctrl[part] = coef[part]
                ref = float(ctrl @ nh.gram @ ctrl)
            else:
                ref = nh.energy
            scores.append((ridge, err / ref if ref > 0 else np.inf))
        best = min(scores, key=lambda s: s[1])[0]
        total = _Normal(nt.gram + nh.gram, nt.rhs + nh.rhs, nt.energy + nh.energy,
                        nt.rows + nh.rows)
        chol = cho_factor(total.gram / np.outer(scale, scale) + best * eye)
        coef = self._constrained(chol, total, scale, lay, [])
        return coef, best, scores, total, scale, chol

    def _enforce_positive(self, samples, chol, normal, scale, lay, case, kp, kd):
        """Cut and refit (:data:`CUT_ROUNDS`) until λ_min(S M S) >= floor; then certify."""
        step = max(1, samples.n_samples // 2000)
        data = self.raw_mass_matrix(samples.theta[::step])
        diag = np.diagonal(data, axis1=1, axis2=2).mean(axis=0)
        if np.any(diag <= 0.0):
            diag = np.full(self.n_joints, np.abs(diag).max() or 1.0)
        self.inertia_scale_ = 1.0 / np.sqrt(diag)
        s = self.inertia_scale_
        floor = self.min_eigenvalue
        if floor is None:
            lam = np.linalg.eigvalsh(data * np.outer(s, s))[:, 0]
            floor = 0.1 * float(lam.min()) if lam.min() > 0.0 else 0.01
        self.min_eigenvalue_ = floor
        rng = np.random.default_rng(0)
        lo = np.full(self.n_joints, -np.pi) if self.joint_lower is None else \
            np.asarray(self.joint_lower, dtype=float)
        hi = np.full(self.n_joints, np.pi) if self.joint_upper is None else \
            np.asarray(self.joint_upper, dtype=float)
        check = rng.uniform(lo, hi, (self.check_points, self.n_joints))
        cuts = []
        for _ in range(CUT_ROUNDS):
            if self._late():
                break
            lam, vecs = np.linalg.eigh(self.raw_mass_matrix(check) * np.outer(s, s))
            bad = np.flatnonzero(lam[:, 0] < floor)
            if bad.size == 0:
                break
            for k in _spread(check, bad[np.argsort(lam[bad, 0])], CUTS_PER_ROUND):
                cuts.append((self._cut_row(check[k], s * vecs[k, :, 0], lay), 2.0 * floor))
            coef = self._constrained(chol, normal, scale, lay, cuts)
            self._set(coef, lay, case, kp, kd)
        self.cuts_ = len(cuts)
        lam = np.linalg.eigvalsh(self.raw_mass_matrix(check) * np.outer(s, s))[:, 0]
        self.check_min_eigenvalue_ = float(lam.min())
        self.floor_active_ = float(np.mean(lam < floor))
        self.certificate_ = None
        varying = np.count_nonzero(np.any(self.basis.frequencies[
            np.any(self._w_mass != 0.0, axis=(1, 2))] != 0, axis=0))
        self.late_ = self._late()
        if self.max_cells > 0 and varying <= self.max_certified_joints and not self.late_:
            self.certificate_ = certify_inertia(
                self.basis, self._full_coef[lay.mass], floor, s, self.joint_lower,
                self.joint_upper, self.max_cells)

    def _late(self) -> bool:
        deadline = getattr(self, '_deadline', None)
        return deadline is not None and time.perf_counter() > deadline

    def _cut_row(self, theta, v, lay):
        """Row r with ``r @ coef`` = vᵀ M(θ) v."""
        phi = self.basis.values(theta)
        entries = np.zeros(self.basis.n_entry_features)
        start = 0
        for (a, b), ix in zip(self.basis.mass_entries, self.basis.mass_index):
            weight = v[a] * v[b] * (1.0 if a == b else 2.0)
            entries[start:start + ix.size] = weight * phi[ix]
            start += ix.size
        if self.basis.mass_tie is not None:
            entries = entries @ self.basis.mass_tie
        row = np.zeros(lay.size)
        row[lay.mass] = entries
        return row

    def condition_number(self) -> float:
        """Return the condition number of the fitted, column-scaled regressor."""
        self._check()
        normal, scale = self._scaled_gram
        ev = np.linalg.eigvalsh(normal.gram / np.outer(scale, scale))
        return float(np.sqrt(ev[-1] / ev[0])) if ev[0] > 0 else float('inf')


def torque_nrmse(predicted, measured) -> float:
    """Return the torque NRMSE: RMSE / std of the measured torque per joint, joint mean."""
    return nrmse(predicted, measured)

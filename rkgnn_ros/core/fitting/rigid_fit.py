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
The rigid-body arm of a robot description, fitted in closed form in each of the three cases.

With the kinematics known, the arm's equation is linear in its parameters,
Y(θ, θ̇, θ̈) π = τ (:mod:`rkgnn_ros.core.rigid`), and each case is one consistent least
squares (:func:`~rkgnn_ros.core.rigid.solve.fit_consistent`) on the filtered samples of
:mod:`.rigid_data`:

- case 1 (:func:`fit_torque`): Y π = τ, each joint's rows divided by its RMS torque;
- case 2 (:func:`fit_closed`, gains given): Y π = Kp e + Kd ė [+ Y_g ρ] [+ Ki ∫e];
- case 3 (:func:`fit_closed`, no gains): the same with Kp, Kd (and Ki) unknown too. Arm and
  servo then scale together: the fit fixes the mean Kp at 1, and the robot description
  fixes the one factor left: the arm is scaled so that the URDF's parameters explain its
  torques best (a least-squares factor over the data), so the gains come out in N m/rad
  as far as the URDF's masses are right (``info['scale_from']``).

A servo's gravity compensation (Y_g ρ on θ or on θd, :class:`.rigid_law.GravityFeatures`)
and an integral are fitted where they explain held-out data clearly better
(:func:`fit_closed_forms`). Each fit is scored on held-out samples: case 1 by the torque
error (RMSE on the held-out samples / std over fitted and held-out samples, per joint),
cases 2 and 3 by the closed loop's equation error (RMS of Y π minus the servo's torque on
the held-out samples over the servo torque's std on all of them, per joint). The spread is
the whole window's: a held-out part of a second or less can see a joint's torque hardly
vary, and its own spread would call a small error large. :class:`RigidArm` is
the arm a fit gives, with the model interface the gate and the feed-forward use.
"""

import dataclasses
import math
from typing import NamedTuple, Optional, Sequence, Tuple

import numpy as np

from .controller_laws import ControllerLaw
from .policy import FORM_GAIN, FORM_MIN_ERROR, FULL_EVALUATIONS, SELECT_EVALUATIONS
from .rigid_data import choose_sigma, filtered_rows, FilteredRows
from .rigid_law import GravityFeatures
from ..data import Dataset
from ..rigid import consistency
from ..rigid.kernels import N_INERTIAL, N_JOINT
from ..rigid.solve import fit_consistent
from ..rigid.structure import RigidStructure
from ..servo_law import pd_torque

__all__ = ['RigidArm', 'RigidFit', 'fit_closed', 'fit_closed_forms', 'fit_torque',
           'torque_errors']


class RigidArm:
    """
    A rigid-body arm: a structure and its full parameter vector (every body realizable).

    Parameters
    ----------
    structure : RigidStructure
        Kinematics and joint order.
    parameters : array_like, shape (P,)
        Ten inertial parameters per body, four per joint (:mod:`rkgnn_ros.core.rigid`).
    info : dict, optional
        What the fit says of itself (errors, samples, case, scale).

    """

    case = 'torque'

    def __init__(self, structure: RigidStructure, parameters, info: Optional[dict] = None):
        self.structure = structure
        self.parameters = np.array(parameters, dtype=float).reshape(-1)
        if self.parameters.size != structure.n_parameters:
            raise ValueError(f'{structure.n_parameters} parameters expected, got '
                             f'{self.parameters.size}')
        self.info = dict(info or {})

    @property
    def n_joints(self) -> int:
        """Return the number of joints n."""
        return self.structure.n_joints

    @property
    def joint_names(self):
        """Return the joint names, in the joint vector's order."""
        return self.structure.joint_names

    def _flat(self, *arrays):
        n = self.n_joints
        arrays = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in arrays))
        shape = arrays[0].shape
        return shape, [np.ascontiguousarray(a.reshape(-1, n)) for a in arrays]

    def inverse_dynamics(self, theta, theta_dot, theta_ddot) -> np.ndarray:
        """Return τ = M θ̈ + V + G + F (N m), shape (..., n)."""
        shape, flat = self._flat(theta, theta_dot, theta_ddot)
        return self.structure.inverse_dynamics(self.parameters, *flat).reshape(shape)

    def forward_dynamics(self, theta, theta_dot, tau) -> np.ndarray:
        """Return θ̈ = M⁻¹ (τ − V − G − F) (rad/s²), shape (..., n)."""
        shape, flat = self._flat(theta, theta_dot, tau)
        return self.structure.accelerations(self.parameters, *flat).reshape(shape)

    def mass_matrix(self, theta) -> np.ndarray:
        """Return M(θ) (kg m²), shape (..., n, n)."""
        shape, flat = self._flat(theta)
        n = self.n_joints
        return self.structure.mass_matrix(self.parameters, flat[0]).reshape(shape + (n,))

    def gravity_terms(self, theta) -> np.ndarray:
        """Return G(θ) (N m), shape (..., n)."""
        shape, flat = self._flat(theta)
        return self.structure.gravity_torque(self.parameters, flat[0]).reshape(shape)

    def bodies(self) -> np.ndarray:
        """Return the bodies' ten inertial parameters, shape (n, 10)."""
        return self.parameters[:N_INERTIAL * self.n_joints].reshape(-1, N_INERTIAL)

    def joint_terms(self) -> np.ndarray:
        """Return each joint's (armature, viscous, Coulomb, offset), shape (n, 4)."""
        return self.parameters[N_INERTIAL * self.n_joints:].reshape(-1, N_JOINT)

    def consistent(self) -> bool:
        """Return whether every body is realizable (J ⪰ 0, to rounding)."""
        return bool(np.all(consistency.realizable(self.bodies(), 1e-9)))

    def simulate(self, x0, t, tau=None, theta_d=None, theta_d_dot=None,
                 substeps: int = 4) -> np.ndarray:
        """
        Roll the arm out from ``x0`` (2n,) over the times ``t`` (K,) by Runge-Kutta-Gill.

        Open loop under ``tau`` (K, n), held over each interval, or closed with the PD of
        :attr:`kp`, :attr:`kd` (set by a case-2 fit) along ``theta_d``, ``theta_d_dot``
        (K, n), linear between samples. Returns the states (K, 2n), NaN from a divergence on.
        """
        from ..integration.rkg import rkg_step
        n = self.n_joints
        t = np.asarray(t, dtype=float)
        closed = tau is None
        if closed and getattr(self, 'kp', None) is None:
            raise ValueError('a closed-loop rollout needs the gains kp, kd')
        out = np.full((t.size, 2 * n), np.nan)
        x = np.asarray(x0, dtype=float).copy()
        out[0] = x

        def rate(state, u):
            torque = u if not closed else pd_torque(self.kp, self.kd, u[:n] - state[:n],
                                                    u[n:] - state[n:])
            acc = self.structure.accelerations(self.parameters, state[None, :n],
                                               state[None, n:], torque[None])[0]
            return np.concatenate([state[n:], acc])

        for k in range(t.size - 1):
            h = (t[k + 1] - t[k]) / substeps
            for s in range(substeps):
                if closed:
                    a, b = s / substeps, (s + 0.5) / substeps
                    u0 = np.concatenate([(1 - a) * theta_d[k] + a * theta_d[k + 1],
                                         (1 - a) * theta_d_dot[k] + a * theta_d_dot[k + 1]])
                    uh = np.concatenate([(1 - b) * theta_d[k] + b * theta_d[k + 1],
                                         (1 - b) * theta_d_dot[k] + b * theta_d_dot[k + 1]])
                    c = (s + 1) / substeps
                    u1 = np.concatenate([(1 - c) * theta_d[k] + c * theta_d[k + 1],
                                         (1 - c) * theta_d_dot[k] + c * theta_d_dot[k + 1]])
                else:
                    u0 = uh = u1 = np.asarray(tau[k], dtype=float)
                x = rkg_step(rate, x, h, u0, uh, u1)
            if not np.all(np.isfinite(x)) or np.max(np.abs(x)) > 1e6:
                break
            out[k + 1] = x
        return out

    def scaled(self, factor: float) -> 'RigidArm':
        """Return the arm with every parameter multiplied by ``factor`` > 0."""
        return RigidArm(self.structure, self.parameters * float(factor), self.info)


class RigidFit(NamedTuple):
    """What one rigid-body fit gives."""

    arm: RigidArm
    #: cases 2 and 3: the servo the fit found (gains, gravity weights, integral); else None
    law: Optional[ControllerLaw]
    #: held-out error per joint (torque error in case 1, equation error otherwise)
    errors: np.ndarray
    #: training samples used
    samples: int

    @property
    def error(self) -> float:
        """Return the worst joint's held-out error; inf without held-out samples."""
        return float(np.max(self.errors)) if self.errors.size else math.inf


def _rms(x: np.ndarray) -> np.ndarray:
    value = np.sqrt(np.mean(np.square(x), axis=0))
    return np.where(np.isfinite(value) & (value > 0.0), value, 1.0)


def torque_errors(arm: RigidArm, rows: Optional[FilteredRows],
                  spread_of: Optional[np.ndarray] = None) -> np.ndarray:
    """
    Return the torque error per joint on filtered rows, RMSE / std (inf: none).

    ``spread_of`` (K, n): the torques whose std normalises (default the rows' own).
    """
    if rows is None or rows.tau is None or rows.n_samples < 2:
        return np.full(arm.n_joints, math.inf)
    return _relative(rows.regressor @ arm.parameters - rows.tau,
                     rows.tau if spread_of is None else spread_of)


def _relative(residual: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Return the RMS of ``residual`` (K, n) over the std of ``reference`` (K', n)."""
    with np.errstate(all='ignore'):
        rmse = np.sqrt(np.mean(np.square(residual), axis=0))
        std = np.std(reference, axis=0)
    floor = max(1e-3 * float(np.max(std)), 1e-12) if std.size else 1e-12
    out = rmse / np.maximum(std, floor)
    return np.where(np.isfinite(out), out, math.inf)


def _prepare(structure, train, validation, sigma, measured_velocity, features=None):
    """Return the filtered rows of ``train`` and ``validation`` (None: too short), and σ."""
    def regressor(theta, theta_dot, theta_ddot):
        return structure.regressor(theta, theta_dot, theta_ddot)

    if sigma is None:        # one filter for both, chosen on the training data's noise
        sigma = choose_sigma(train)
    fit = filtered_rows(train, regressor, sigma, measured_velocity, features)
    held = (filtered_rows(validation, regressor, sigma, measured_velocity, features)
            if validation else None)
    if fit is None or fit.n_samples < 2:
        return None, None, sigma
    return fit, held, sigma


def fit_torque(structure: RigidStructure, train: Sequence[Dataset],
               validation: Sequence[Dataset] = (), prior=None, sigma: Optional[float] = None,
               measured_velocity: bool = False,
               min_samples: int = 50) -> Optional[RigidFit]:
    """
    Return case 1's arm fitted on ``train`` (with torque) and scored on ``validation``.

    None with fewer than ``min_samples`` filtered samples. ``prior``: the parameters pulled
    towards where the data do not decide (default the URDF's).
    """
    train = [seg for seg in train if seg.tau is not None]
    validation = [seg for seg in validation if seg.tau is not None]
    fit, held, sigma = _prepare(structure, train, validation, sigma, measured_velocity)
    if fit is None or fit.n_samples < min_samples:
        return None
    weights = 1.0 / _rms(fit.tau)
    rows = fit.regressor.reshape(-1, structure.n_parameters)
    w = np.tile(weights, fit.n_samples)
    result = fit_consistent(structure, rows * w[:, None], fit.tau.reshape(-1) * w, prior=prior)
    arm = RigidArm(structure, result.parameters,
                   {'case': 'torque', 'samples': int(fit.n_samples), 'sigma': sigma,
                    'rms_residual': result.rms_residual, 'evaluations': result.evaluations})
    errors = torque_errors(arm, held, None if held is None or held.tau is None
                           else np.concatenate([fit.tau, held.tau]))
    if held is not None and held.tau is not None:
        _normal_level(arm, None, held)
    arm.info['torque_errors'] = errors.tolist()
    return RigidFit(arm, None, errors, int(fit.n_samples))


class _Closed(NamedTuple):
    """The columns of a closed-loop fit: servo torque = known part + extras @ k."""

    known: np.ndarray        # (N, n): Kp e + Kd ė with known gains (zeros in case 3)
    extras: np.ndarray       # (N, n, E): each unknown's torque per unit
    normalise: Optional[np.ndarray]
    layout: dict             # name -> slice of k: 'kp', 'kd', 'ki', 'constants', 'gravity'


def _closed_columns(structure, samples: FilteredRows, features, kp, kd, integral: bool,
                    gravity: Optional[str]) -> _Closed:
    n = structure.n_joints
    eye = np.eye(n)[None]
    e, e_dot = samples.error, samples.error_rate
    columns, layout = [], {}

    def add(name, block):
        start = sum(c.shape[2] for c in columns)
        layout[name] = slice(start, start + block.shape[2])
        columns.append(block)

    known = np.zeros_like(e)
    if kp is None:
        add('kp', e[:, :, None] * eye)
        add('kd', e_dot[:, :, None] * eye)
    else:
        known = np.asarray(kp) * e + np.asarray(kd) * e_dot
    if integral:
        add('ki', samples.integral[:, :, None] * eye)
        segs = np.unique(samples.segment)
        if segs.size > 1:   # ∫e starts anew in each segment: one constant each after the first
            const = np.zeros((samples.n_samples, n, n * (segs.size - 1)))
            for k, seg in enumerate(segs[1:]):
                const[samples.segment == seg, :, k * n:(k + 1) * n] = np.eye(n)
            add('constants', const)
    if gravity is not None and features.size:
        add('gravity', samples.gravity[gravity])
    extras = (np.concatenate(columns, axis=2) if columns
              else np.zeros((samples.n_samples, n, 0)))
    normalise = None
    if kp is None:
        normalise = np.zeros(extras.shape[2])
        normalise[layout['kp']] = 1.0 / n                   # the mean Kp is 1
    return _Closed(known, extras, normalise, layout)


def _law_of(layout: dict, k: np.ndarray, n: int, kp, kd, features, gravity,
            samples: FilteredRows) -> ControllerLaw:
    def part(name):
        return k[layout[name]] if name in layout else None

    law_kp = part('kp') if kp is None else np.asarray(kp, dtype=float)
    law_kd = part('kd') if kd is None else np.asarray(kd, dtype=float)
    ki = part('ki') if 'ki' in layout else np.zeros(n)
    constants = part('constants')
    bias = constants[-n:] if constants is not None and constants.size else np.zeros(n)
    # ∫e at the newest sample (its segment's): the law's integral term now
    integral_term = ki * samples.integral[-1] if 'ki' in layout else np.zeros(n)
    rho = part('gravity')
    with_gravity = rho is not None and rho.size > 0
    return ControllerLaw(kp=law_kp, kd=np.maximum(law_kd, 0.0), ki=ki, bias=bias,
                         integral_term=integral_term, feedforward=np.zeros(n),
                         theta_weights=np.tile(rho, (n, 1)) if with_gravity
                         else np.zeros((n, 0)),
                         theta_input=gravity if with_gravity else 'measured',
                         features=features if with_gravity else None,
                         fit_ratio=np.zeros(n), samples=samples.n_samples)


def servo_torque(law: ControllerLaw, samples: FilteredRows) -> np.ndarray:
    """Return the law's torque on filtered samples (K, n); its integral from each start."""
    servo = pd_torque(law.kp, law.kd, samples.error, samples.error_rate)
    if np.any(law.ki != 0.0):
        servo = servo + law.ki * samples.integral
    if law.theta_weights.size:
        servo = servo + np.einsum('kif,if->ki', samples.gravity[law.theta_input],
                                  law.theta_weights)
    return servo


def residual(arm: RigidArm, law: Optional[ControllerLaw],
             samples: FilteredRows) -> Tuple[np.ndarray, np.ndarray]:
    """
    Return the model's residual on filtered samples (K, n), and what it is judged against.

    Without a law (case 1) the torque's: Y π − τ, against τ; with one (cases 2 and 3) the
    closed loop's equation error: Y π − the servo's torque, against that torque (an
    integral's unknown value at the samples' start removed as each joint's mean).
    """
    if law is None:
        return samples.regressor @ arm.parameters - samples.tau, samples.tau
    servo = servo_torque(law, samples)
    out = samples.regressor @ arm.parameters - servo
    if np.any(law.ki != 0.0):
        out = out - out.mean(axis=0)
    return out, servo


def _equation_errors(arm: RigidArm, law: ControllerLaw, samples: Optional[FilteredRows],
                     fitted: FilteredRows) -> np.ndarray:
    """
    Return the closed loop's equation error per joint on ``samples`` (inf: none).

    Normalised by the std of the servo's torque on ``samples`` and ``fitted`` together.
    """
    n = arm.n_joints
    if samples is None or samples.n_samples < 2 or samples.error is None:
        return np.full(n, math.inf)
    out, servo = residual(arm, law, samples)
    return _relative(out, np.concatenate([servo_torque(law, fitted), servo]))


def _normal_level(arm: RigidArm, law, samples: Optional[FilteredRows]) -> None:
    """Keep the held-out residual's RMS and the judged torque's spread in ``arm.info``."""
    if samples is None or samples.n_samples < 2:
        return
    out, reference = residual(arm, law, samples)
    arm.info['residual_rms'] = np.sqrt(np.mean(out ** 2, axis=0)).tolist()
    arm.info['torque_spread'] = np.std(reference, axis=0).tolist()


class ClosedFitOptions(NamedTuple):
    """The basis, prior and filter options of :func:`fit_closed` (see there)."""

    features: Optional[GravityFeatures] = None
    prior: object = None
    sigma: Optional[float] = None
    measured_velocity: bool = False
    min_samples: int = 50
    max_evaluations: int = 200


def fit_closed(structure: RigidStructure, train: Sequence[Dataset],
               validation: Sequence[Dataset] = (), kp=None, kd=None, integral: bool = False,
               gravity: Optional[str] = None, **options) -> Optional[RigidFit]:
    """
    Return the arm and servo of the closed loop fitted on ``train`` (cases 2 and 3).

    ``kp``, ``kd`` (n,) known (case 2) or None (case 3: fitted, module docstring).
    ``integral``: a PID servo; ``gravity``: a gravity compensation on 'measured' θ or
    'desired' θd (None: none); ``max_evaluations``: the consistent solver's budget. None
    with too few samples or a fit that fails.
    """
    (features, prior, sigma, measured_velocity, min_samples,
     max_evaluations) = ClosedFitOptions(**options)
    need = ('theta_d', 'theta_d_dot')
    train = [seg for seg in train if all(getattr(seg, k) is not None for k in need)]
    validation = [seg for seg in validation if all(getattr(seg, k) is not None for k in need)]
    if features is None and gravity is not None:
        features = GravityFeatures(structure)
    fit, held, sigma = _prepare(structure, train, validation, sigma, measured_velocity,
                                features if gravity is not None else None)
    if fit is None or fit.n_samples < min_samples:
        return None
    n = structure.n_joints
    cols = _closed_columns(structure, fit, features, kp, kd, integral, gravity)
    rows = fit.regressor.reshape(-1, structure.n_parameters)
    # cases 2 and 3: the arm's constant offset is the servo's constant (one column, not two)
    extras = -cols.extras.reshape(fit.n_samples * n, cols.extras.shape[2])
    target = cols.known.reshape(-1)
    prior = structure.prior if prior is None else np.asarray(prior, dtype=float)
    scale = 1.0
    if kp is None:
        weights, scale = _case_three_start(structure, rows, extras, cols.normalise, prior, n)
        if weights is None:
            return None
        prior = prior * scale
    else:
        weights = 1.0 / _rms(cols.known)
    w = np.tile(weights, fit.n_samples)
    try:
        result = fit_consistent(structure, rows * w[:, None], target * w, extras * w[:, None],
                                cols.normalise, prior=prior, extra_ridge=1e-8,
                                max_evaluations=max_evaluations)
    except (ValueError, np.linalg.LinAlgError):
        return None
    law = _law_of(cols.layout, result.extra, n, kp, kd, features, gravity, fit)
    if not (np.all(np.isfinite(law.kp)) and np.all(law.kp > 0.0)):
        return None
    parameters = result.parameters
    if kp is None:      # case 3: from units of the mean Kp back to N m (module docstring)
        parameters = parameters / scale
        law = dataclasses.replace(
            law, kp=law.kp / scale, kd=law.kd / scale, ki=law.ki / scale,
            bias=law.bias / scale, integral_term=law.integral_term / scale,
            theta_weights=law.theta_weights / scale)
    arm = RigidArm(structure, parameters,
                   {'case': 'unknown' if kp is None else 'pd_gains', 'sigma': sigma,
                    'samples': int(fit.n_samples), 'rms_residual': result.rms_residual,
                    'evaluations': result.evaluations, 'form': law.describe(),
                    'mean_kp_unit_in_newton_metres': 1.0 / scale,
                    'scale_from': 'robot_description' if kp is None else 'gains'})
    errors = _equation_errors(arm, law, held, fit)
    if held is not None and held.error is not None:
        _normal_level(arm, law, held)
    arm.info['equation_errors'] = errors.tolist()
    return RigidFit(arm, law, errors, int(fit.n_samples))


def _case_three_start(structure, rows, extras, normalise, prior, n):
    """
    Return the per-joint row weights and the scale of case 3 (module docstring).

    One unweighted linear least squares (base parameters and the unknowns, mean Kp 1) gives
    the servo's torque, whose RMS per joint weighs the rows, and the factor s by which the
    URDF's parameters best explain that fit's arm torque: the arm is fitted with the prior
    s π_URDF, i.e. in units of N m divided by 1 / s.
    """
    base = structure.base
    k0 = normalise / float(normalise @ normalise)
    _, _, vt = np.linalg.svd(normalise[None, :])
    null = vt[1:].T
    design = np.hstack([rows[:, base.independent], extras @ null])
    target = -(extras @ k0)
    col = np.sqrt(np.mean(design * design, axis=0))
    col[col == 0.0] = 1.0
    solution, *_ = np.linalg.lstsq(design / col, target, rcond=1e-10)
    solution = solution / col
    beta = solution[:base.rank]
    k = k0 + null @ solution[base.rank:]
    kp, kd = k[:n], k[n:2 * n]
    if not (np.all(np.isfinite(k)) and np.all(kp > 0.0)):
        return None, 1.0
    servo = (extras[:, :2 * n] @ -np.concatenate([kp, kd])).reshape(-1, n)
    weights = 1.0 / _rms(servo)
    fitted = rows[:, base.independent] @ beta
    nominal = rows @ prior
    denom = float(nominal @ nominal)
    scale = float(fitted @ nominal) / denom if denom > 0.0 else 0.0
    if not (math.isfinite(scale) and scale > 0.0):
        scale = 1.0 / max(float(np.mean(np.abs(kp))), 1e-12)
    return weights, scale


class FormsOptions(NamedTuple):
    """The filter and prior options of :func:`fit_closed_forms` (see there)."""

    sigma: Optional[float] = None
    measured_velocity: bool = False
    prior: object = None


def fit_closed_forms(structure: RigidStructure, train: Sequence[Dataset],
                     validation: Sequence[Dataset], kp=None, kd=None,
                     features: Optional[GravityFeatures] = None, **options) -> Optional[RigidFit]:
    """
    Return the closed-loop fit of the form the held-out data support best.

    A PD first; a gravity compensation (on θ, then on θd) and an integral are each kept
    only where the held-out error is at most :data:`~.policy.FORM_GAIN` of the simpler
    form's and that one leaves more than :data:`~.policy.FORM_MIN_ERROR`. The forms are
    compared on fits of at most :data:`~.policy.SELECT_EVALUATIONS` solver evaluations; the
    chosen one, unless its fit converged within them, is fitted again with
    :data:`~.policy.FULL_EVALUATIONS`.
    """
    sigma, measured_velocity, prior = FormsOptions(**options)
    if features is None:
        features = GravityFeatures(structure)

    def attempt(integral, gravity, budget):
        return fit_closed(structure, train, validation, kp, kd, integral, gravity,
                          features=features, prior=prior, sigma=sigma,
                          measured_velocity=measured_velocity, max_evaluations=budget)

    form = (False, None)
    best = attempt(*form, SELECT_EVALUATIONS)
    for integral, gravity in ((False, 'measured'), (False, 'desired'), (True, None),
                              (True, 'measured')):
        if best is not None and not best.error > FORM_MIN_ERROR:
            break
        other = attempt(integral, gravity, SELECT_EVALUATIONS)
        if other is None:
            continue
        if best is None or other.error <= FORM_GAIN * best.error:
            best, form = other, (integral, gravity)
    if best is not None and best.arm.info['evaluations'] >= SELECT_EVALUATIONS:
        best = attempt(*form, FULL_EVALUATIONS) or best     # not converged: its full fit
    return best

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
The PD tracking error of eq. (10) for a population of gains: the objective of the PD tuning.

The cost of one candidate (diagonal gains Kp, Kd) is::

    J = 1/t_N Σ_i ( ‖θd(i) - θ(i)‖ + ‖θ̇d(i) - θ̇(i)‖ )

where the sum runs over the samples t_i = i / rate, i = 1 .. N-1, of the closed loop started
on the reference at t = 0 (the initial sample is given, not simulated, as in
:mod:`rkgnn_ros.core.fitting.fitness`), and the norms are Euclidean over the joints. The same
error computed from :func:`rkgnn_ros.core.sim.simulate.simulate` output (LSODA, rtol 1e-9)
agrees to 4e-8 relative or better (6e-10 for the paper's gains, 4e-8 at the stiffest).

Simulation. The closed loop (continuous PD, torque computed from the reference at every
stage) is integrated by fixed Runge-Kutta-Gill steps (:mod:`..integration.rkg`, the
stability polynomial of classical RK4), ``substeps`` steps per sampling interval. The
reference is evaluated once on the stage grid t_i + k h / 2 and shared by every candidate.
:meth:`TrackingProblem.cost` runs one compiled numba kernel over the whole population:
parallel over candidates (``prange``, dynamic chunks of one candidate, since diverging
candidates stop early), ``nogil``, the plant's arithmetic from
:func:`rkgnn_ros.core.sim.plant_kernels.forward_dynamics_into` with per-candidate buffers
(no allocation in the loop). :meth:`TrackingProblem.cost_numpy` is the plain numpy reference
(:func:`rkgnn_ros.core.integration.rkg.rkg_step` on ``PlanarArm.dynamics``, batched over the
population); the two agree to rounding.

Step. The gains are bounded, so the stiffest closed loop is bounded: the step is the
plant's :meth:`PlanarArm.stable_step` at the largest gains (the upper bounds on every
joint), over the reference's states and a grid of configurations covering every relative
joint angle (the mass matrix depends on those only), with safety :data:`STEP_SAFETY`;
see :func:`tuning_step`. For the paper's arm and the default bounds the stiffest loop is
the stretched arm (|λ| = 4.36e3 1/s), the step 4.8e-4 s, 21 steps per 10 ms sample.

Divergence. A candidate costs +inf (never NaN) if its simulation turns non-finite or a
joint speed exceeds ``max_speed`` (checked after every step; the kernel then stops), or if
it is unstable at the chosen step: some eigenvalue λ of its closed-loop Jacobian,
linearised on the reference states, has |R(h λ)| > 1, with R the RK4 stability
polynomial (:meth:`TrackingProblem.unstable`). At the default step gains inside the
bounds never are; gains beyond them may be.
"""

import math
from typing import Optional, Tuple

from numba import get_parallel_chunksize, njit, prange, set_parallel_chunksize
import numpy as np

from .plant import PlanarArm
from .plant_kernels import forward_dynamics_into
from .simulate import MAX_SPEED, sample_count
from .trajectories import Reference
from ..integration.rkg import (gill_node, gill_stage, IMAG_STABILITY_LIMIT, rkg_step,
                               stability_polynomial)
from ..servo_law import compiled_pd_torque, pd_torque


#: Default gain bounds ((Kp_lo, Kp_hi), (Kd_lo, Kd_hi)), the same on every joint. They
#: contain the paper's gains.
DEFAULT_BOUNDS = ((0.0, 100.0), (0.0, 50.0))

#: Fraction of the RK4 stability limit used by :func:`tuning_step`. The plant's default
#: (0.5) allows for states away from the sampled ones; here the sampled states cover every
#: configuration, which leaves the velocity terms (for the paper's arm, joint speeds up to
#: 20 rad/s change the largest |λ| by under 5 %) and the nonlinearity. At 0.75 the fast
#: modes are still damped by each step (|R(-2.09)| = 0.37), and the cost agrees with a
#: tight adaptive solution to 4e-8.
STEP_SAFETY = 0.75

#: Relative tolerance between the compiled kernel and the numpy reference in the check
#: that runs once per process (see :meth:`TrackingProblem.cost`).
_KERNEL_RTOL = 1e-9

_kernel_verified = False


# -- compiled kernel ----------------------------------------------------------------------


@njit(cache=True, nogil=True, error_model='numpy')
def _pd_torque_into(th, om, ref, j, kp, kd, tau):
    """Write the PD torque towards θd = ref[j, 0], θ̇d = ref[j, 1] into ``tau`` (n,)."""
    for i in range(th.shape[0]):
        tau[i] = compiled_pd_torque(kp[i], kd[i], ref[j, 0, i] - th[i], ref[j, 1, i] - om[i])


@njit(cache=True, nogil=True, error_model='numpy', inline='always')
def diverged(th, om, n, max_speed) -> bool:
    """Return whether a joint's speed is beyond ``max_speed`` (rad/s) or its angle not finite."""
    for i in range(n):
        if not (abs(om[i]) <= max_speed and math.isfinite(th[i])):
            return True
    return False


@njit(cache=True, nogil=True, error_model='numpy', inline='always')
def sample_error(ref, j, th, om, n) -> float:
    """Return eq. (10)'s term of sample j: ‖θd - θ‖ + ‖θ̇d - θ̇‖ (ref[j] is [θd, θ̇d])."""
    e_theta = 0.0
    e_rate = 0.0
    for i in range(n):
        e_theta += (ref[j, 0, i] - th[i]) ** 2
        e_rate += (ref[j, 1, i] - om[i]) ** 2
    return math.sqrt(e_theta) + math.sqrt(e_rate)


@njit(cache=True, nogil=True, error_model='numpy')
def _closed_loop_cost(x0, ref, substeps, h, gains, p, d, gh, viscous, coulomb,
                      coulomb_velocity, max_speed):
    """
    Return the eq. (10) cost of candidate ``p``, or +inf if it diverges.

    ``x0`` (2n,) is the start state, ``ref`` (2 substeps (N - 1) + 1, 2, n) holds θd and θ̇d
    at the stage times t_0 + k h / 2, ``gains`` (P, 2n) the rows [Kp, Kd]; the rest are
    the plant's kernel constants and the speed limit. Runge-Kutta-Gill with the state kept
    as θ and θ̇ (n,) each, so that the plant kernel takes them unsliced; the package's one
    stage update (:func:`..integration.rkg.gill_stage`) advances each half.
    """
    n = x0.shape[0] // 2
    kp = np.empty(n)
    kd = np.empty(n)
    th = np.empty(n)            # θ
    om = np.empty(n)            # θ̇
    yth = np.empty(n)           # stage state
    yom = np.empty(n)
    qth = np.empty(n)           # Gill's accumulator
    qom = np.empty(n)
    acc = np.empty(n)           # θ̈ at the stage
    tau = np.empty(n)
    work = np.empty((n + 3, n))
    for i in range(n):
        kp[i] = gains[p, i]
        kd[i] = gains[p, n + i]
        th[i] = x0[i]
        om[i] = x0[n + i]
    n_samples = (ref.shape[0] - 1) // (2 * substeps) + 1
    total = 0.0
    j = 0
    for _ in range(1, n_samples):
        for _ in range(substeps):
            for i in range(n):
                yth[i] = th[i]
                yom[i] = om[i]
            for stage in range(4):
                _pd_torque_into(yth, yom, ref, j + gill_node(stage), kp, kd, tau)
                forward_dynamics_into(yth, yom, tau, d, gh, viscous, coulomb, coulomb_velocity,
                                      work, acc)
                gill_stage(stage, h, th, yth, yom, qth)     # θ' = θ̇, before θ̇ moves on
                gill_stage(stage, h, om, yom, acc, qom)     # θ̇' = θ̈
            if diverged(th, om, n, max_speed):
                return math.inf
            j += 2
        total += sample_error(ref, j, th, om, n)
    return total / (n_samples - 1)


@njit(cache=True, nogil=True, parallel=True, error_model='numpy')
def _population_cost(x0, ref, substeps, h, gains, d, gh, viscous, coulomb, coulomb_velocity,
                     max_speed, out):
    """Write the cost of every row of ``gains`` (P, 2n) into ``out`` (P,), in parallel."""
    for p in prange(gains.shape[0]):
        out[p] = _closed_loop_cost(x0, ref, substeps, h, gains, p, d, gh, viscous, coulomb,
                                   coulomb_velocity, max_speed)


# -- the step --------------------------------------------------------------------------


def planar_joints(arm, reference: Reference) -> int:
    """Return the joints of ``arm``, a PlanarArm, and ``reference``'s, or raise."""
    if not isinstance(arm, PlanarArm):
        raise TypeError(f'arm must be a PlanarArm, got {type(arm).__name__}')
    if reference.n_joints != arm.n_joints:
        raise ValueError(f'reference has {reference.n_joints} joints, the arm {arm.n_joints}')
    return arm.n_joints


def bounds_arrays(bounds, n: int) -> Tuple[np.ndarray, np.ndarray]:
    """Return (lo, hi), shape (2n,) each, from ((Kp_lo, Kp_hi), (Kd_lo, Kd_hi))."""
    try:
        (kp_lo, kp_hi), (kd_lo, kd_hi) = bounds
        parts = [np.broadcast_to(np.asarray(b, dtype=float), (n,))
                 for b in (kp_lo, kd_lo, kp_hi, kd_hi)]
    except (TypeError, ValueError):
        raise ValueError('bounds must be ((kp_lo, kp_hi), (kd_lo, kd_hi)) with scalars or '
                         f'({n},) arrays, got {bounds!r}') from None
    lo = np.concatenate(parts[:2])
    hi = np.concatenate(parts[2:])
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(lo <= hi)):
        raise ValueError(f'bounds must be finite with lo <= hi, got {bounds!r}')
    return lo, hi


def _configuration_grid(n: int, theta_1: float, max_points: int = 1024) -> np.ndarray:
    """
    Return configurations covering every relative joint angle, shape (K, n).

    θ_2 .. θ_n on a uniform grid of an even number of points per axis over [-π, π) (so the
    stretched arm, all zeros, is on it), at most ``max_points`` in all; θ_1 = ``theta_1``
    (the mass matrix does not depend on θ_1).
    """
    if n == 1:
        return np.array([[theta_1]])
    per_axis = max(2, min(64, int(max_points ** (1.0 / (n - 1)))))
    per_axis -= per_axis % 2
    axis = np.linspace(-np.pi, np.pi, per_axis, endpoint=False)
    mesh = np.meshgrid(*([axis] * (n - 1)), indexing='ij')
    rel = np.stack([m.ravel() for m in mesh], axis=-1)
    return np.concatenate([np.full((rel.shape[0], 1), theta_1), rel], axis=-1)


def tuning_step(arm: PlanarArm, reference: Reference, duration: float,
                bounds=DEFAULT_BOUNDS, safety: float = STEP_SAFETY,
                samples: int = 200) -> float:
    """
    Return an integration step stable for every gain inside the bounds.

    :meth:`PlanarArm.stable_step` at the largest gains (the upper bounds, on every joint)
    over ``samples`` states of the reference on [0, duration] and a grid of configurations
    covering every relative joint angle at rest (:func:`_configuration_grid`, about 1000
    states). The closed-loop stiffness grows with the gains (the Kd M⁻¹ block dominates),
    so the upper corner of the box is the stiffest candidate; :meth:`TrackingProblem.unstable`
    checks every candidate anyway.

    Parameters
    ----------
    arm : PlanarArm
        The plant.
    reference : Reference
        The desired trajectory.
    duration : float
        Time span (s).
    bounds : ((kp_lo, kp_hi), (kd_lo, kd_hi))
        Gain bounds, scalars or (n,) arrays.
    safety : float
        Fraction of the stability limit, in (0, 1]; :data:`STEP_SAFETY` by default.
    samples : int
        Reference states.

    Returns
    -------
    float
        The step (s).

    """
    n = arm.n_joints
    _, hi = bounds_arrays(bounds, n)
    if not (np.isfinite(duration) and duration > 0.0):
        raise ValueError(f'duration must be positive, got {duration}')
    if int(samples) < 1:
        raise ValueError(f'samples must be >= 1, got {samples}')
    theta_d, theta_d_dot = reference.evaluate(np.linspace(0.0, float(duration), int(samples)))
    grid = _configuration_grid(n, float(theta_d[0, 0]))
    theta = np.concatenate([theta_d, grid])
    theta_dot = np.concatenate([theta_d_dot, np.zeros_like(grid)])
    return arm.stable_step(hi[:n], hi[n:], theta, theta_dot, safety=safety)


# -- the tracking cost --------------------------------------------------------------------


class TrackingProblem:
    """
    The tracking error of eq. (10) for one arm, reference and horizon, batched over gains.

    Everything that does not depend on the gains is prepared once: the sample times, the
    step, the reference on the stage grid, the plant's kernel constants and the open-loop
    linearisations for the stability check.

    Parameters
    ----------
    arm : PlanarArm
        The plant.
    reference : Reference
        Desired trajectory; the closed loop starts on it, x(0) = [θd(0), θ̇d(0)].
    duration : float
        Simulated time (s); samples at t_i = i / rate up to ``duration``.
    rate : float
        Sampling rate of the error (Hz).
    step : float, optional
        Largest integration step (s); each sampling interval is split into ``substeps``
        equal steps, h = 1 / (rate substeps) <= step. Default :func:`tuning_step` with the
        default bounds.
    max_speed : float
        A joint speed above this (rad/s) is divergence.
    check_samples : int
        Reference states at which :meth:`unstable` linearises.

    Attributes
    ----------
    t : ndarray, shape (N,)
        Sample times.
    substeps : int
        Runge-Kutta-Gill steps per sampling interval.
    h : float
        The step (s).
    x0 : ndarray, shape (2n,)
        Start state.
    stage_reference : ndarray, shape (2 substeps (N - 1) + 1, 2, n)
        θd and θ̇d at the stage times t_0 + k h / 2.

    """

    def __init__(self, arm: PlanarArm, reference: Reference, duration: float,
                 rate: float = 100.0, step: Optional[float] = None,
                 max_speed: float = MAX_SPEED, check_samples: int = 50):
        self.arm = arm
        self.n = planar_joints(arm, reference)
        self.reference = reference
        if not (np.isfinite(rate) and rate > 0.0):
            raise ValueError(f'rate must be positive, got {rate}')
        if not (np.isfinite(duration) and duration > 0.0):
            raise ValueError(f'duration must be positive, got {duration}')
        n_samples = sample_count(duration, rate)
        if not max_speed > 0.0:
            raise ValueError(f'max_speed must be positive, got {max_speed}')
        self.rate = float(rate)
        self.max_speed = float(max_speed)
        self.t = np.arange(n_samples) / self.rate
        if step is None:
            step = tuning_step(arm, reference, float(self.t[-1]))
        if not (np.isfinite(step) and step > 0.0):
            raise ValueError(f'step must be positive, got {step}')
        self.substeps = max(1, int(math.ceil(1.0 / (self.rate * step) - 1e-9)))
        self.h = 1.0 / (self.rate * self.substeps)
        # stage times (i + k / (2 substeps)) / rate, k = 0 .. 2 substeps - 1, then t_{N-1}
        frac = np.arange(2 * self.substeps) / (2 * self.substeps)
        stage_t = ((np.arange(n_samples - 1)[:, None] + frac[None, :]).ravel() / self.rate)
        stage_t = np.append(stage_t, self.t[-1])
        theta_d, theta_d_dot = reference.evaluate(stage_t)                 # (K, n) each
        self.stage_reference = np.ascontiguousarray(np.stack([theta_d, theta_d_dot], axis=1))
        self.x0 = np.concatenate([theta_d[0], theta_d_dot[0]])
        self._constants = tuple(arm.kernel_constants())
        self._prepare_stability_check(int(check_samples))

    @property
    def n_samples(self) -> int:
        """Count of samples N (the cost averages over the last N - 1)."""
        return self.t.size

    # -- costs ----------------------------------------------------------------------------

    def _gains(self, gains) -> np.ndarray:
        g = np.ascontiguousarray(gains, dtype=float)
        if g.ndim != 2 or g.shape[1] != 2 * self.n:
            raise ValueError(f'gains must have shape (P, {2 * self.n}) = [Kp, Kd] rows, got '
                             f'{g.shape}')
        if not np.all(np.isfinite(g)):
            raise ValueError('gains must be finite')
        return g

    def cost(self, gains) -> np.ndarray:
        """
        Return the tracking error of eq. (10) of every candidate (compiled, parallel).

        The first call in a process also holds the compiled kernel to :meth:`cost_numpy` on
        a short span and recompiles it once if they differ (numba's on-disk cache does not
        notice a change of the plant's kernel in another file).

        Parameters
        ----------
        gains : array_like, shape (P, 2n)
            Rows [Kp_1 .. Kp_n, Kd_1 .. Kd_n] of diagonal gains.

        Returns
        -------
        ndarray, shape (P,)
            Costs; +inf for a candidate that diverges or is unstable at the step, never NaN.

        """
        g = self._gains(gains)
        if not _kernel_verified:
            self._verify_kernel()
        return self._compiled(g, self.stage_reference)

    def cost_numpy(self, gains) -> np.ndarray:
        """Return :meth:`cost` computed in plain numpy (the reference), shape (P,)."""
        return self._numpy(self._gains(gains), self.stage_reference)

    def _compiled(self, g, ref) -> np.ndarray:
        out = np.empty(g.shape[0])
        # chunks of one candidate, handed out dynamically: diverging ones finish early (set
        # here, not in the kernel, which could then not be cached; the setting is per thread)
        chunksize = get_parallel_chunksize()
        set_parallel_chunksize(1)
        try:
            _population_cost(self.x0, ref, self.substeps, self.h, g, *self._constants,
                             self.max_speed, out)
        finally:
            set_parallel_chunksize(chunksize)
        out[self.unstable(g)] = np.inf
        return out

    def _numpy(self, g, ref) -> np.ndarray:
        n, arm = self.n, self.arm
        kp, kd = g[:, :n], g[:, n:]                                      # (P, n) each

        def f(x, u):                                                     # x (P, 2n)
            tau = pd_torque(kp, kd, u[0] - x[:, :n], u[1] - x[:, n:])
            return arm.dynamics(x, tau)

        x = np.tile(self.x0, (g.shape[0], 1))                           # (P, 2n)
        diverged = np.zeros(g.shape[0], dtype=bool)
        total = np.zeros(g.shape[0])
        n_samples = (ref.shape[0] - 1) // (2 * self.substeps) + 1
        j = 0
        with np.errstate(all='ignore'):
            for _ in range(1, n_samples):
                for _ in range(self.substeps):
                    x = rkg_step(f, x, self.h, ref[j], ref[j + 1], ref[j + 2])
                    j += 2
                    bad = ~(np.all(np.isfinite(x), axis=1)
                            & np.all(np.abs(x[:, n:]) <= self.max_speed, axis=1))
                    diverged |= bad
                    x[diverged] = self.x0                # keep the arithmetic tame
                total += (np.linalg.norm(ref[j, 0] - x[:, :n], axis=1)
                          + np.linalg.norm(ref[j, 1] - x[:, n:], axis=1))
        out = total / (n_samples - 1)
        out[diverged | self.unstable(g)] = np.inf
        return out

    def _verify_kernel(self):
        """Hold the compiled kernel to the numpy reference on three samples; recompile once."""
        global _kernel_verified
        n = self.n
        g = np.array([np.concatenate([np.full(n, 30.0), np.full(n, 5.0)]),
                      np.concatenate([np.full(n, 5.0), np.full(n, 0.5)])])
        ref = self.stage_reference[:2 * self.substeps * min(3, self.n_samples - 1) + 1]
        expected = self._numpy(g, ref)

        def matches():
            got = self._compiled(g, ref)
            return bool(np.all(np.abs(got - expected) <= _KERNEL_RTOL * np.abs(expected)))

        if not matches():
            _pd_torque_into.recompile()
            _closed_loop_cost.recompile()
            _population_cost.recompile()
            if not matches():
                raise RuntimeError('the compiled tracking cost disagrees with the numpy '
                                   'reference (PlanarArm.dynamics)')
        _kernel_verified = True

    # -- stability at the step ------------------------------------------------------------

    def _prepare_stability_check(self, samples: int):
        """Linearise the open loop (τ = 0) at ``samples`` reference states, once."""
        n, arm = self.n, self.arm
        theta_d, theta_d_dot = self.reference.evaluate(
            np.linspace(0.0, float(self.t[-1]), max(1, samples)))
        x = np.concatenate([theta_d, theta_d_dot], axis=-1)             # (S, 2n)
        delta = 1e-6 * np.maximum(1.0, np.abs(x))                        # (S, 2n)
        bump = np.eye(2 * n) * delta[:, None, :]                         # (S, 2n, 2n) rows
        zero = np.zeros(n)
        f_plus = arm.dynamics(x[:, None, :] + bump, zero)
        f_minus = arm.dynamics(x[:, None, :] - bump, zero)
        # jac[s, r, c] = ∂f_r / ∂x_c
        self._open_jacobian = np.swapaxes((f_plus - f_minus) / (2.0 * delta[:, :, None]), 1, 2)
        self._inv_mass = np.linalg.inv(arm.mass_matrix(theta_d))        # (S, n, n)

    def unstable(self, gains) -> np.ndarray:
        """
        Return which candidates are linearly unstable under Runge-Kutta-Gill at step ``h``.

        On the reference (θ = θd, so τ = 0) the closed-loop Jacobian is the open loop's
        plus [[0, 0], [-M⁻¹ Kp, -M⁻¹ Kd]], the same as :meth:`PlanarArm.closed_loop_eigenvalues`.
        A candidate is unstable if, at any of the ``check_samples`` states, an eigenvalue
        with Re λ < 0 has |R(h λ)| > 1 (R the RK4 stability polynomial) or one with
        Re λ >= 0 has h |λ| > 2√2 (the step does not resolve it; the rule of
        :func:`rkgnn_ros.core.integration.rkg.stability_radius`).

        Parameters
        ----------
        gains : array_like, shape (P, 2n)
            Rows [Kp, Kd] of diagonal gains.

        Returns
        -------
        ndarray of bool, shape (P,)

        """
        g = self._gains(gains)
        n = self.n
        kp, kd = g[:, :n], g[:, n:]
        jac = np.broadcast_to(self._open_jacobian,
                              (g.shape[0],) + self._open_jacobian.shape).copy()  # (P, S, 2n, 2n)
        jac[..., n:, :n] -= self._inv_mass[None] * kp[:, None, None, :]
        jac[..., n:, n:] -= self._inv_mass[None] * kd[:, None, None, :]
        lam = np.linalg.eigvals(jac)                                    # (P, S, 2n)
        z = self.h * lam
        growth = np.abs(stability_polynomial(z))
        size = np.abs(lam)
        left = lam.real < -1e-12 * size
        bad = np.where(left, growth > 1.0 + 1e-12, self.h * size > IMAG_STABILITY_LIMIT)
        return bad.any(axis=(1, 2))


def tracking_cost(arm: PlanarArm, reference: Reference, gains, duration: float,
                  rate: float = 100.0, step: Optional[float] = None,
                  max_speed: float = MAX_SPEED) -> np.ndarray:
    """
    Return the tracking error of eq. (10) of a population of diagonal PD gains.

    A one-off :class:`TrackingProblem`; build the problem once to evaluate many
    populations on the same reference.

    Parameters
    ----------
    arm : PlanarArm
        The plant.
    reference : Reference
        Desired trajectory; the closed loop starts on it.
    gains : array_like, shape (P, 2n)
        Rows [Kp_1 .. Kp_n, Kd_1 .. Kd_n].
    duration : float
        Simulated time (s).
    rate : float
        Sampling rate of the error (Hz).
    step : float, optional
        Largest integration step (s); default :func:`tuning_step` at the largest gains of
        :data:`DEFAULT_BOUNDS` (for the paper's arm 4.8e-4 s).
    max_speed : float
        A joint speed above this (rad/s) is divergence.

    Returns
    -------
    ndarray, shape (P,)
        The mean over the samples t_i = i / rate (i >= 1) of ‖θd - θ‖ + ‖θ̇d - θ̇‖; +inf
        for a candidate that diverges or is unstable at the step, never NaN.

    """
    return TrackingProblem(arm, reference, duration, rate, step, max_speed).cost(gains)

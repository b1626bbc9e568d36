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
The tracking error of eq. (10) under a digital PD servo: sampled, held, saturated.

Why. :mod:`.tuning` tunes the paper's PD for a continuous servo with unlimited torque, and
there eq. (10) keeps falling as the gains grow: the optimum lies on the bounds, far from the
published Kp = diag(32.84, 42.05, 42.31), Kd = diag(42.44, 0.19, 4.86). A real servo is
digital and its actuators saturate, and both bound the useful gains: a derivative gain
with Kd T / M near 2 (T the servo period, M the joint's inertia) makes the sampled loop
oscillate or diverge, and a saturated torque no longer grows with the gain. This module
evaluates eq. (10) for such a servo, batched over a population of gains, so that
:func:`.tuning.tune_pd_gains` runs the paper's EA on it (``problem=``) and the study in
``tools/paper.py --pd-study`` can say which assumptions bring the optimum near the
published gains.

The servo. At every servo instant t_k = k / servo_rate it reads the exact state and the
reference there and applies τ_k = clip(Kp (θd - θ) + Kd (θ̇d - θ̇), ±τ_max) until the next
instant (zero-order hold). Between instants the torque is constant, so the arm alone is
integrated, by Runge-Kutta-Gill steps of at most ``step`` (the arm without the PD is not
stiff: its fastest eigenvalue allows 11 ms for the paper's arm, so the step is set by
accuracy, 1 ms by default). The error is sampled at ``rate`` as in :mod:`.tuning`: the mean
over t_i = i / rate, i >= 1, of ‖θd - θ‖ + ‖θ̇d - θ̇‖, from the state on the reference at 0.
A joint speed above ``max_speed`` or a non-finite state costs +inf.

:meth:`SampledTrackingProblem.cost` is one compiled kernel over the population (numba,
parallel over candidates); :meth:`SampledTrackingProblem.cost_numpy` is the plain numpy
reference on :func:`rkgnn_ros.core.integration.rkg.rkg_step` and ``PlanarArm.dynamics``; the
two agree to rounding.
"""

import math

from numba import get_parallel_chunksize, njit, prange, set_parallel_chunksize
import numpy as np

from .plant import PlanarArm
from .plant_kernels import forward_dynamics_into
from .simulate import MAX_SPEED, sample_count
from .tracking import diverged, planar_joints, sample_error, TrackingProblem
from .trajectories import Reference
from ..integration.rkg import gill_stage, rkg_step
from ..servo_law import compiled_pd_torque, pd_torque

__all__ = ['DEFAULT_STEP', 'SampledTrackingProblem']

#: Largest integration step between servo instants (s): the error of the held-torque
#: rollout is then far below the differences the study compares.
DEFAULT_STEP = 1e-3


@njit(cache=True, nogil=True, error_model='numpy')
def _held_torque_step(x, tau, h, d, gh, viscous, coulomb, coulomb_velocity, xs, f, q, work):
    """
    Advance x = [θ, θ̇] (2n,) in place by one RKG step of width ``h`` under the torque ``tau``.

    The stage loop of :func:`..integration.rkg.rkg_step` with its compiled stage update
    :func:`..integration.rkg.gill_stage`; ``xs``, ``f``, ``q`` (2n,) and ``work`` (n + 3, n)
    are the caller's buffers.
    """
    n = tau.shape[0]
    xs[:] = x
    for stage in range(4):
        f[:n] = xs[n:]
        forward_dynamics_into(xs[:n], xs[n:], tau, d, gh, viscous, coulomb, coulomb_velocity,
                              work, f[n:])
        gill_stage(stage, h, x, xs, f, q)


@njit(cache=True, nogil=True, error_model='numpy')
def _sampled_cost(x0, servo_ref, sample_ref, per_servo, per_sample, h, gains, p, limit,
                  d, gh, viscous, coulomb, coulomb_velocity, max_speed):
    """
    Return the eq. (10) cost of candidate ``p`` under the digital servo, or +inf.

    ``servo_ref`` (K, 2, n) holds θd, θ̇d at the servo instants, ``sample_ref`` (N, 2, n) at
    the error samples; the servo acts every ``per_servo`` steps of width ``h`` and the error
    is taken every ``per_sample`` steps. ``gains`` (P, 2n) are rows [Kp, Kd]; ``limit`` (n,)
    the torque limits (inf: none).
    """
    n = x0.shape[0] // 2
    x = x0.copy()
    th = x[:n]                          # views: the step updates x in place
    om = x[n:]
    tau = np.zeros(n)
    xs = np.empty(2 * n)
    f = np.empty(2 * n)
    q = np.empty(2 * n)
    work = np.empty((n + 3, n))
    n_steps = (sample_ref.shape[0] - 1) * per_sample
    total = 0.0
    for step in range(n_steps):
        if step % per_servo == 0:
            k = step // per_servo
            for i in range(n):
                u = compiled_pd_torque(gains[p, i], gains[p, n + i],
                                       servo_ref[k, 0, i] - th[i], servo_ref[k, 1, i] - om[i])
                tau[i] = min(max(u, -limit[i]), limit[i])
        _held_torque_step(x, tau, h, d, gh, viscous, coulomb, coulomb_velocity, xs, f, q,
                          work)
        if diverged(th, om, n, max_speed):
            return math.inf
        if (step + 1) % per_sample == 0:
            total += sample_error(sample_ref, (step + 1) // per_sample, th, om, n)
    return total / (sample_ref.shape[0] - 1)


@njit(cache=True, nogil=True, parallel=True, error_model='numpy')
def _population_cost(x0, servo_ref, sample_ref, per_servo, per_sample, h, gains, limit,
                     d, gh, viscous, coulomb, coulomb_velocity, max_speed, out):
    """Write the cost of every row of ``gains`` (P, 2n) into ``out`` (P,), in parallel."""
    for p in prange(gains.shape[0]):
        out[p] = _sampled_cost(x0, servo_ref, sample_ref, per_servo, per_sample, h, gains, p,
                               limit, d, gh, viscous, coulomb, coulomb_velocity, max_speed)


def _grid(rate: float, servo_rate: float, step: float):
    """
    Return (steps per servo period, steps per error sample, step) on one common grid.

    One of the two rates must be an integer multiple of the other (to 1e-9).
    """
    ratio = servo_rate / rate
    if abs(ratio - round(ratio)) < 1e-9 and round(ratio) >= 1:
        servos_per_sample, samples_per_servo = int(round(ratio)), 1
    elif abs(1.0 / ratio - round(1.0 / ratio)) < 1e-9:
        servos_per_sample, samples_per_servo = 1, int(round(1.0 / ratio))
    else:
        raise ValueError(f'servo_rate {servo_rate} Hz and rate {rate} Hz: one must be an '
                         'integer multiple of the other')
    per_servo = samples_per_servo * max(1, int(math.ceil(
        1.0 / (servo_rate * samples_per_servo * step) - 1e-9)))
    h = 1.0 / (servo_rate * per_servo)
    per_sample = per_servo * servos_per_sample // samples_per_servo
    return per_servo, per_sample, h


class SampledTrackingProblem:
    """
    Eq. (10) for a digital PD servo, batched over gains: the ``problem`` of ``tune_pd_gains``.

    Parameters
    ----------
    arm : PlanarArm
        The plant.
    reference : Reference
        Desired trajectory; the arm starts on it, x(0) = [θd(0), θ̇d(0)].
    duration : float
        Simulated time (s).
    servo_rate : float
        Servo rate (Hz): torque computed from the state every 1 / servo_rate s and held.
        It or ``rate`` must be an integer multiple of the other.
    torque_limit : float or array_like, shape (n,), optional
        Symmetric saturation |τ_i| <= torque_limit_i (N m); None: none.
    rate : float
        Sampling rate of the error (Hz).
    step : float
        Largest integration step (s).
    max_speed : float
        A joint speed above this (rad/s) is divergence.

    Attributes
    ----------
    h : float
        The integration step (s), a divisor of both periods.
    per_servo, per_sample : int
        Steps per servo period and per error sample.
    x0 : ndarray, shape (2n,)
        Start state.

    """

    def __init__(self, arm: PlanarArm, reference: Reference, duration: float,
                 servo_rate: float, torque_limit=None, rate: float = 100.0,
                 step: float = DEFAULT_STEP, max_speed: float = MAX_SPEED):
        self.arm = arm
        self.n = n = planar_joints(arm, reference)
        for name, value in (('duration', duration), ('servo_rate', servo_rate), ('rate', rate),
                            ('step', step), ('max_speed', max_speed)):
            if not (np.isfinite(value) and value > 0.0):
                raise ValueError(f'{name} must be positive, got {value}')
        n_samples = sample_count(duration, rate)
        self.rate, self.servo_rate = float(rate), float(servo_rate)
        self.max_speed = float(max_speed)
        self.per_servo, self.per_sample, self.h = _grid(self.rate, self.servo_rate, step)
        limit = np.inf if torque_limit is None else torque_limit
        self.torque_limit = np.broadcast_to(np.asarray(limit, dtype=float), (n,)).copy()
        if not np.all(self.torque_limit > 0.0):
            raise ValueError(f'torque_limit must be positive, got {torque_limit!r}')
        self.t = np.arange(n_samples) / self.rate
        n_servo = (n_samples - 1) * self.per_sample // self.per_servo + 1
        servo_t = np.arange(n_servo) * (self.per_servo * self.h)
        self.servo_reference = self._stacked(reference, servo_t)          # (K, 2, n)
        self.sample_reference = self._stacked(reference, self.t)          # (N, 2, n)
        self.x0 = self.sample_reference[0].reshape(-1).copy()
        self._constants = tuple(arm.kernel_constants())

    @staticmethod
    def _stacked(reference, times) -> np.ndarray:
        theta_d, theta_d_dot = reference.evaluate(times)
        return np.ascontiguousarray(np.stack([theta_d, theta_d_dot], axis=1))

    # the same check of the (P, 2n) gain rows as the continuous problem's (it reads self.n)
    _gains = TrackingProblem._gains

    def cost(self, gains) -> np.ndarray:
        """
        Return the tracking error of eq. (10) of every candidate (compiled, parallel).

        ``gains``: (P, 2n) rows as for :meth:`.tracking.TrackingProblem.cost`. Returns the
        (P,) costs; +inf for a candidate whose rollout diverges, never NaN.
        """
        g = self._gains(gains)
        out = np.empty(g.shape[0])
        chunksize = get_parallel_chunksize()
        set_parallel_chunksize(1)          # diverging candidates finish early
        try:
            _population_cost(self.x0, self.servo_reference, self.sample_reference,
                             self.per_servo, self.per_sample, self.h, g, self.torque_limit,
                             *self._constants, self.max_speed, out)
        finally:
            set_parallel_chunksize(chunksize)
        return out

    def cost_numpy(self, gains) -> np.ndarray:
        """Return :meth:`cost` computed in plain numpy (the reference), shape (P,)."""
        g = self._gains(gains)
        n = self.n
        x = np.tile(self.x0, (g.shape[0], 1))                           # (P, 2n)
        total = np.zeros(g.shape[0])
        diverged = np.zeros(g.shape[0], dtype=bool)
        n_steps = (self.t.size - 1) * self.per_sample
        with np.errstate(all='ignore'):
            for step in range(n_steps):
                if step % self.per_servo == 0:
                    ref = self.servo_reference[step // self.per_servo]     # (2, n)
                    tau = pd_torque(g[:, :n], g[:, n:], ref[0] - x[:, :n], ref[1] - x[:, n:])
                    tau = np.clip(tau, -self.torque_limit, self.torque_limit)
                x = rkg_step(self.arm.dynamics, x, self.h, tau, tau, tau)
                diverged |= ~(np.all(np.isfinite(x), axis=1)
                              & np.all(np.abs(x[:, n:]) <= self.max_speed, axis=1))
                x[diverged] = self.x0                                    # keep it tame
                if (step + 1) % self.per_sample == 0:
                    ref = self.sample_reference[(step + 1) // self.per_sample]
                    total += (np.linalg.norm(ref[0] - x[:, :n], axis=1)
                              + np.linalg.norm(ref[1] - x[:, n:], axis=1))
        out = total / (self.t.size - 1)
        out[diverged] = np.inf
        return out

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
The simulated arm stepped in real time: the state ``sim_arm`` publishes, without ROS.

:class:`ArmSimulator` holds the plant of :mod:`.plant` under the servo of :mod:`.servo`
tracking a reference, and advances it sample by sample as the node's clock asks. Between
samples the continuous plant is advanced by fixed Runge-Kutta-Gill steps
(:func:`..integration.rkg.rkg_step`, the package's 4-stage 4th-order Runge-Kutta; it has the
stability polynomial of classical RK4) of at most ``max_step`` seconds: each interval is
split into equal steps. The state is [θ, θ̇, I], I the servo's integral term. Without a
control rate the servo is continuous (the reference is evaluated at every stage time, I is
integrated with the plant); with one, a digital servo computes the torque from the true
state at t = j / control_rate and holds it (zero-order hold), its integral advancing once
per tick, and the steps end exactly at every tick. A feed-forward torque
(:attr:`ArmSimulator.feedforward`, a :class:`~.servo.FeedforwardTrack`) is added to the
servo's torque at the servo's time; the continuous steps end at its start and end, where it
jumps.

The steps run compiled (:func:`_rkg_pd_steps`: the stage loop with the shared stage update
:func:`..integration.rkg.gill_stage`, the plant's compiled forward dynamics and the servo's
compiled torque), held at start to the numpy step on the same state; ``compiled=False``
runs the numpy step itself (the only one for a URDF arm, whose dynamics are Pinocchio's).
The fixed step, unlike :mod:`.simulate`'s adaptive solvers, costs the same every sample,
which a real-time publisher needs.
"""

import math
from typing import NamedTuple, Optional, Tuple

from numba import njit
import numpy as np

from .plant import PlanarArm
from .plant_kernels import forward_dynamics_kernel
from .servo import (DEFAULT_WINDUP_TIME, FeedforwardTrack, Servo, servo_integral_rate_into,
                    servo_torque_into)
from .trajectories import Reference
from ..integration.rkg import gill_node, gill_stage, rkg_step

__all__ = ['ArmSimulator', 'SimulationDiverged', 'TIME_TOL']

#: Simulation times closer than this (s) are the same instant (controller ticks, samples).
TIME_TOL = 1e-9


class SimulationDiverged(RuntimeError):
    """The simulated state became non-finite or exceeded ``max_speed``."""


@njit(cache=True, nogil=True)
def _pd_rate(x, ref, j, tau_held, servo, d, gh, fv, fc, vc, out):
    """
    Write ẋ = [θ̇, θ̈, İ] of the servo's closed loop at ``x`` (3n,) into ``out`` (3n,).

    The state is [θ, θ̇, I], I the servo's integral term (N m). With ``ref`` of shape
    (K, 2, n) (K > 0) the torque is the continuous servo torque towards θd = ref[j, 0],
    θ̇d = ref[j, 1] (:func:`.servo.servo_torque_into`, ``servo`` its
    :class:`~.servo.ServoConstants`), plus τ_ff = ref[j, 2] when ``ref`` has shape
    (K, 3, n); with K = 0 it is ``tau_held`` (n,) and I
    does not move (a digital servo advances it at its ticks). θ̈ comes from the plant's
    compiled single-state kernel (the arithmetic of ``PlanarArm.forward_dynamics``); ``d``,
    ``gh`` are the arm's constants and ``fv``, ``fc``, ``vc`` its viscous and Coulomb
    friction and Coulomb smoothing velocity.
    """
    n = x.shape[0] // 3
    theta = x[:n]
    theta_dot = x[n:2 * n]
    if ref.shape[0] > 0:
        raw = np.empty(n)
        tau = np.empty(n)
        if ref.shape[1] > 2:  # a feed-forward torque in ref[j, 2]
            servo_torque_into(servo, theta, theta_dot, ref[j, 0], ref[j, 1], x[2 * n:], raw,
                              tau, ref[j, 2])
        else:
            servo_torque_into(servo, theta, theta_dot, ref[j, 0], ref[j, 1], x[2 * n:], raw,
                              tau)
        servo_integral_rate_into(servo, theta, ref[j, 0], raw, tau, out[2 * n:])
    else:
        tau = tau_held
        out[2 * n:] = 0.0
    out[:n] = theta_dot
    out[n:2 * n] = forward_dynamics_kernel(theta, theta_dot, tau, d, gh, fv, fc, vc)


@njit(cache=True, nogil=True)
def _rkg_pd_steps(x, h, steps, ref, tau_held, servo, d, gh, fv, fc, vc):
    """
    Return ``x`` (3n,) advanced by ``steps`` Runge-Kutta-Gill steps of width ``h``.

    The stage loop of :func:`..integration.rkg.rkg_step` with its compiled stage update
    (:func:`..integration.rkg.gill_stage`) applied to :func:`_pd_rate`: ``ref``
    (2 steps + 1, 2 or 3, n) holds θd, θ̇d (and τ_ff) at the stage times t + k h/2, or has
    shape (0, 2, n) for the held torque ``tau_held``. The other arguments are those of
    :func:`_pd_rate`.
    """
    m = x.shape[0]
    x = x.copy()
    f = np.empty(m)
    q = np.empty(m)
    y = np.empty(m)
    for i in range(steps):
        y[:] = x
        for stage in range(4):
            _pd_rate(y, ref, 2 * i + gill_node(stage), tau_held, servo, d, gh, fv, fc, vc, f)
            gill_stage(stage, h, x, y, f, q)
    return x


class ServoOptions(NamedTuple):
    """The servo's options of :class:`ArmSimulator` beyond its gains (see there)."""

    compiled: bool = True
    ki: object = 0.0
    tau_limit: object = None
    gravity_compensation: str = 'none'
    windup_time: float = DEFAULT_WINDUP_TIME


class ArmSimulator:
    """
    Fixed-step simulation of an arm under its servo tracking a reference.

    Simulation time ``t`` starts at 0, the reference's time origin, with the arm on the
    reference. :meth:`advance` integrates to a later time; :meth:`sample` reports the state,
    the applied torque and the desired trajectory at the current time.

    Parameters
    ----------
    arm : PlanarArm or UrdfArm
        The plant; a URDF arm (no compiled kernel) needs ``compiled=False``.
    kp, kd : array_like, shape (n,)
        Diagonal PD gains.
    reference : Reference
        Desired trajectory θd(t), θ̇d(t).
    max_step : float
        Largest integration step (s); every interval is split into equal steps.
    control_rate : float, optional
        None or 0: continuous PD. Otherwise a digital PD at this rate (Hz) with zero-order
        hold, ticking at t = j / control_rate.
    max_speed : float
        A joint speed above this (rad/s), or a non-finite state, raises
        :class:`SimulationDiverged`.
    ki, tau_limit, gravity_compensation, windup_time
        The rest of the servo (:class:`~.servo.Servo`): integral gains (the
        integral term is ``x[2n:]``, starting at 0), torque limits (None: none), Ĝ from
        the arm's own model on the 'measured' or 'desired' position ('none': without),
        back-calculation time constant.

    Attributes
    ----------
    feedforward : FeedforwardTrack or None
        A feed-forward torque on the simulation's time axis, added to the servo's torque
        (zero outside its points); None: the servo alone.

    """

    def __init__(self, arm: PlanarArm, kp, kd, reference: Reference, max_step: float,
                 control_rate: Optional[float] = None, max_speed: float = 100.0, **options):
        compiled, ki, tau_limit, gravity_compensation, windup_time = ServoOptions(**options)
        self.arm = arm
        self.n = n = arm.n_joints
        self.servo = Servo(np.asarray(kp, dtype=float), np.asarray(kd, dtype=float), ki=ki,
                           tau_limit=tau_limit, gravity=gravity_compensation, arm=arm,
                           windup_time=windup_time)
        if self.servo.n_joints != n:
            raise ValueError(f'the gains have {self.servo.n_joints} joints, the arm {n}')
        if reference.n_joints != n:
            raise ValueError(f'reference has {reference.n_joints} joints, the arm {n}')
        self.reference = reference
        self.max_step = float(max_step)
        self.max_speed = float(max_speed)
        self.control_period = 1.0 / control_rate if control_rate else None
        self.compiled = bool(compiled)
        # the servo's record and the plant's compiled-kernel constants (planar arm only)
        self._constants = ((self.servo.constants(),) + tuple(arm.kernel_constants())
                           if self.compiled else None)
        self._no_ref = np.empty((0, 2, n))
        self._no_tau = np.zeros(n)
        theta_d, theta_d_dot = reference.evaluate(0.0)
        self.x = np.concatenate([theta_d, theta_d_dot, np.zeros(n)])   # (3n,) [θ, θ̇, I]
        self.t = 0.0
        self._tick = 0                                        # index of the next tick
        self._held_tau = None
        self.feedforward: Optional[FeedforwardTrack] = None
        if self.compiled:
            self._check_compiled()
        self._update_digital()

    # -- public ---------------------------------------------------------------------------

    def set_payload(self, mass: float, com=(0.0, 0.0, 0.0)) -> None:
        """
        Carry a point mass ``mass`` (kg) at ``com`` (m) on the last link from now on (0: none).

        The plant changes (:func:`.payload.with_payload` of the nominal arm); the servo's
        gravity compensation keeps the nominal model, as a real servo's does.
        """
        from .payload import with_payload
        nominal = getattr(self, '_nominal', None) or self.arm
        self._nominal = nominal
        self.arm = nominal if float(mass) == 0.0 else with_payload(nominal, mass, com)
        if self.compiled:
            self._constants = ((self.servo.constants(),)
                               + tuple(self.arm.kernel_constants()))

    def sample(self) -> Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """
        Return θ, θ̇, the applied torque τ, θd and θ̇d at the current time, each (n,).

        τ is the continuous PD torque at this instant, or the held digital torque (at a
        controller tick the newly computed one).
        """
        n = self.n
        theta, theta_dot = self.x[:n].copy(), self.x[n:2 * n].copy()
        theta_d, theta_d_dot = self.reference.evaluate(float(self.t))
        if self.control_period is None:
            tau = self.servo.torque(theta, theta_dot, theta_d, theta_d_dot, self.x[2 * n:],
                                    self._feedforward_at(self.t))
        else:
            tau = self._held_tau.copy()
        return theta, theta_dot, tau, theta_d, theta_d_dot

    def advance(self, t_end: float):
        """
        Integrate from the current time to ``t_end`` (s).

        Raises
        ------
        SimulationDiverged
            If the state becomes non-finite or a joint speed exceeds ``max_speed``.

        """
        t_end = float(t_end)
        with np.errstate(over='ignore', invalid='ignore', divide='ignore'):
            while self.t < t_end - TIME_TOL:
                if self.control_period is None:
                    stop = self._feedforward_edge(t_end)
                    self._integrate_continuous(self.t, stop)
                    self.t = stop
                else:
                    stop = min(t_end, self._tick * self.control_period)
                    self._integrate_held(self.t, stop)
                    self.t = stop
                    self._update_digital()
                self._check()

    # -- internals ------------------------------------------------------------------------

    def _feedforward_at(self, t):
        """Return τ_ff at time(s) ``t`` ((n,) or (T, n)), or None without a feed-forward."""
        return None if self.feedforward is None else self.feedforward.evaluate(t)

    def _feedforward_edge(self, t_end: float) -> float:
        """Return the feed-forward's start or end if it lies before ``t_end``, else t_end."""
        if self.feedforward is not None:
            for edge in (self.feedforward.start, self.feedforward.end):
                if self.t + TIME_TOL < edge < t_end - TIME_TOL:
                    return edge
        return t_end

    def _steps(self, span: float) -> int:
        return max(1, int(math.ceil(span / self.max_step - 1e-9)))

    def _f_pd(self, x, u):
        """Return ẋ (3n,) under the continuous servo; ``u`` (2 or 3, n): θd, θ̇d, τ_ff."""
        n = self.n
        theta, theta_dot = x[:n], x[n:2 * n]
        raw, tau = self.servo.torques(theta, theta_dot, u[0], u[1], x[2 * n:],
                                      u[2] if u.shape[0] > 2 else None)
        out = np.empty(3 * n)
        out[:n] = theta_dot
        out[n:2 * n] = self.arm.forward_dynamics(theta, theta_dot, tau)
        out[2 * n:] = self.servo.integral_rate(theta, u[0], raw, tau)
        return out

    def _f_held(self, x, tau):
        """Return ẋ (3n,) under a given torque ``tau`` (n,); the integral does not move."""
        n = self.n
        out = np.zeros(3 * n)
        out[:n] = x[n:2 * n]
        out[n:2 * n] = self.arm.forward_dynamics(x[:n], x[n:2 * n], tau)
        return out

    def _integrate_continuous(self, t_a: float, t_b: float):
        steps = self._steps(t_b - t_a)
        h = (t_b - t_a) / steps
        # every stage time t_a + k h/2 (k = 0 .. 2 steps) in one vectorised evaluation
        stage_t = t_a + 0.5 * h * np.arange(2 * steps + 1)
        stage_t[-1] = t_b
        theta_d, theta_d_dot = self.reference.evaluate(stage_t)     # (2s+1, n) each
        rows = [theta_d, theta_d_dot]
        if self.feedforward is not None:
            # τ_ff jumps at the track's start and end (advance() integrates up to them): at
            # the interval's ends take its value from inside the interval
            inset = min(TIME_TOL, 0.25 * (t_b - t_a))
            rows.append(self._feedforward_at(np.clip(stage_t, t_a + inset, t_b - inset)))
        u = np.stack(rows, axis=1)                                  # (2s+1, 2 or 3, n)
        if self.compiled:
            self.x = _rkg_pd_steps(self.x, h, steps, u, self._no_tau, *self._constants)
            return
        x, f = self.x, self._f_pd
        for i in range(steps):
            x = rkg_step(f, x, h, u[2 * i], u[2 * i + 1], u[2 * i + 2])
        self.x = x

    def _integrate_held(self, t_a: float, t_b: float):
        steps = self._steps(t_b - t_a)
        h = (t_b - t_a) / steps
        tau = self._held_tau
        if self.compiled:
            self.x = _rkg_pd_steps(self.x, h, steps, self._no_ref, tau, *self._constants)
            return
        x, f = self.x, self._f_held
        for _ in range(steps):
            x = rkg_step(f, x, h, tau, tau, tau)
        self.x = x

    def _compiled_matches(self) -> bool:
        """Return whether one compiled step equals the numpy step from the start state."""
        h = self.max_step
        stage_t = np.array([0.0, 0.5 * h, h])
        theta_d, theta_d_dot = self.reference.evaluate(stage_t)
        u = np.stack([theta_d, theta_d_dot], axis=1)
        x0 = self.x + 0.01            # off the reference, so that the torque is not zero
        compiled = _rkg_pd_steps(x0, h, 1, u, self._no_tau, *self._constants)
        reference = rkg_step(self._f_pd, x0, h, u[0], u[1], u[2])
        scale = np.max(np.abs(reference - x0)) + 1e-300
        return bool(np.max(np.abs(compiled - reference)) <= 1e-9 * scale)

    def _check_compiled(self):
        """
        Hold the compiled step to the numpy step; recompile once if they differ.

        numba's on-disk cache does not notice a change of the plant's kernel in another file,
        so a stale cached :func:`_rkg_pd_steps` is recompiled here.
        """
        if self._compiled_matches():
            return
        _pd_rate.recompile()
        _rkg_pd_steps.recompile()
        if not self._compiled_matches():
            raise RuntimeError('the compiled simulation step disagrees with the numpy step '
                               '(PlanarArm.forward_dynamics); use compiled=False')

    def _update_digital(self):
        """
        At a controller tick, compute and hold the torque from the true state.

        The servo's integral term advances by one forward-Euler step of its period.
        """
        if self.control_period is None:
            return
        tick_time = self._tick * self.control_period
        if tick_time <= self.t + TIME_TOL:
            n = self.n
            theta, theta_dot, integral = self.x[:n], self.x[n:2 * n], self.x[2 * n:]
            theta_d, theta_d_dot = self.reference.evaluate(float(tick_time))
            raw, self._held_tau = self.servo.torques(theta, theta_dot, theta_d, theta_d_dot,
                                                     integral, self._feedforward_at(tick_time))
            rate = self.servo.integral_rate(theta, theta_d, raw, self._held_tau)
            self.x = np.concatenate([self.x[:2 * n], integral + self.control_period * rate])
            self._tick += 1

    def _check(self):
        speed = np.abs(self.x[self.n:2 * self.n])
        if not (np.all(np.isfinite(self.x)) and np.max(speed) <= self.max_speed):
            raise SimulationDiverged(
                f'the simulation diverged at t = {self.t:.6g} s (state {self.x}, max_speed '
                f'{self.max_speed} rad/s): is integration_step small enough, or (digital '
                'control) control_rate high enough for the gains?')

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
The ``sim_arm`` node: the planar arm (or a URDF arm) under its servo, simulated in real time.

The plant of :mod:`rkgnn_ros.core.sim.plant` (``PlanarArm``) tracks a reference of
:mod:`rkgnn_ros.core.sim.trajectories` under the servo of :mod:`rkgnn_ros.core.sim.servo`:
by default the paper's PD τ = Kp (θd - θ) + Kd (θ̇d - θ̇); with ``ki`` a PID (with
back-calculation anti-windup, ``windup_time``), with ``gravity_compensation`` plus the
arm's own gravity torque at θ or θd, with ``tau_limit`` saturating drives. It runs on the
node's clock (``use_sim_time`` is honoured like in any node). What ``joint_states``
carries is what a driver publishes (:mod:`rkgnn_ros.core.sim.sensors`): ``sensors.*``.

Topics (published)
------------------
``joint_states`` (sensor_msgs/JointState, reliable, volatile, depth 10)
    θ in ``position`` (with the optional encoder noise), θ̇ in ``velocity`` as
    ``sensors.velocity`` says (sensed with noise, differenced, low-pass filtered, or an
    empty field), the applied torque τ in ``effort`` (the servo's torque at that instant
    after saturation, or the held torque of a digital servo; never noisy; an empty field
    when ``sensors.effort`` is false).
``joint_commands`` (sensor_msgs/JointState, reliable, volatile, depth 10)
    θd in ``position``, θ̇d in ``velocity``, NaN in ``effort``; the same stamps as
    ``joint_states``.
``reference_trajectory`` (trajectory_msgs/JointTrajectory, reliable, transient local, depth 1)
    θd and θ̇d over the next ``reference_horizon`` seconds every ``reference_dt`` seconds,
    stamped with the stamp of the state it was published with (``time_from_start`` 0 is
    that state's command). Transient local so that a late subscriber gets the current one
    at once; a volatile subscriber is compatible too.
``robot_description`` (std_msgs/String, reliable, transient local, depth 1)
    With a URDF arm (:mod:`rkgnn_ros.arm_model`): its URDF with the locked joints fixed,
    once at start, for robot_state_publisher and rviz.

Timing
------
Simulation time τ starts at 0 (the reference's time origin) at the first clock reading
that is not zero (under ``use_sim_time`` the node waits for ``/clock``); the arm starts on
the reference, x(0) = [θd(0), θ̇d(0)]. Sample m is at τ_m = m / ``publish_rate`` and is
stamped ``origin + τ_m``, so stamps are exactly uniform. A timer at ``publish_rate`` on
the node's clock computes which samples are due from the clock (never by counting timer
calls, so the simulation cannot drift), integrates up to each and publishes it. If the
node falls behind by more than :data:`CATCH_UP_LIMIT` seconds it does not try to catch
up: the simulation pauses for the missed time (the origin moves forward, the next sample
is stamped with the current time), the skip is counted and logged (throttled). If the
clock jumps backwards (a replayed bag starting over) the origin moves back the same way.

Integration
-----------
Between samples the continuous plant is advanced by fixed Runge-Kutta-Gill steps
(:func:`.core.integration.rkg.rkg_step`, the package's 4-stage 4th-order Runge-Kutta; it has
the stability polynomial of classical RK4) of at most ``integration_step`` seconds: each
interval is split into equal steps. The state is [θ, θ̇, I], I the servo's integral term.
With ``control_rate`` = 0 the servo is continuous (the reference is evaluated at every
stage time, I is integrated with the plant); with ``control_rate`` > 0 a digital servo
computes the torque from the true state at τ = j / ``control_rate`` and holds it (zero-order
hold), its integral advancing once per tick, and the steps end exactly at every tick.
``integration_step`` is checked at start against the closed-loop stiffness at the start
state (:meth:`PlanarArm.stable_step`); an unstable step is refused.

All parameters are read-only (set them at start; they define the simulated system)
except ``noise.theta_std`` and ``noise.theta_dot_std``, which can be changed at any time.
"""

from functools import partial
import math
import sys
import traceback
from typing import List, NamedTuple, Optional, Tuple

from numba import njit
import numpy as np
from rcl_interfaces.msg import SetParametersResult
import rclpy
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.task import Future
from rclpy.time import Time
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from trajectory_msgs.msg import JointTrajectory

from .arm_model import build_urdf_arm, reference_limit_warning, URDF_PARAMETERS
from .conversions import make_joint_state, make_joint_trajectory
from .core.integration.rkg import ALPHA, BETA, D, E, G, GAMMA, rkg_step
from .core.sim.plant import (ArmParameters, forward_dynamics_kernel, MASS_MODELS,
                             max_stable_rkg_step, PlanarArm, RK4_REAL_STABILITY_LIMIT)
from .core.sim.sensors import SensorModel, VELOCITY_SOURCES
from .core.sim.servo import (DEFAULT_WINDUP_TIME, GRAVITY_MODES, Servo,
                             servo_integral_rate_into, servo_torque_into)
from .core.sim.trajectories import Chirp, hanging_pose, paper_reference, Reference, SumOfSines
from .parameters import Change, ParameterSpec

NODE_NAME = 'sim_arm'

#: Reference kinds of the ``reference.type`` parameter.
REFERENCE_TYPES = ('paper', 'sines', 'chirp')

#: Falling behind the clock by more than this (s) skips ahead instead of catching up.
CATCH_UP_LIMIT = 0.5

#: Most points in one reference_trajectory message.
MAX_REFERENCE_POINTS = 100_000

#: Simulation times closer than this (s) are the same instant (controller ticks, samples).
_TIME_TOL = 1e-9

_NANO = 1_000_000_000


class ConfigurationError(ValueError):
    """An invalid parameter at start; the message names the parameter."""


class SimulationDiverged(RuntimeError):
    """The simulated state became non-finite or exceeded ``max_speed``."""


# -- the simulation (numpy and numba, no rclpy) -------------------------------------------


@njit(cache=True, nogil=True)
def _pd_rate(x, ref, j, tau_held, servo, d, gh, fv, fc, vc, out):
    """
    Write ẋ = [θ̇, θ̈, İ] of the servo's closed loop at ``x`` (3n,) into ``out`` (3n,).

    The state is [θ, θ̇, I], I the servo's integral term (N m). With ``ref`` of shape
    (K, 2, n) (K > 0) the torque is the continuous servo torque towards θd = ref[j, 0],
    θ̇d = ref[j, 1] (:func:`.core.sim.servo.servo_torque_into`, ``servo`` its
    :class:`~.core.sim.servo.ServoConstants`); with K = 0 it is ``tau_held`` (n,) and I
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
        servo_torque_into(servo, theta, theta_dot, ref[j, 0], ref[j, 1], x[2 * n:], raw, tau)
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

    The compiled twin of :func:`.core.integration.rkg.rkg_step` (Gill's coefficients imported
    from there) applied to :func:`_pd_rate`: ``ref`` (2 steps + 1, 2, n) holds θd, θ̇d at the
    stage times t + k h/2, or has shape (0, 2, n) for the held torque ``tau_held``. The
    other arguments are those of :func:`_pd_rate`.
    """
    m = x.shape[0]
    x = x.copy()
    f = np.empty(m)
    q = np.empty(m)
    y = np.empty(m)
    for i in range(steps):
        j = 2 * i
        _pd_rate(x, ref, j, tau_held, servo, d, gh, fv, fc, vc, f)
        for r in range(m):
            k = h * f[r]
            y[r] = x[r] + 0.5 * k
            q[r] = k
        _pd_rate(y, ref, j + 1, tau_held, servo, d, gh, fv, fc, vc, f)
        for r in range(m):
            k = h * f[r]
            y[r] += ALPHA * (k - q[r])
            q[r] = BETA * q[r] + E * k
        _pd_rate(y, ref, j + 1, tau_held, servo, d, gh, fv, fc, vc, f)
        for r in range(m):
            k = h * f[r]
            y[r] += D * (k - q[r])
            q[r] = GAMMA * q[r] + G * k
        _pd_rate(y, ref, j + 2, tau_held, servo, d, gh, fv, fc, vc, f)
        for r in range(m):
            x[r] = y[r] + h * f[r] / 6.0 - q[r] / 3.0
    return x


class ArmSimulator:
    """
    Fixed-step simulation of an arm under its servo tracking a reference.

    Simulation time ``t`` starts at 0, the reference's time origin, with the arm on the
    reference. :meth:`advance` integrates to a later time; :meth:`sample` reports the state,
    the applied torque and the desired trajectory at the current time.

    Parameters
    ----------
    arm : PlanarArm
        The plant.
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
        The rest of the servo (:class:`~.core.sim.servo.Servo`): integral gains (the
        integral term is ``x[2n:]``, starting at 0), torque limits (None: none), Ĝ from
        the arm's own model on the 'measured' or 'desired' position ('none': without),
        back-calculation time constant.

    """

    def __init__(self, arm: PlanarArm, kp, kd, reference: Reference, max_step: float,
                 control_rate: Optional[float] = None, max_speed: float = 100.0,
                 compiled: bool = True, *, ki=0.0, tau_limit=None,
                 gravity_compensation: str = 'none',
                 windup_time: float = DEFAULT_WINDUP_TIME):
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
        if self.compiled:
            self._check_compiled()
        self._update_digital()

    # -- public ---------------------------------------------------------------------------

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
            tau = self.servo.torque(theta, theta_dot, theta_d, theta_d_dot, self.x[2 * n:])
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
            while self.t < t_end - _TIME_TOL:
                if self.control_period is None:
                    self._integrate_continuous(self.t, t_end)
                    self.t = t_end
                else:
                    stop = min(t_end, self._tick * self.control_period)
                    self._integrate_held(self.t, stop)
                    self.t = stop
                    self._update_digital()
                self._check()

    # -- internals ------------------------------------------------------------------------

    def _steps(self, span: float) -> int:
        return max(1, int(math.ceil(span / self.max_step - 1e-9)))

    def _f_pd(self, x, u):
        """Return ẋ (3n,) under the continuous servo; ``u`` (2, n) holds θd and θ̇d."""
        n = self.n
        theta, theta_dot = x[:n], x[n:2 * n]
        raw, tau = self.servo.torques(theta, theta_dot, u[0], u[1], x[2 * n:])
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
        u = np.stack([theta_d, theta_d_dot], axis=1)                # (2s+1, 2, n)
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
        if tick_time <= self.t + _TIME_TOL:
            n = self.n
            theta, theta_dot, integral = self.x[:n], self.x[n:2 * n], self.x[2 * n:]
            theta_d, theta_d_dot = self.reference.evaluate(float(tick_time))
            raw, self._held_tau = self.servo.torques(theta, theta_dot, theta_d, theta_d_dot,
                                                     integral)
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


# -- parameters ---------------------------------------------------------------------------


#: A row of the table below: set at start unless it says ``change=Change.LIVE``.
_Spec = partial(ParameterSpec, change=Change.START)

_MAX_INT = 2 ** 31 - 1

#: Every parameter: name, default (also in config/sim_arm.yaml), description, range.
PARAMETERS = (
    _Spec('joint_names', ['joint1', 'joint2', 'joint3'],
          'Names of the n joints, base to tip; n is their count.',
          constraints='at least one; unique, non-empty names'),
    _Spec('masses', [6.0, 4.0, 3.0], 'Link masses m_i (kg).',
          constraints='n values, each > 0'),
    _Spec('lengths', [0.2, 0.3, 0.1], 'Link lengths l_i (m).',
          constraints='n values, each > 0'),
    _Spec('mass_model', 'point',
          "'point': each mass at the tip of its link; 'rod': uniform slender rods.",
          constraints="'point' or 'rod'"),
    _Spec('gravity', 9.81, 'Gravitational acceleration along -y (m/s^2).', 0.0, 100.0),
    _Spec('viscous', [0.5, 0.3, 0.1], 'Viscous friction coefficients (N m s/rad).',
          constraints='n values, each >= 0'),
    _Spec('coulomb', [0.3, 0.2, 0.1],
          'Coulomb friction levels (N m), smoothed as coulomb * tanh(v / coulomb_velocity).',
          constraints='n values, each >= 0'),
    _Spec('coulomb_velocity', 0.05, 'Smoothing velocity of the Coulomb friction (rad/s).',
          1e-6, 100.0),
    _Spec('kp', [32.84, 42.05, 42.31], 'Proportional gains, diagonal (N m/rad).',
          constraints='n values, each >= 0'),
    _Spec('kd', [42.44, 0.19, 4.86], 'Derivative gains, diagonal (N m s/rad).',
          constraints='n values, each >= 0'),
    _Spec('ki', [0.0],
          'Integral gains, diagonal (N m/(rad s)); 0 = no integral term (a PD servo).',
          constraints='n values or one for every joint, each >= 0'),
    _Spec('gravity_compensation', 'none',
          "Gravity torque the servo adds from the arm's own model: 'none', 'measured' "
          "(at the measured position) or 'desired' (at the commanded position).",
          constraints="'none', 'measured' or 'desired'"),
    _Spec('tau_limit', [0.0],
          'Torque limits of the drives (N m); the applied, published torque is clipped to '
          '+-limit; 0 = no limit.', constraints='n values or one for every joint, each >= 0'),
    _Spec('windup_time', DEFAULT_WINDUP_TIME,
          'Back-calculation anti-windup time constant of the integral term (s).',
          1e-4, 1e4),
    _Spec('reference.type', 'paper',
          "Desired trajectory: 'paper' (fixed sums of sines about the hanging pose), "
          "'sines' (random sums of sines, reference.seed), 'chirp' (linear chirp).",
          constraints="'paper', 'sines' or 'chirp'"),
    _Spec('reference.seed', 1, "Seed of the random sines of reference.type 'sines'.",
          0, _MAX_INT),
    _Spec('reference.amplitude', 0.5,
          "Amplitude per joint (rad) of 'sines' (sum of the sines' amplitudes) and 'chirp'; "
          "'paper' has fixed amplitudes.", 0.0, math.pi),
    _Spec('reference.n_terms', 3, "Sines per joint of 'sines'.", 1, 20),
    _Spec('reference.min_frequency', 0.1, "Lowest frequency of 'sines' (Hz).", 0.001, 50.0),
    _Spec('reference.max_frequency', 0.8,
          "Highest frequency of 'sines' (Hz), >= reference.min_frequency.", 0.001, 50.0),
    _Spec('reference.chirp_start_frequency', 0.05, "Start frequency of 'chirp' (Hz).",
          0.0, 50.0),
    _Spec('reference.chirp_end_frequency', 1.0,
          "Frequency of 'chirp' at the end of its sweep, held afterwards (Hz).", 0.0, 50.0),
    _Spec('reference.chirp_duration', 60.0, "Sweep time of 'chirp' (s).", 0.01, 1e9),
    _Spec('noise.theta_std', 0.0,
          'Standard deviation of the white noise on the published positions (rad); '
          'may be changed at run time.', 0.0, 1.0, change=Change.LIVE),
    _Spec('noise.theta_dot_std', 0.0,
          'Standard deviation of the white noise on the published velocities (rad/s) when '
          "sensors.velocity is 'sensor'; may be changed at run time.", 0.0, 100.0,
          change=Change.LIVE),
    _Spec('sensors.velocity', 'sensor',
          "What the driver publishes as velocity: 'sensor' (true velocity plus "
          "noise.theta_dot_std), 'difference' (backward difference of the published "
          "positions), 'filtered' (that difference through a first-order low-pass at "
          "sensors.velocity_cutoff) or 'none' (an empty velocity field).",
          constraints="'sensor', 'difference', 'filtered' or 'none'"),
    _Spec('sensors.velocity_cutoff', 20.0,
          "Cut-off of the low-pass of sensors.velocity 'filtered' (Hz).", 0.01, 1e4),
    _Spec('sensors.effort', True,
          'Publish the applied torque as effort; false: an empty effort field (a driver '
          'without torque sensing).'),
    _Spec('seed', 0, 'Seed of the measurement noise generator.', 0, _MAX_INT),
    _Spec('publish_rate', 100.0, 'Rate of joint_states and joint_commands (Hz).',
          1.0, 10000.0),
    _Spec('control_rate', 0.0,
          'Rate of a digital PD with zero-order hold (Hz); 0 = continuous-time PD.',
          0.0, 1e6),
    _Spec('integration_step', 0.0005,
          'Largest fixed Runge-Kutta step (s); must be stable for the closed loop.',
          1e-6, 0.1),
    _Spec('max_speed', 100.0,
          'A joint speed above this (rad/s) means the simulation diverged: the node stops '
          'with an error.', 1e-3, 1e6),
    _Spec('reference_horizon', 3.0, 'Time covered by each reference_trajectory (s).',
          0.0, 3600.0),
    _Spec('reference_dt', 0.02, 'Spacing of the reference_trajectory points (s).',
          1e-4, 10.0),
    _Spec('reference_rate', 2.0,
          'Rate of reference_trajectory (Hz): it goes out with every k-th state, '
          'k = floor(publish_rate / reference_rate), so never less often than asked.',
          1.0, 10000.0),
    _Spec('duration', 0.0,
          'Seconds of clock time from the start of the simulation after which the node exits '
          'cleanly (exit code 0); 0 = run forever.',
          0.0, 1e9),
) + URDF_PARAMETERS

_BY_NAME = {spec.name: spec for spec in PARAMETERS}


class SimConfig(NamedTuple):
    """The validated settings of a :class:`SimArm`."""

    joint_names: Tuple[str, ...]
    arm: PlanarArm                   # or a UrdfArm (robot_description)
    robot_description: str           # the URDF arm's (reduced) URDF, '' for the planar arm
    kp: np.ndarray
    kd: np.ndarray
    ki: np.ndarray
    gravity_compensation: str
    tau_limit: Optional[np.ndarray]
    windup_time: float
    sensors: SensorModel
    reference: Reference
    reference_type: str
    seed: int
    theta_std: float
    theta_dot_std: float
    publish_rate: float
    control_rate: float
    integration_step: float
    stable_step: float
    max_speed: float
    reference_horizon: float
    reference_dt: float
    reference_rate: float
    duration: float


def _joint_vector(values: dict, name: str, n: int, *, positive: bool,
                  broadcast: bool = False) -> np.ndarray:
    arr = np.asarray(values[name], dtype=float)
    if broadcast and arr.shape == (1,):
        arr = np.full(n, arr[0])
    if arr.shape != (n,):
        raise ConfigurationError(
            f'{name} has {arr.size} values but the arm has {n} joints; give one per joint'
            + (' or one for every joint' if broadcast else ''))
    if not np.all(np.isfinite(arr)):
        raise ConfigurationError(f'{name} must be finite, got {arr.tolist()}')
    bad = arr <= 0.0 if positive else arr < 0.0
    if np.any(bad):
        bound = '> 0' if positive else '>= 0'
        raise ConfigurationError(f'{name} must all be {bound}, got {arr.tolist()}')
    return arr


def _build_reference(values: dict, n: int, offsets=None) -> Reference:
    kind = values['reference.type']
    if kind not in REFERENCE_TYPES:
        raise ConfigurationError(
            f'reference.type must be one of {list(REFERENCE_TYPES)}, got {kind!r}')
    offsets = hanging_pose(n) if offsets is None else offsets
    if kind == 'paper':
        paper = paper_reference(n)
        return SumOfSines(offsets, paper.amplitudes, paper.frequencies_hz, paper.phases)
    amplitude = values['reference.amplitude']
    if kind == 'sines':
        low, high = values['reference.min_frequency'], values['reference.max_frequency']
        if low > high:
            raise ConfigurationError(
                f'reference.min_frequency ({low} Hz) must not exceed reference.max_frequency '
                f'({high} Hz)')
        rng = np.random.default_rng(values['reference.seed'])
        return SumOfSines.random(n, rng, n_terms=values['reference.n_terms'],
                                 amplitude=amplitude, max_frequency_hz=high,
                                 min_frequency_hz=low, offsets=offsets)
    return Chirp(offsets, np.full(n, amplitude),
                 values['reference.chirp_start_frequency'],
                 values['reference.chirp_end_frequency'], values['reference.chirp_duration'])


def build_config(values: dict) -> Tuple[SimConfig, List[str]]:
    """
    Validate parameter values (name -> value) and build the simulated system.

    Returns the configuration and a list of warnings. Raises :class:`ConfigurationError`
    naming the offending parameter. Ranges of scalar parameters are enforced by rclpy
    through their descriptors before this runs; they are checked here only where the
    array parameters or cross-parameter rules need it.
    """
    warnings = []
    urdf = build_urdf_arm(values, ConfigurationError)
    names = (urdf.joint_names if urdf is not None
             else tuple(str(name) for name in values['joint_names']))
    if not names or any(not name for name in names):
        raise ConfigurationError(
            f'joint_names must list at least one non-empty name, got {list(names)}')
    if len(set(names)) != len(names):
        raise ConfigurationError(f'joint_names must be unique, got {list(names)}')
    n = len(names)
    viscous = _joint_vector(values, 'viscous', n, positive=False)
    coulomb = _joint_vector(values, 'coulomb', n, positive=False)
    kp = _joint_vector(values, 'kp', n, positive=False)
    kd = _joint_vector(values, 'kd', n, positive=False)
    ki = _joint_vector(values, 'ki', n, positive=False, broadcast=True)
    tau_limit = _joint_vector(values, 'tau_limit', n, positive=False, broadcast=True)
    if values['gravity_compensation'] not in GRAVITY_MODES:
        raise ConfigurationError(
            f'gravity_compensation must be one of {list(GRAVITY_MODES)}, got '
            f'{values["gravity_compensation"]!r}')
    if values['sensors.velocity'] not in VELOCITY_SOURCES:
        raise ConfigurationError(
            f'sensors.velocity must be one of {list(VELOCITY_SOURCES)}, got '
            f'{values["sensors.velocity"]!r}')
    if values['sensors.velocity'] != 'sensor' and values['noise.theta_dot_std'] > 0.0:
        raise ConfigurationError(
            f'noise.theta_dot_std must be 0 with sensors.velocity '
            f'{values["sensors.velocity"]!r}: only a sensed velocity has noise of its own')
    sensors = SensorModel(theta_std=values['noise.theta_std'],
                          theta_dot_std=values['noise.theta_dot_std'],
                          velocity=values['sensors.velocity'],
                          velocity_cutoff=values['sensors.velocity_cutoff'],
                          effort=values['sensors.effort'])
    try:
        if urdf is None:
            arm = _planar_arm(values, n, viscous, coulomb)
        else:
            arm = urdf.arm
            arm.set_friction(viscous, coulomb)
    except ValueError as error:     # messages name the field, e.g. 'gravity must be finite'
        if isinstance(error, ConfigurationError):
            raise
        raise ConfigurationError(str(error)) from None
    try:
        reference = _build_reference(values, n, None if urdf is None else urdf.home)
    except ValueError as error:
        if isinstance(error, ConfigurationError):
            raise
        raise ConfigurationError(f'reference.*: {error}') from None
    if urdf is not None:
        warnings.append(reference_limit_warning(arm, reference) or '')

    reference_dt = values['reference_dt']
    horizon = values['reference_horizon']
    if horizon / reference_dt > MAX_REFERENCE_POINTS:
        raise ConfigurationError(
            f'reference_horizon / reference_dt = {horizon / reference_dt:.0f} points; at most '
            f'{MAX_REFERENCE_POINTS} (increase reference_dt)')

    # the step must be stable for the closed loop at the start state (on the reference)
    h = values['integration_step']
    theta0, theta_dot0 = reference.evaluate(0.0)
    stiffness = arm.closed_loop_stiffness(theta0, theta_dot0, kp, kd)
    limit = arm.stable_step(kp, kd, theta0, theta_dot0, safety=1.0)
    if not h < limit:
        raise ConfigurationError(
            f'integration_step = {h} s is unstable: at the start state the fastest eigenvalue '
            f'of the closed loop has |lambda| = {stiffness:.4g} 1/s and the Runge-Kutta step '
            f'is stable only below {limit:.4g} s (h |lambda| < {RK4_REAL_STABILITY_LIMIT:.3f}'
            f' on the real axis); use integration_step <= {0.5 * limit:.3g} s')
    along = max_stable_rkg_step(arm, kp, kd, reference, duration=10.0, samples=100,
                                safety=0.5)
    if h > along:
        warnings.append(
            f'integration_step = {h} s is more than half the stability limit somewhere on the '
            f'first 10 s of the reference (half-limit {along:.3g} s); the simulation may '
            'become inaccurate or diverge')
    control_rate = values['control_rate']
    if control_rate > 0.0 and control_rate < 0.5 * stiffness:
        warnings.append(
            f'control_rate = {control_rate} Hz is below about |lambda| / 2 = '
            f'{0.5 * stiffness:.0f} Hz for the fastest eigenvalue of the closed loop: the '
            'digital PD may chatter or diverge')
    config = SimConfig(
        joint_names=names, arm=arm,
        robot_description='' if urdf is None else urdf.description, kp=kp, kd=kd, ki=ki,
        gravity_compensation=values['gravity_compensation'],
        tau_limit=np.where(tau_limit > 0.0, tau_limit, np.inf) if np.any(tau_limit) else None,
        windup_time=float(values['windup_time']), sensors=sensors, reference=reference,
        reference_type=values['reference.type'], seed=int(values['seed']),
        theta_std=float(values['noise.theta_std']),
        theta_dot_std=float(values['noise.theta_dot_std']),
        publish_rate=float(values['publish_rate']), control_rate=float(control_rate),
        integration_step=float(h), stable_step=float(limit),
        max_speed=float(values['max_speed']), reference_horizon=float(horizon),
        reference_dt=float(reference_dt), reference_rate=float(values['reference_rate']),
        duration=float(values['duration']))
    return config, [warning for warning in warnings if warning]


def _planar_arm(values: dict, n: int, viscous, coulomb) -> PlanarArm:
    """Return the planar arm of the parameters (n joints)."""
    masses = _joint_vector(values, 'masses', n, positive=True)
    lengths = _joint_vector(values, 'lengths', n, positive=True)
    if values['mass_model'] not in MASS_MODELS:
        raise ConfigurationError(
            f'mass_model must be one of {list(MASS_MODELS)}, got {values["mass_model"]!r}')
    return PlanarArm(ArmParameters(
        masses=masses, lengths=lengths, mass_model=values['mass_model'],
        gravity=values['gravity'], viscous=viscous, coulomb=coulomb,
        coulomb_velocity=values['coulomb_velocity']))


# -- the node -----------------------------------------------------------------------------


class SimArm(Node):
    """
    Simulate the arm in real time and publish its states, commands and reference.

    See the module docstring for topics, timing and parameters. Construction raises
    :class:`ConfigurationError` (after logging it) when a parameter is invalid.

    Parameters
    ----------
    **kwargs
        Passed to :class:`rclpy.node.Node` (``context``, ``parameter_overrides``, ...).

    """

    def __init__(self, **kwargs):
        super().__init__(NODE_NAME, **kwargs)
        try:
            values = self._declare_parameters()
            self.config, warnings = build_config(values)
        except ConfigurationError as error:
            self.get_logger().fatal(f'invalid configuration: {error}')
            self.destroy_node()
            raise
        for warning in warnings:
            self.get_logger().warning(warning)
        config = self.config
        self.sim = ArmSimulator(config.arm, config.kp, config.kd, config.reference,
                                config.integration_step, config.control_rate or None,
                                config.max_speed, compiled=isinstance(config.arm, PlanarArm),
                                ki=config.ki, tau_limit=config.tau_limit,
                                gravity_compensation=config.gravity_compensation,
                                windup_time=config.windup_time)
        self._names = list(config.joint_names)
        self._rate = config.publish_rate
        self._sensors = config.sensors.stream(1.0 / self._rate,
                                              np.random.default_rng(config.seed))
        self._ref_every = max(1, int(math.floor(config.publish_rate / config.reference_rate
                                                + 1e-9)))
        steps = int(math.ceil(config.reference_horizon / config.reference_dt - 1e-9))
        self._ref_times = config.reference_dt * np.arange(steps + 1)   # (K,) from 0
        self._origin_ns: Optional[int] = None      # clock time of simulation time 0
        self._start_ns: Optional[int] = None
        self._index = 0                            # last published sample
        self._next_ref_index = 0
        #: per-reason counters of timing events
        self.counters = {'skips': 0, 'skipped_seconds': 0.0, 'clock_jumps_back': 0,
                         'samples': 0, 'references': 0}
        self.exit_code = 0
        #: completes (with the exit code) when ``duration`` is reached or the simulation fails
        self.finished = Future()

        state_qos = QoSProfile(depth=10, history=HistoryPolicy.KEEP_LAST,
                               reliability=ReliabilityPolicy.RELIABLE,
                               durability=DurabilityPolicy.VOLATILE)
        reference_qos = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                                   reliability=ReliabilityPolicy.RELIABLE,
                                   durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self._state_pub = self.create_publisher(JointState, 'joint_states', state_qos)
        self._command_pub = self.create_publisher(JointState, 'joint_commands', state_qos)
        self._reference_pub = self.create_publisher(
            JointTrajectory, 'reference_trajectory', reference_qos)
        if config.robot_description:
            self._description_pub = self.create_publisher(String, 'robot_description',
                                                          reference_qos)
            self._description_pub.publish(String(data=config.robot_description))
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.add_post_set_parameters_callback(self._after_set_parameters)
        self._timer = self.create_timer(1.0 / self._rate, self._on_timer)
        servo = self.sim.servo.describe()
        control = (f'digital {servo} at {config.control_rate:g} Hz' if config.control_rate
                   else f'continuous {servo}')
        sensors = config.sensors
        published = f'velocity {sensors.velocity!r}' + ('' if sensors.effort else ', no effort')
        arm = (config.arm.describe() if config.robot_description
               else f'planar arm, {config.arm.params.mass_model} masses')
        self.get_logger().info(
            f'{len(self._names)} joints {self._names}, {arm}, '
            f'{control}, reference {config.reference_type!r}, publishing at '
            f'{self._rate:g} Hz ({published}), integration_step {config.integration_step:g} s '
            f'(stable below {config.stable_step:.3g} s at the start state)')

    # -- parameters -----------------------------------------------------------------------

    def _declare_parameters(self) -> dict:
        values = {}
        for spec in PARAMETERS:
            try:
                values[spec.name] = spec.declare(self)
            except ParameterException as error:
                reason = error.args[0] if error.args else repr(error)
                raise ConfigurationError(f'parameter {spec.name!r}: {reason}') from None
        return values

    def _on_set_parameters(self, parameters) -> SetParametersResult:
        """Check run-time changes of the live parameters by their table rows; never raise."""
        try:
            for param in parameters:
                spec = _BY_NAME.get(param.name)
                if spec is not None and spec.change == Change.LIVE:
                    reason = spec.check(param.value)
                    if reason:
                        return SetParametersResult(successful=False, reason=reason)
                velocity = self.config.sensors.velocity
                if param.name == 'noise.theta_dot_std' and param.value > 0.0 and \
                        velocity != 'sensor':
                    return SetParametersResult(
                        successful=False,
                        reason=f'noise.theta_dot_std must be 0 with sensors.velocity '
                               f'{velocity!r}: only a sensed velocity has noise of its own')
            return SetParametersResult(successful=True)
        except Exception as error:  # a callback must never raise
            return SetParametersResult(successful=False, reason=f'rejected: {error!r}')

    def _after_set_parameters(self, parameters):
        """Hand new noise levels to the next published sample."""
        for param in parameters:
            if param.name == 'noise.theta_std':
                self._sensors.set_noise(theta_std=float(param.value))
            elif param.name == 'noise.theta_dot_std':
                self._sensors.set_noise(theta_dot_std=float(param.value))

    # -- timing ---------------------------------------------------------------------------

    @property
    def time_origin_ns(self) -> Optional[int]:
        """
        Return the clock time (ns) of simulation time 0, None before the start.

        Simulation time is also the reference's time: a sample stamped s is at
        τ = (s - time_origin_ns) / 1e9. The origin moves forward when the node skips ahead
        and back when the clock jumps back.
        """
        return self._origin_ns

    def _stamp_ns(self, index: int) -> int:
        return self._origin_ns + int(round(index * _NANO / self._rate))

    def _due_index(self, now_ns: int) -> int:
        """Return the last sample index whose stamp is not after ``now_ns``."""
        m = int(math.floor((now_ns - self._origin_ns) * self._rate / _NANO))
        while self._stamp_ns(m + 1) <= now_ns:
            m += 1
        while m > 0 and self._stamp_ns(m) > now_ns:
            m -= 1
        return m

    def _on_timer(self):
        if self.finished.done():
            return
        try:
            self._step()
        except SimulationDiverged as error:
            self._fail(str(error))
        except Exception:  # nothing may escape a callback
            if not self.context.ok():
                return  # shut down (SIGINT) while publishing: the requested end, no failure
            self._fail(f'unexpected error in the simulation step:\n{traceback.format_exc()}')

    def _fail(self, message: str):
        self.get_logger().error(f'{message}; stopping')
        self.exit_code = 1
        self._timer.cancel()
        self.finished.set_result(1)

    def _step(self):
        now_ns = self.get_clock().now().nanoseconds
        if self._origin_ns is None:
            if now_ns <= 0:
                self.get_logger().info(
                    'waiting for the clock (use_sim_time is set and no /clock yet)',
                    throttle_duration_sec=5.0)
                return
            self._origin_ns = self._start_ns = now_ns
            self._publish_sample(0)
            self.get_logger().info('simulation started')
            return
        if self.config.duration > 0.0 and now_ns - self._start_ns >= self.config.duration * _NANO:
            self.get_logger().info(
                f'duration {self.config.duration:g} s reached after '
                f'{self.counters["samples"]} samples; exiting')
            self._timer.cancel()
            self.finished.set_result(0)
            return
        last_ns = self._stamp_ns(self._index)
        if now_ns < last_ns:
            # clock jumped back: continue the simulation from the new time
            self.counters['clock_jumps_back'] += 1
            self.get_logger().warning(
                f'the clock jumped back by {(last_ns - now_ns) / 1e9:.3f} s; the simulation '
                'continues from the new time', throttle_duration_sec=1.0)
            shift = now_ns - last_ns
            self._origin_ns += shift
            self._start_ns += shift                # ``duration`` counts clock time run
            self._next_ref_index = self._index + 1
            return
        due = self._due_index(now_ns)
        if (due - self._index) / self._rate > CATCH_UP_LIMIT:
            # fell behind: pause the simulation for the missed time, stamp the next sample now
            gap = (now_ns - last_ns) / 1e9 - 1.0 / self._rate
            self.counters['skips'] += 1
            self.counters['skipped_seconds'] += gap
            self.get_logger().warning(
                f'fell behind the clock by {gap:.3f} s (> {CATCH_UP_LIMIT} s): skipped ahead, '
                f'the simulation paused for that time ({self.counters["skips"]} skips, '
                f'{self.counters["skipped_seconds"]:.3f} s in all)', throttle_duration_sec=1.0)
            next_offset = self._stamp_ns(self._index + 1) - self._origin_ns
            self._origin_ns = now_ns - next_offset
            self._next_ref_index = self._index + 1
            due = self._index + 1
        for index in range(self._index + 1, due + 1):
            self.sim.advance(index / self._rate)
            self._publish_sample(index)

    def _publish_sample(self, index: int):
        self._index = index
        stamp = Time(nanoseconds=self._stamp_ns(index)).to_msg()
        theta, theta_dot, tau, theta_d, theta_d_dot = self.sim.sample()
        theta, theta_dot, tau = self._sensors.measure(theta, theta_dot, tau)
        state = make_joint_state(stamp, self._names, theta, theta_dot, tau)
        if self.config.sensors.velocity == 'none':
            state.velocity = []                # as a driver without velocity publishes it
        if not self.config.sensors.effort:
            state.effort = []
        self._state_pub.publish(state)
        self._command_pub.publish(
            make_joint_state(stamp, self._names, theta_d, theta_d_dot, None))
        self.counters['samples'] += 1
        if index >= self._next_ref_index:
            self._next_ref_index = index + self._ref_every
            ref_theta, ref_theta_dot = self.config.reference.evaluate(
                self.sim.t + self._ref_times)
            self._reference_pub.publish(make_joint_trajectory(
                stamp, self._names, self._ref_times, ref_theta, ref_theta_dot))
            self.counters['references'] += 1


def main(args=None) -> int:
    """Run the node until SIGINT, shutdown or ``duration``; return the exit code."""
    rclpy.init(args=args)
    node = None
    exit_code = 0
    try:
        node = SimArm()
        rclpy.spin_until_future_complete(node, node.finished)
        exit_code = node.exit_code
    except ConfigurationError:
        exit_code = 1                       # logged by the node
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RuntimeError:
        # SIGINT landing inside rclpy's message conversion surfaces as a pybind11
        # RuntimeError ("Unable to convert call argument"); once the context is shut down
        # that is the requested shutdown, not a failure.
        if rclpy.ok():
            raise
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return exit_code


if __name__ == '__main__':
    sys.exit(main())

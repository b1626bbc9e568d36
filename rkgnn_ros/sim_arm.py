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
arm's own gravity torque at θ or θd, with ``tau_limit`` saturating drives (by default at
twice the arm's torque scale on its reference, :mod:`rkgnn_ros.core.sim.torque_scale`: a
drive never applies an unbounded torque, and a feed-forward beyond it is refused). It runs
on the node's clock (``use_sim_time`` is honoured like in any node). What ``joint_states``
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
    With a URDF arm (:mod:`rkgnn_ros.sim_node.arm_model`): its URDF with the locked joints fixed,
    once at start, for robot_state_publisher and rviz.

Topics (subscribed)
-------------------
``~/feedforward`` (trajectory_msgs/JointTrajectory, reliable, depth 10)
    A feed-forward torque, as a servo with an effort interface takes it: the points'
    ``effort`` (one per joint, mapped by name; positions and velocities are ignored),
    at ``header.stamp + time_from_start`` on the node's clock (a zero stamp: now), linear
    between points, added to the servo's torque (before saturation) at the servo's time:
    τ = servo + τ_ff; ``effort`` in ``joint_states`` stays the applied torque. The newest
    sound trajectory replaces the one before; after its last point, or on an empty
    trajectory, the servo runs alone. A malformed or stale one (unknown, missing or
    repeated joints, a point without efforts, NaN or inf, an effort beyond ``tau_limit``,
    times not increasing, its last point in the past) is not applied and drops the one
    before: the servo runs alone, and the reason is counted and logged (at most once a
    second per reason; :mod:`rkgnn_ros.core.sim.receiver`); a clock jumping back drops
    it too (its times are on the old timeline). The subscription is raw:
    the size budgets of every JointTrajectory input (:mod:`rkgnn_ros.wire.conversions`: 8 MiB,
    10,000 points, 256 names of at most 256 bytes) are checked on the bytes first, and a
    message over one is refused as ``over_budget``, plain CDR that is no JointTrajectory
    as ``bad_shape``, both before rclpy builds the message.

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
The arm under its servo is advanced by fixed Runge-Kutta-Gill steps of at most
``integration_step`` seconds (:mod:`rkgnn_ros.core.sim.arm_simulator`): a continuous servo
with ``control_rate`` = 0, else a digital one that holds its torque between ticks at
``control_rate``. ``integration_step`` is checked at start against the closed-loop
stiffness at the start state (:meth:`PlanarArm.stable_step`); an unstable step is refused.
The parameter table and these checks are :mod:`rkgnn_ros.sim_node.parameters`.

All parameters are read-only (set them at start; they define the simulated system)
except ``noise.theta_std`` and ``noise.theta_dot_std``, which can be changed at any time.
"""

import math
import sys
import traceback
from typing import NamedTuple, Optional, Sequence, Tuple

import numpy as np
from rcl_interfaces.msg import SetParametersResult
import rclpy
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.task import Future
from rclpy.time import Time
from rkgnn_ros.core.sim.arm_simulator import ArmSimulator, SimulationDiverged
from rkgnn_ros.core.sim.plant import PlanarArm
from rkgnn_ros.core.sim.receiver import FeedforwardReceiver
from rkgnn_ros.node.parameters import Change
from rkgnn_ros.node.stacks import start_up, tear_down
from rkgnn_ros.sim_node.parameters import build_config, BY_NAME, ConfigurationError, PARAMETERS
from rkgnn_ros.wire.cdr import (encapsulation_problem, joint_trajectory_cdr_size,
                                parse_trajectory_efforts_cdr)
from rkgnn_ros.wire.conversions import (make_joint_state, make_joint_trajectory,
                                        MAX_MESSAGE_JOINTS, MAX_NAME_BYTES, MAX_TRAJECTORY_BYTES,
                                        MAX_TRAJECTORY_POINTS)
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from std_srvs.srv import SetBool
from trajectory_msgs.msg import JointTrajectory

NODE_NAME = 'sim_arm'

#: Falling behind the clock by more than this (s) skips ahead instead of catching up.
CATCH_UP_LIMIT = 0.5

_NANO = 1_000_000_000


def _over_budget(names, points: int) -> Optional[str]:
    """Return why a trajectory's names or number of points are over the budgets, or None."""
    if len(names) > MAX_MESSAGE_JOINTS:
        return f'{len(names)} joint names, over the budget of {MAX_MESSAGE_JOINTS}'
    if points > MAX_TRAJECTORY_POINTS:
        return f'{points} points, over the budget of {MAX_TRAJECTORY_POINTS}'
    longest = max((len(name.encode('utf-8', 'surrogatepass')) for name in names), default=0)
    if longest > MAX_NAME_BYTES:
        return f'a joint name of {longest} bytes, over the budget of {MAX_NAME_BYTES}'
    return None


class FeedforwardMessage(NamedTuple):
    """The fields of a feed-forward JointTrajectory that ``sim_arm`` reads."""

    stamp_ns: int                # header stamp (0: now)
    names: Tuple[str, ...]
    times: np.ndarray            # (K,) time_from_start (s)
    efforts: Sequence            # (K, m) array, or K arrays: the efforts in the message's order


def read_feedforward(raw: bytes):
    """
    Return the :class:`FeedforwardMessage` in ``raw`` (CDR bytes), or ``(reason, message)``.

    The reason is ``'over_budget'`` (bytes, names or points over the budgets of
    :mod:`rkgnn_ros.wire.conversions`, checked before anything is built from the points) or
    ``'bad_shape'`` (plain CDR that does not form a JointTrajectory, or bytes of another
    encapsulation than plain CDR). The bytes are read by :mod:`rkgnn_ros.wire.cdr`, never by
    rclpy: its deserializer prints on stderr for each malformed message, and building a
    10,000-point message and its efforts took a third of a second, time the simulation
    fell behind by (:func:`~rkgnn_ros.wire.cdr.parse_trajectory_efforts_cdr`: milliseconds).
    """
    if len(raw) > MAX_TRAJECTORY_BYTES:
        return 'over_budget', f'{len(raw)} bytes, over the budget of {MAX_TRAJECTORY_BYTES}'
    raw = bytes(raw)
    problem = encapsulation_problem(raw, 'JointTrajectory')
    if problem is not None:
        return 'bad_shape', problem
    size = joint_trajectory_cdr_size(raw)
    reason = None if size is None else _over_budget(*size)
    if reason is not None:
        return 'over_budget', reason
    parsed = parse_trajectory_efforts_cdr(raw)
    if parsed is None:
        return 'bad_shape', f'{len(raw)} bytes of CDR that do not form a JointTrajectory'
    sec, nanosec, names, times, efforts = parsed
    reason = _over_budget(names, len(times))
    if reason is not None:
        return 'over_budget', reason
    return FeedforwardMessage(sec * _NANO + nanosec, names, times, efforts)


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
        # the driver's own faults (stamp jitter, dropped messages) draw from their own stream
        self._driver_rng = np.random.default_rng([config.seed, 1])
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
                         'samples': 0, 'references': 0, 'dropped': 0}
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
        self._feedforward = FeedforwardReceiver(self._names, config.tau_limit)
        self._feedforward_logged = {}              # reason -> clock time (s) of its last log
        self._feedforward_on = False
        # raw: the size budgets are checked on the bytes, before the points become objects
        self.create_subscription(JointTrajectory, '~/feedforward', self._on_feedforward, 10,
                                 raw=True)
        if config.robot_description:
            self._description_pub = self.create_publisher(String, 'robot_description',
                                                          reference_qos)
            self._description_pub.publish(String(data=config.robot_description))
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.add_post_set_parameters_callback(self._after_set_parameters)
        self._payload_on = False
        self.create_service(SetBool, '~/payload', self._on_payload)
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
            f'(stable below {config.stable_step:.3g} s at the start state), drive limits '
            f'{config.tau_limit_note}')

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
                spec = BY_NAME.get(param.name)
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
            if self._feedforward.active:           # its times belong to the old timeline
                self._feedforward_event(self._feedforward.refuse(
                    'clock_jump', 'the clock jumped back: its times are on the old timeline'))
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
            self._timed_payload(index / self._rate)
            origin = self._origin_ns / _NANO
            self._feedforward_event(self._feedforward.expire(origin + self.sim.t))
            self.sim.feedforward = self._feedforward.track(origin)
            self.sim.advance(index / self._rate)
            self._publish_sample(index)

    # -- payload ---------------------------------------------------------------------------

    def _set_payload(self, on: bool, why: str) -> str:
        mass, com = self.config.payload[0], self.config.payload[1]
        if on and mass <= 0.0:
            return 'payload.mass is 0: nothing to attach'
        self._payload_on = on
        self.sim.set_payload(mass if on else 0.0, com)
        when = f'at simulation time {self.sim.t:.3f} s' + (
            '' if self._origin_ns is None else
            f', stamp {self._origin_ns / _NANO + self.sim.t:.6f} s')
        text = (f'payload of {mass:g} kg at {list(com)} m attached ({why}), {when}' if on else
                f'payload released ({why}), {when}')
        self.get_logger().info(text)
        return text

    def _timed_payload(self, t: float) -> None:
        """Attach or release the payload at payload.attach_at / detach_at (simulation s)."""
        _, _, attach, detach = self.config.payload
        if attach and not self._payload_on and self.sim.t < attach <= t:
            self._set_payload(True, f'payload.attach_at {attach:g} s')
        elif detach and self._payload_on and self.sim.t < detach <= t:
            self._set_payload(False, f'payload.detach_at {detach:g} s')

    def _on_payload(self, request, response):
        try:
            response.message = self._set_payload(bool(request.data), '~/payload')
            response.success = bool(request.data) == self._payload_on
        except Exception as error:  # nothing may escape a callback
            response.success, response.message = False, f'payload not changed: {error}'
        return response

    # -- feed-forward ---------------------------------------------------------------------

    def _on_feedforward(self, raw: bytes):
        """Take a feed-forward trajectory (applied at the next step); never raises."""
        receiver = self._feedforward
        try:
            msg = read_feedforward(raw)
            if not isinstance(msg, FeedforwardMessage):
                event = receiver.refuse(*msg)
            elif self._origin_ns is None:
                event = receiver.refuse('not_started', 'the simulation has not started')
            else:
                event = receiver.offer(self._origin_ns / _NANO + self.sim.t,
                                       msg.stamp_ns / _NANO, msg.names, msg.times, msg.efforts)
            self._feedforward_event(event)
        except Exception as error:  # nothing may escape a callback
            self._feedforward_event(receiver.refuse('bad_shape', f'unreadable ({error!r})'))

    def _feedforward_event(self, event):
        """Log a fall-back to the servo alone (once a second per reason) or a resumption."""
        if event is None:
            return
        applied, self._feedforward_on = self._feedforward_on, event.applied
        if event.applied:
            if not applied:
                self.get_logger().info('feed-forward applied: servo + feed-forward')
            return
        now = self.get_clock().now().nanoseconds / _NANO
        if now - self._feedforward_logged.get(event.reason, -math.inf) >= 1.0:
            self._feedforward_logged[event.reason] = now
            text = (f'feed-forward {event.reason} ({self._feedforward.counts[event.reason]} '
                    f'so far): {event.message}; the servo runs alone')
            if event.reason in ('stopped', 'expired'):  # the normal ends of a feed-forward
                self.get_logger().info(text)
            else:
                self.get_logger().warning(text)

    def _publish_sample(self, index: int):
        self._index = index
        stamp = Time(nanoseconds=self._stamp_ns(index)).to_msg()
        theta, theta_dot, tau, theta_d, theta_d_dot = self.sim.sample()
        theta, theta_dot, tau = self._sensors.measure(theta, theta_dot, tau)
        config = self.config
        jitter = (self._driver_rng.uniform(-config.stamp_jitter, config.stamp_jitter)
                  if config.stamp_jitter > 0.0 else 0.0)
        dropped = (config.drop_fraction > 0.0
                   and self._driver_rng.random() < config.drop_fraction)
        state = make_joint_state(
            Time(nanoseconds=self._stamp_ns(index) + int(round(jitter * _NANO))).to_msg()
            if jitter else stamp, self._names, theta, theta_dot, tau)
        if config.sensors.velocity == 'none':
            state.velocity = []                # as a driver without velocity publishes it
        if not config.sensors.effort:
            state.effort = []
        if dropped:
            self.counters['dropped'] += 1
        else:
            self._state_pub.publish(state)
        if config.publish_commands:
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
    interrupt = start_up(args)
    node, exit_code = None, 0
    try:
        node = SimArm()
        interrupt.arm()                     # a SIGINT now ends the spin, raises nothing
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
        tear_down(node)
    return exit_code


if __name__ == '__main__':
    sys.exit(main())

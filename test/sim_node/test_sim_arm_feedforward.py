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
sim_arm's feed-forward input: the receiver's rules, the simulator's sum, the node's topic.

The receiver (:mod:`rkgnn_ros.core.sim.receiver`) with plain arrays; the simulator
with a feed-forward against the accurate simulation; the node through its topics only:
what it applied is read back from what it publishes (``joint_states`` effort minus the PD
torque of ``joint_commands``; no sensor noise by default), and why it refused from
``/rosout``.
"""

import math
import os
import random

import numpy as np
import pytest
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message
from rkgnn_ros.core.control.feedforward import plan_feedforward
from rkgnn_ros.core.sim.arm_simulator import ArmSimulator
from rkgnn_ros.core.sim.plant import PlanarArm
from rkgnn_ros.core.sim.receiver import FeedforwardReceiver, REASONS
from rkgnn_ros.core.sim.servo import FeedforwardTrack, Servo
from rkgnn_ros.core.sim.simulate import simulate
from rkgnn_ros.core.sim.trajectories import paper_reference
from rkgnn_ros.sim_arm import FeedforwardMessage, read_feedforward, SimArm
from rkgnn_ros.wire.conversions import MAX_TRAJECTORY_BYTES, MAX_TRAJECTORY_POINTS
from ros_helpers import retire_node, Rosout, spinning_context, stamp_ns, wait_for
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

DOMAIN_ID = int(os.environ.get('ROS_DOMAIN_ID') or random.SystemRandom().randint(150, 199))
JOINTS = ('joint1', 'joint2', 'joint3')
KP = np.array([32.84, 42.05, 42.31])
KD = np.array([42.44, 0.19, 4.86])
ARM = PlanarArm.paper()
PATIENCE = 60.0  # s: a condition's longest wait (a passing test waits only as long as it takes)


# ----------------------------------------------------------------------------- receiver

def offer(receiver, now=10.0, start=10.0, names=JOINTS, times=(0.0, 1.0),
          efforts=((1.0, 2.0, 3.0), (1.0, 2.0, 3.0))):
    return receiver.offer(now, start, names, list(times), [list(e) for e in efforts])


def test_the_receiver_maps_joints_by_name_and_applies_on_its_time_axis():
    receiver = FeedforwardReceiver(JOINTS, tau_limit=[20.0, 10.0, 5.0])
    event = offer(receiver, names=('joint3', 'joint1', 'joint2'),
                  efforts=((3.0, 1.0, 2.0), (4.0, 2.0, 3.0)))
    assert event.applied and receiver.active
    track = receiver.track(origin=9.0)          # simulation time = clock - 9 s
    np.testing.assert_allclose(track.evaluate(1.5), [1.5, 2.5, 3.5])
    np.testing.assert_allclose(track.evaluate(0.5), 0.0)   # before its first point
    assert receiver.track(origin=9.0) is track  # not rebuilt without a change
    assert receiver.expire(10.9) is None
    assert receiver.expire(11.1).reason == 'expired' and not receiver.active
    assert receiver.track(origin=9.0) is None
    assert receiver.expire(12.0) is None        # reported once


@pytest.mark.parametrize('change, reason, words', [
    ({'names': ('joint1', 'joint2', 'gripper')}, 'unknown_joint', "'gripper'"),
    ({'names': ('joint1', 'joint2'), 'efforts': ((1.0, 2.0), (1.0, 2.0))}, 'missing_joint',
     "'joint3'"),
    ({'names': ('joint1', 'joint1', 'joint2')}, 'duplicate_joint', 'twice'),
    ({'times': (0.0,), 'efforts': ((1.0, 2.0, 3.0),)}, 'bad_shape', 'at least 2'),
    ({'efforts': ((1.0, 2.0, 3.0), (1.0, 2.0))}, 'bad_shape', 'point 1 has 2 efforts'),
    ({'efforts': ((1.0, 2.0, 3.0), ())}, 'no_effort', 'point 1'),
    ({'efforts': ((1.0, math.nan, 3.0), (1.0, 2.0, 3.0))}, 'non_finite', "'joint2'"),
    ({'efforts': ((1.0, 2.0, 3.0), (1.0, 2.0, -math.inf))}, 'non_finite', "'joint3'"),
    ({'efforts': ((1.0, 2.0, 3.0), (1.0, 2.0, 5.5))}, 'over_limit', 'limit 5'),
    ({'times': (0.0, 0.0)}, 'non_increasing_time', 'increase'),
    ({'start': 8.0}, 'stale', '1 s in the past'),
    ({'times': (), 'efforts': ()}, 'stopped', 'empty'),
])
def test_a_bad_trajectory_is_refused_with_its_reason_and_drops_the_one_applied(
        change, reason, words):
    receiver = FeedforwardReceiver(JOINTS, tau_limit=[20.0, 10.0, 5.0])
    assert offer(receiver).applied
    event = offer(receiver, **change)
    assert not event.applied and event.reason == reason and words in event.message
    assert not receiver.active and receiver.track(0.0) is None
    assert receiver.counts[reason] == 1 and reason in REASONS
    assert sum(receiver.counts.values()) == 1


# ----------------------------------------------------------------------------- simulator

@pytest.mark.parametrize('control_rate', [None, 500.0])
def test_the_simulator_adds_the_feedforward_like_simulate(control_rate):
    reference = paper_reference(3)
    t = np.arange(0.0, 1.0 + 1e-9, 0.02)
    theta_d, theta_d_dot = reference.evaluate(t)
    effort = plan_feedforward(ARM, t, theta_d, theta_d_dot).effort
    track = FeedforwardTrack(t + 0.2, effort)             # starts 0.2 s late, ends at 1.2 s
    fast = ArmSimulator(ARM, KP, KD, reference, 5e-4, control_rate)
    plain = ArmSimulator(ARM, KP, KD, reference, 5e-4, control_rate, compiled=False)
    fast.feedforward = plain.feedforward = track
    servo = Servo(KP, KD)
    truth = simulate(ARM, servo, reference, duration=1.5, rate=100.0, feedforward=track,
                     control_rate=control_rate)
    for k in range(1, 151):
        fast.advance(0.01 * k)
        plain.advance(0.01 * k)
        np.testing.assert_allclose(fast.x, plain.x, rtol=0, atol=1e-10)
        theta, theta_dot, tau, theta_d, theta_d_dot = fast.sample()
        # the fixed steps end at the feed-forward's start and end, where it jumps (without
        # that the first-order error of stepping over a jump reached 9e-5 rad here; with it
        # the two agreed to 1e-9 rad when this test was written)
        assert np.max(np.abs(theta - truth.theta[k])) < 1e-7
        if control_rate is None:  # the applied torque is the servo's plus the feed-forward
            expected = servo.torque(theta, theta_dot, theta_d, theta_d_dot) + \
                track.evaluate(0.01 * k)
            np.testing.assert_allclose(tau, expected, rtol=0, atol=1e-9)


# ----------------------------------------------------------------------------- the node

@pytest.fixture(scope='module')
def ros():
    """Yield (context, executor) with the executor spinning in a background thread."""
    with spinning_context(DOMAIN_ID) as pair:
        yield pair


class Arm:
    """A started sim_arm and a probe that records its states and commands and sends to it."""

    def __init__(self, context, executor, **overrides):
        self.executor = executor
        self.probe = Node(f'ff_probe_{random.getrandbits(32):08x}', context=context)
        self.states, self.commands = {}, {}
        qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        self.probe.create_subscription(JointState, 'joint_states',
                                       lambda m: self.states.__setitem__(stamp_ns(m), m), qos)
        self.probe.create_subscription(JointState, 'joint_commands',
                                       lambda m: self.commands.__setitem__(stamp_ns(m), m), qos)
        self.rosout = Rosout(self.probe)
        self.send = self.probe.create_publisher(JointTrajectory, '/sim_arm/feedforward',
                                                10).publish
        executor.add_node(self.probe)
        self.node = SimArm(context=context, parameter_overrides=[
            Parameter(name, value=value) for name, value in overrides.items()])
        executor.add_node(self.node)
        assert wait_for(lambda: self.node.count_subscribers('joint_states') > 0
                        and self.node.get_subscriptions_info_by_topic('/sim_arm/feedforward')
                        and len(self.applied()) > 5, PATIENCE)

    def close(self):
        retire_node(self.executor, self.node)
        retire_node(self.executor, self.probe)

    def applied(self):
        """Return {stamp (ns): τ − PD torque (n,)} for every state whose command arrived."""
        out = {}
        for stamp, state in list(self.states.items()):
            command = self.commands.get(stamp)
            if command is not None:
                pd = KP * (np.array(command.position) - state.position) + \
                    KD * (np.array(command.velocity) - state.velocity)
                out[stamp] = np.array(state.effort) - pd
        return out

    def now_ns(self):
        return max(self.states)

    def newest_is(self, value):
        """Return whether the newest state with its command had ``value`` applied."""
        applied = self.applied()
        return bool(applied) and np.allclose(applied[max(applied)], value, atol=1e-9)

    def warnings(self, *words):
        return self.rosout.lines('sim_arm', 'feed-forward', *words)


def trajectory(start_ns, efforts, dt=0.5, names=JOINTS):
    msg = JointTrajectory(joint_names=list(names))
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(start_ns), 1_000_000_000)
    for k, effort in enumerate(efforts):
        point = JointTrajectoryPoint(effort=[float(e) for e in effort])
        point.time_from_start.sec, point.time_from_start.nanosec = divmod(
            int(round(k * dt * 1e9)), 1_000_000_000)
        msg.points.append(point)
    return msg


def test_the_size_budgets_are_checked_on_the_bytes():
    names = [f'j{i}' for i in range(3)]
    good = serialize_message(trajectory(5_000_000_000, [(1.0, 2.0, 3.0)] * 3, names=names))
    assert isinstance(read_feedforward(good), FeedforwardMessage)
    for msg, words in [
            (trajectory(0, [(0.0,)] * (MAX_TRAJECTORY_POINTS + 1), dt=1e-3, names=['j']),
             'points'),
            (trajectory(0, [(0.0,) * 257] * 2, names=[f'j{i}' for i in range(257)]), 'names'),
            (trajectory(0, [(0.0,)] * 2, names=['j' * 257]), 'bytes')]:
        reason, message = read_feedforward(serialize_message(msg))
        assert reason == 'over_budget' and words in message
    reason, message = read_feedforward(b'\0' * (MAX_TRAJECTORY_BYTES + 1))
    assert reason == 'over_budget' and str(MAX_TRAJECTORY_BYTES) in message
    for cut in (10, 40, len(good) // 2):    # truncated: never deserialized
        assert read_feedforward(good[:cut])[0] == 'bad_shape'


def test_another_encapsulation_is_refused_before_rclpy_prints_a_line(capfd):
    good = serialize_message(trajectory(5_000_000_000, [(1.0, 2.0, 3.0)] * 3))
    malformed = good[:20] + b'\xff\xff\xff\x7f' + good[24:]  # a count beyond the end
    capfd.readouterr()
    for code in (2, 3, 6, 7, 8, 9, 10, 11, 0x100):
        head = code.to_bytes(2, 'big')
        for raw in (head + good[2:], head + malformed[2:]):
            reason, message = read_feedforward(raw)
            assert reason == 'bad_shape' and f'0x{code:04x}' in message
    err = capfd.readouterr().err
    assert 'sequence size' not in err and 'Fast CDR' not in err, err[:500]


def test_the_node_applies_a_feedforward_and_falls_back_on_bad_ones(ros):
    context, executor = ros
    arm = Arm(context, executor, tau_limit=[30.0, 20.0, 6.0])
    try:
        # a constant feed-forward over the next 30 s: the applied torque is PD + it
        start = arm.now_ns()
        arm.send(trajectory(start, [(1.0, -0.5, 0.25)] * 61))
        assert wait_for(lambda: arm.rosout.lines('sim_arm', 'feed-forward applied'), PATIENCE)
        assert wait_for(lambda: sum(1 for s, v in arm.applied().items()
                                    if s > start and np.allclose(v, [1.0, -0.5, 0.25],
                                                                 atol=1e-9)) >= 10, PATIENCE)
        for words, msg in [
                ('non_finite', trajectory(arm.now_ns(), [(1.0, math.nan, 0.0)] * 3)),
                ('over_limit', trajectory(arm.now_ns(), [(1.0, 0.0, 9.0)] * 3)),
                ('unknown_joint', trajectory(arm.now_ns(), [(1.0, 0.0, 0.0)] * 3,
                                             names=('joint1', 'joint2', 'gripper'))),
                ('stale', trajectory(arm.now_ns() - 5_000_000_000, [(1.0, 0.0, 0.0)] * 3)),
                ('non_increasing_time', trajectory(arm.now_ns(), [(1.0, 0.0, 0.0)] * 3,
                                                   dt=0.0)),
                # the size budgets of every input, checked on the bytes (raw subscription)
                ('over_budget', trajectory(arm.now_ns(), [(1.0,) * 257] * 3,
                                           names=[f'j{i}' for i in range(257)])),
                ('bad_shape', b'\x00\x01\x00\x00' + bytes(range(40)))]:
            # re-apply a good one, then the bad one: it must stop the feed-forward
            arm.send(trajectory(arm.now_ns(), [(1.0, -0.5, 0.25)] * 61))
            assert wait_for(lambda: arm.newest_is([1.0, -0.5, 0.25]), PATIENCE)
            sent = arm.now_ns()
            arm.send(msg)
            assert wait_for(lambda: arm.warnings(words), PATIENCE), words
            assert wait_for(lambda: sum(1 for s, v in arm.applied().items()
                                        if s > sent and np.allclose(v, 0.0, atol=1e-9)) >= 5,
                            PATIENCE), words
        # an empty trajectory stops the feed-forward, said as information
        arm.send(trajectory(arm.now_ns(), [(1.0, -0.5, 0.25)] * 61))
        assert wait_for(lambda: arm.newest_is([1.0, -0.5, 0.25]), PATIENCE)
        arm.send(trajectory(arm.now_ns(), []))
        assert wait_for(lambda: arm.rosout.lines('sim_arm', 'stopped', level='info'), PATIENCE)
        # through all of it the node kept publishing, and every effort stayed finite
        count = len(arm.states)
        assert wait_for(lambda: len(arm.states) > count + 10, PATIENCE)
        assert all(np.all(np.isfinite(s.effort)) for s in list(arm.states.values()))
    finally:
        arm.close()


def test_a_feedforward_that_ends_falls_back_to_the_servo_alone(ros):
    context, executor = ros
    arm = Arm(context, executor)
    try:
        start = arm.now_ns()
        arm.send(trajectory(start, [(0.5, 0.5, 0.1)] * 4))   # 1.5 s long
        end = start + 1_500_000_000
        assert wait_for(lambda: arm.warnings('expired', 'last point has passed'), PATIENCE)
        assert wait_for(lambda: len([s for s in arm.applied() if s > end + 20_000_000]) >= 5,
                        PATIENCE)
        applied = arm.applied()
        # before the message arrived the servo ran alone; after it, PD + the feed-forward
        during = [v for s, v in applied.items() if start < s <= end]
        after = [v for s, v in applied.items() if s > end + 20_000_000]
        on = [np.allclose(v, [0.5, 0.5, 0.1], atol=1e-9) for v in during]
        assert any(on) and all(a or np.allclose(v, 0.0, atol=1e-9) for a, v in zip(on, during))
        assert all(np.allclose(v, 0.0, atol=1e-9) for v in after)
    finally:
        arm.close()

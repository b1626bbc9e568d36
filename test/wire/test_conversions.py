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
Message <-> array boundary: reliability items 1-8 and 11, builders, property test.

Each item test feeds a real message through the same path the node uses (convert, then
either count the rejection in the buffer or add the sample) and checks the reason code,
the counter, and that the data buffered before is unchanged.
"""

import math

from builtin_interfaces.msg import Duration, Time
from hypothesis import given, HealthCheck, settings
from hypothesis import strategies as st
import numpy as np
import pytest
from rclpy.serialization import serialize_message
from rkgnn_ros.streams.buffer import StreamBuffer
from rkgnn_ros.wire import conversions as conv
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

JOINTS = ('joint1', 'joint2')
T0 = 1000.0


def joint_state(names=JOINTS, position=(0.1, 0.2), velocity=(1.0, 2.0), effort=(),
                stamp=T0):
    msg = JointState()
    msg.header.stamp = Time(sec=int(math.floor(stamp)),
                            nanosec=int(round((stamp - math.floor(stamp)) * 1e9)))
    msg.name = list(names)
    msg.position = [float(v) for v in position]
    msg.velocity = [float(v) for v in velocity]
    msg.effort = [float(v) for v in effort]
    return msg


def trajectory(names=JOINTS, times=(0.0, 0.5, 1.0), positions=None, velocities=None,
               stamp=T0):
    msg = JointTrajectory()
    msg.header.stamp = Time(sec=int(stamp), nanosec=0)
    msg.joint_names = list(names)
    points = []
    for k, t in enumerate(times):
        point = JointTrajectoryPoint()
        point.time_from_start = Duration(sec=int(math.floor(t)),
                                         nanosec=int(round((t - math.floor(t)) * 1e9)))
        point.positions = list(positions[k]) if positions is not None else \
            [0.1 * k * (j + 1) for j in range(len(names))]
        if velocities is not None:
            point.velocities = list(velocities[k])
        points.append(point)
    msg.points = points
    return msg


def ingest(buffer, msg, need_velocity=True):
    """Do what the identifier's joint_states callback does, by both ways of reading."""
    result = conv.joint_state_to_arrays(msg, buffer.joints, need_velocity=need_velocity,
                                        need_effort=buffer.need_tau)
    from_bytes = conv.joint_state_cdr_to_arrays(
        serialize_message(msg), buffer.joints, need_velocity=need_velocity,
        need_effort=buffer.need_tau)
    assert from_bytes.ok == result.ok
    if not result.ok:
        assert from_bytes == result
    else:
        assert from_bytes.stamp == result.stamp and from_bytes.sec_nanosec == result.sec_nanosec
        for x, y in zip(from_bytes[1:4], result[1:4]):
            assert (x is None and y is None) or np.array_equal(x, y)
    if not result.ok:
        buffer.count_drop('state', result.reason)
        return result
    return buffer.add_state(result.stamp, result.position,
                            np.zeros(len(buffer.joints)) if result.velocity is None
                            else result.velocity, result.effort)


def filled_buffer():
    """Return a buffer holding 1 s of good states at 100 Hz (no commands needed)."""
    buffer = StreamBuffer(JOINTS, model_step=0.01, window=10.0, gap_threshold=0.1,
                          need_tau=False, need_desired=False)
    for k in range(101):
        t = T0 + 0.01 * k
        assert ingest(buffer, joint_state(position=(math.sin(t), math.cos(t)), stamp=t))
    return buffer


def fingerprint(buffer):
    """Return everything observable about the buffered data, as plain copies."""
    stats = buffer.stats()
    t, theta, theta_dot = buffer.latest_state()
    segments = [(d.t.copy(), d.theta.copy(), d.theta_dot.copy()) for d in buffer.snapshot()]
    return stats['state_samples'], t, theta.copy(), theta_dot.copy(), segments


def assert_same(before, after):
    assert before[0] == after[0]
    assert before[1] == after[1]
    np.testing.assert_array_equal(before[2], after[2])
    np.testing.assert_array_equal(before[3], after[3])
    assert len(before[4]) == len(after[4])
    for a, b in zip(before[4], after[4]):
        for x, y in zip(a, b):
            np.testing.assert_array_equal(x, y)


def check_rejected(msg, reason, need_velocity=True):
    """Feed one bad message after good data; check reason, counter, data unchanged."""
    buffer = filled_buffer()
    before = fingerprint(buffer)
    result = ingest(buffer, msg, need_velocity=need_velocity)
    assert not result.ok
    assert result.reason == reason
    assert result.reason in conv.REJECTION_REASONS
    assert buffer.stats()['drops']['state'][reason] == 1
    assert buffer.counters[reason] == 1
    assert_same(before, fingerprint(buffer))
    return result


# ---------------------------------------------------------------- reliability items


def test_item01_position_name_size_mismatch_dropped():
    msg = joint_state(names=JOINTS, position=(0.1, 0.2, 0.3), stamp=T0 + 2.0)
    result = check_rejected(msg, 'size_mismatch')
    assert 'position has 3 values for 2 names' in result.message


def test_item01_velocity_size_mismatch_dropped():
    msg = joint_state(velocity=(1.0,), stamp=T0 + 2.0)
    result = check_rejected(msg, 'size_mismatch')
    assert 'velocity has 1 values for 2 names' in result.message


@pytest.mark.parametrize('names, position', [((), (0.1, 0.2)), (JOINTS, ()), ((), ())])
def test_item02_empty_name_or_position_dropped(names, position):
    msg = joint_state(names=names, position=position, velocity=(), stamp=T0 + 2.0)
    result = check_rejected(msg, 'empty')
    assert 'empty JointState' in result.message


@pytest.mark.parametrize('velocity', [(), (math.nan, 2.0), (1.0, math.nan)])
def test_item03_missing_velocity_dropped(velocity):
    msg = joint_state(velocity=velocity, stamp=T0 + 2.0)
    result = check_rejected(msg, 'missing_velocity')
    assert 'velocity' in result.message


def test_item03_velocity_not_needed_is_none_not_data():
    msg = joint_state(velocity=(math.nan, 2.0), stamp=T0 + 2.0)
    result = conv.joint_state_to_arrays(msg, JOINTS, need_velocity=False)
    assert result.ok
    assert result.velocity is None  # NaN never becomes data


@pytest.mark.parametrize('effort', [(), (1.0, math.nan)])
def test_item03_missing_effort_when_torque_needed(effort):
    buffer = StreamBuffer(JOINTS, 0.01, 10.0, 0.1, need_tau=True, need_desired=False)
    assert ingest(buffer, joint_state(effort=(3.0, 4.0), stamp=T0))
    result = ingest(buffer, joint_state(effort=effort, stamp=T0 + 0.01))
    assert result.reason == 'missing_effort'
    assert buffer.counters['missing_effort'] == 1
    assert buffer.stats()['state_samples'] == 1


@pytest.mark.parametrize('field, value, reason', [
    ('position', math.nan, 'non_finite'), ('position', math.inf, 'non_finite'),
    ('position', -math.inf, 'non_finite'), ('velocity', math.inf, 'non_finite')])
def test_item04_non_finite_used_field_rejected(field, value, reason):
    values = {'position': [0.1, 0.2], 'velocity': [1.0, 2.0]}
    values[field][1] = value
    msg = joint_state(position=values['position'], velocity=values['velocity'],
                      stamp=T0 + 2.0)
    result = check_rejected(msg, reason)
    assert "'joint2'" in result.message


def test_item04_non_finite_in_ignored_joint_is_harmless():
    msg = joint_state(names=('joint1', 'gripper', 'joint2'), position=(0.1, math.nan, 0.2),
                      velocity=(1.0, math.inf, 2.0), stamp=T0)
    result = conv.joint_state_to_arrays(msg, JOINTS)
    assert result.ok
    np.testing.assert_array_equal(result.position, [0.1, 0.2])
    np.testing.assert_array_equal(result.velocity, [1.0, 2.0])


def test_item05_extra_joint_ignored():
    buffer = filled_buffer()
    msg = joint_state(names=('gripper', 'joint2', 'joint1'), position=(9.0, 0.2, 0.1),
                      velocity=(9.0, 2.0, 1.0), stamp=T0 + 1.01)
    assert ingest(buffer, msg)
    t, theta, theta_dot = buffer.latest_state()
    assert t == pytest.approx(T0 + 1.01)
    np.testing.assert_array_equal(theta, [0.1, 0.2])
    np.testing.assert_array_equal(theta_dot, [1.0, 2.0])


def test_item05_missing_joint_dropped_and_named():
    msg = joint_state(names=('joint1', 'gripper'), stamp=T0 + 2.0)
    result = check_rejected(msg, 'missing_joint')
    assert "missing joint 'joint2'" in result.message


def test_item06_reordered_names_mapped_by_name():
    joints = ('shoulder', 'elbow', 'wrist')
    buffer = StreamBuffer(joints, 0.01, 10.0, 0.1, need_tau=True, need_desired=False)
    orders = [(0, 1, 2), (2, 0, 1), (1, 2, 0)]
    for k in range(30):
        t = T0 + 0.01 * k
        truth = {'shoulder': (1.0 + t, 10.0, 100.0), 'elbow': (2.0 + t, 20.0, 200.0),
                 'wrist': (3.0 + t, 30.0, 300.0)}
        names = [joints[i] for i in orders[k % 3]]
        msg = joint_state(names=names, position=[truth[n][0] for n in names],
                          velocity=[truth[n][1] for n in names],
                          effort=[truth[n][2] for n in names], stamp=t)
        assert ingest(buffer, msg)
    (segment,) = buffer.snapshot()
    for j, name in enumerate(joints):
        np.testing.assert_allclose(segment.theta[:, j], j + 1.0 + segment.t + 1000.0,
                                   atol=1e-9)
        np.testing.assert_allclose(segment.theta_dot[:, j], 10.0 * (j + 1), atol=1e-12)
        np.testing.assert_allclose(segment.tau[:, j], 100.0 * (j + 1), atol=1e-12)
    assert segment.joint_names == joints


def test_item07_duplicate_joint_name_rejected():
    msg = joint_state(names=('joint1', 'joint2', 'joint1'), position=(0.1, 0.2, 0.3),
                      velocity=(1.0, 2.0, 3.0), stamp=T0 + 2.0)
    result = check_rejected(msg, 'duplicate_name')
    assert "'joint1'" in result.message


def test_item07_duplicate_extra_joint_also_rejected():
    msg = joint_state(names=('joint1', 'joint2', 'gripper', 'gripper'),
                      position=(0.1, 0.2, 0.3, 0.4), velocity=(), stamp=T0 + 2.0)
    check_rejected(msg, 'duplicate_name', need_velocity=False)


def _reference_buffer():
    buffer = StreamBuffer(JOINTS, 0.01, 10.0, 0.1, need_tau=False, need_desired=True)
    good = conv.joint_trajectory_to_arrays(trajectory(), JOINTS)
    assert good.ok
    assert buffer.add_reference(*good)
    return buffer


@pytest.mark.parametrize('msg, reason, words', [
    (trajectory(times=()), 'empty', '0 points'),
    (trajectory(names=()), 'empty', '0 joint names'),
    (trajectory(times=(0.0, 0.5, 0.5)), 'non_increasing_time', 'point 2'),
    (trajectory(times=(0.0, 1.0, 0.5)), 'non_increasing_time', 'point 2'),
    (trajectory(positions=[(0.0, 0.0), (0.1,), (0.2, 0.2)]), 'size_mismatch',
     'point 1 has 1 positions for 2 joint names'),
    (trajectory(velocities=[(0.0, 0.0), (0.1, 0.1, 0.1), (0.2, 0.2)]), 'size_mismatch',
     'point 1 has 3 velocities'),
    (trajectory(velocities=[(0.0, 0.0), (), (0.2, 0.2)]), 'size_mismatch', 'some points'),
    (trajectory(positions=[(0.0, 0.0), (0.1, math.inf), (0.2, 0.2)]), 'non_finite',
     "point 1 position is inf for joint 'joint2'"),
    (trajectory(names=('joint1', 'other')), 'missing_joint', "'joint2'"),
    (trajectory(names=('joint1', 'joint1')), 'duplicate_name', "'joint1'"),
])
def test_item08_bad_trajectory_rejected_saying_which(msg, reason, words):
    buffer = _reference_buffer()
    times = T0 + np.linspace(-1.0, 2.0, 7)
    before = buffer.reference_at(times)
    result = conv.joint_trajectory_to_arrays(msg, JOINTS)
    assert not result.ok
    assert result.reason == reason
    assert words in result.message
    buffer.count_drop('reference', result.reason)
    assert buffer.stats()['drops']['reference'][reason] == 1
    after = buffer.reference_at(times)
    np.testing.assert_array_equal(before[0], after[0])
    np.testing.assert_array_equal(before[1], after[1])


def test_item08_nan_velocities_mean_missing():
    msg = trajectory(velocities=[(0.0, 0.0), (math.nan, 0.1), (0.2, 0.2)])
    result = conv.joint_trajectory_to_arrays(msg, JOINTS)
    assert result.ok and result.velocities is None


def test_item11_zero_stamp_rejected():
    msg = joint_state(stamp=0.0)
    result = check_rejected(msg, 'zero_stamp')
    assert 'zero' in result.message


def test_item11_zero_trajectory_stamp_means_now_when_given():
    msg = trajectory(stamp=0)
    assert conv.joint_trajectory_to_arrays(msg, JOINTS).reason == 'zero_stamp'
    result = conv.joint_trajectory_to_arrays(msg, JOINTS, now=T0 + 5.0)
    assert result.ok and result.t0 == T0 + 5.0


# ---------------------------------------------------------------- conversions proper


def test_joint_state_result_unpacks_in_configured_order():
    msg = joint_state(names=('joint2', 'joint1'), position=(0.2, 0.1), velocity=(2.0, 1.0),
                      effort=(20.0, 10.0), stamp=T0 + 0.25)
    stamp, position, velocity, effort, sec_nanosec = conv.joint_state_to_arrays(msg, JOINTS)
    assert stamp == T0 + 0.25 and sec_nanosec == (1000, 250_000_000)
    np.testing.assert_array_equal(position, [0.1, 0.2])
    np.testing.assert_array_equal(velocity, [1.0, 2.0])
    np.testing.assert_array_equal(effort, [10.0, 20.0])
    position[0] = 99.0  # a copy: the message is untouched
    assert msg.position[1] == 0.1


def test_not_a_message_is_malformed_not_raised():
    assert conv.joint_state_to_arrays(None, JOINTS).reason == 'malformed'
    assert conv.joint_trajectory_to_arrays(object(), JOINTS).reason == 'malformed'


def test_trajectory_arrays():
    msg = trajectory(times=(0.0, 0.5, 1.25), positions=[(0, 1), (2, 3), (4, 5)],
                     velocities=[(6, 7), (8, 9), (10, 11)], names=('joint2', 'joint1'))
    t0, times, positions, velocities = conv.joint_trajectory_to_arrays(msg, JOINTS)
    assert t0 == T0
    np.testing.assert_allclose(times, [0.0, 0.5, 1.25])
    np.testing.assert_array_equal(positions, [[1, 0], [3, 2], [5, 4]])
    np.testing.assert_array_equal(velocities, [[7, 6], [9, 8], [11, 10]])


@pytest.mark.parametrize('seconds', [0.0, 1.5, 1e-9, 1700000000.123456, 12.999999999999])
def test_stamp_round_trip(seconds):
    stamp = conv.seconds_to_stamp(seconds)
    assert 0 <= stamp.nanosec < 1_000_000_000
    assert conv.stamp_to_seconds(stamp) == pytest.approx(seconds, abs=1e-9, rel=1e-15)


@pytest.mark.parametrize('seconds', [-1.0, math.nan, math.inf, 2.0 ** 40])
def test_seconds_to_stamp_refuses_unrepresentable(seconds):
    with pytest.raises(ValueError):
        conv.seconds_to_stamp(seconds)


def test_make_joint_state_fills_nan_not_zeros():
    msg = conv.make_joint_state(12.5, JOINTS, [0.1, 0.2])
    assert isinstance(msg, JointState)
    assert conv.stamp_to_seconds(msg.header.stamp) == 12.5
    assert list(msg.name) == list(JOINTS)
    assert list(msg.position) == [0.1, 0.2]
    assert all(math.isnan(v) for v in msg.velocity) and len(msg.velocity) == 2
    assert all(math.isnan(v) for v in msg.effort) and len(msg.effort) == 2
    back = conv.joint_state_to_arrays(msg, JOINTS, need_velocity=False)
    assert back.ok and back.velocity is None
    with pytest.raises(ValueError):
        conv.make_joint_state(1.0, JOINTS, [0.1, 0.2, 0.3])


def test_make_joint_trajectory_round_trip():
    times = np.array([0.0, 0.1, 0.25])
    positions = np.arange(6.0).reshape(3, 2)
    msg = conv.make_joint_trajectory(T0, JOINTS, times, positions, positions * 10.0)
    assert isinstance(msg.points[1].time_from_start, Duration)
    assert msg.points[2].time_from_start.nanosec == 250_000_000
    back = conv.joint_trajectory_to_arrays(msg, JOINTS)
    assert back.t0 == T0
    np.testing.assert_allclose(back.times, times, atol=1e-9)
    np.testing.assert_array_equal(back.positions, positions)
    np.testing.assert_array_equal(back.velocities, positions * 10.0)
    no_vel = conv.make_joint_trajectory(T0, JOINTS, times, positions)
    assert len(no_vel.points[0].velocities) == 0
    with pytest.raises(ValueError):
        conv.make_joint_trajectory(T0, JOINTS, [0.0, 0.0, 0.1], positions)


def test_make_float64_multiarray_layout():
    labels = ['generation', 'best_cost', 'mean_cost', 'spread', 'evaluations',
              'validation_nrmse']
    msg = conv.make_float64_multiarray([3, 0.5, 0.7, 0.1, 120, 0.02], labels)
    assert isinstance(msg, Float64MultiArray)
    (dim,) = msg.layout.dim
    assert dim.label == 'generation,best_cost,mean_cost,spread,evaluations,validation_nrmse'
    assert (dim.size, dim.stride) == (6, 6)
    assert list(msg.data) == [3, 0.5, 0.7, 0.1, 120, 0.02]
    table = conv.make_float64_multiarray(np.arange(12.0).reshape(2, 6), labels)
    rows, fields = table.layout.dim
    assert (rows.label, rows.size, rows.stride) == ('rows', 2, 12)
    assert (fields.size, fields.stride) == (6, 6)
    assert list(table.data) == list(range(12))
    with pytest.raises(ValueError):
        conv.make_float64_multiarray([1.0, 2.0], labels)
    with pytest.raises(ValueError):
        conv.make_float64_multiarray([1.0], ['a,b'])


# ---------------------------------------------------------------- property test

NAMES = st.one_of(st.sampled_from(['joint1', 'joint2', 'gripper', '']), st.text(max_size=8))
FLOATS = st.one_of(st.floats(allow_nan=True, allow_infinity=True),
                   st.sampled_from([0.0, 1e308, -1e308, 1e6, 1e-300, math.nan]))
FLOAT_LISTS = st.lists(FLOATS, max_size=5)
SEC = st.one_of(st.integers(-2 ** 31, 2 ** 31 - 1), st.integers(999, 1003))
NANOSEC = st.integers(0, 2 ** 32 - 1)


@st.composite
def joint_states(draw):
    msg = JointState()
    msg.header.stamp = Time(sec=draw(SEC), nanosec=draw(NANOSEC))
    msg.name = draw(st.one_of(st.lists(NAMES, max_size=5),
                              st.permutations(['joint1', 'joint2', 'gripper'])))
    size = len(msg.name)
    same = st.lists(FLOATS, min_size=size, max_size=size)
    msg.position = draw(st.one_of(same, FLOAT_LISTS))
    msg.velocity = draw(st.one_of(same, FLOAT_LISTS))
    msg.effort = draw(st.one_of(same, FLOAT_LISTS))
    return msg


@st.composite
def plausible_joint_states(draw):
    """Mostly valid messages near T0, so that samples do reach the buffer."""
    names = draw(st.permutations(['joint1', 'joint2', 'gripper']))
    values = draw(st.sampled_from([st.floats(-10.0, 10.0)] * 3 + [FLOATS]))
    msg = JointState()
    msg.header.stamp = Time(sec=int(T0), nanosec=10_000_000 * draw(st.integers(0, 150)))
    msg.name = names
    msg.position = draw(st.lists(values, min_size=3, max_size=3))
    msg.velocity = draw(st.lists(values, min_size=3, max_size=3))
    msg.effort = draw(st.lists(values, min_size=3, max_size=3))
    return msg


ANY_JOINT_STATES = st.lists(st.one_of(joint_states(), plausible_joint_states(),
                                      plausible_joint_states()), max_size=15)


@st.composite
def joint_trajectories(draw):
    msg = JointTrajectory()
    msg.header.stamp = Time(sec=draw(SEC), nanosec=draw(NANOSEC))
    msg.joint_names = draw(st.one_of(st.lists(NAMES, max_size=4),
                                     st.permutations(['joint1', 'joint2', 'gripper'])))
    size = len(msg.joint_names)
    same = st.lists(FLOATS, min_size=size, max_size=size)
    points = []
    for _ in range(draw(st.integers(0, 5))):
        point = JointTrajectoryPoint()
        point.time_from_start = Duration(sec=draw(st.integers(-2 ** 31, 2 ** 31 - 1)),
                                         nanosec=draw(NANOSEC))
        point.positions = draw(st.one_of(same, FLOAT_LISTS))
        point.velocities = draw(st.one_of(same, FLOAT_LISTS))
        points.append(point)
    msg.points = points
    return msg


@st.composite
def plausible_joint_trajectories(draw):
    """Mostly valid references, so that some do reach the buffer."""
    names = draw(st.permutations(['joint1', 'joint2', 'gripper']))
    values = draw(st.sampled_from([st.floats(-10.0, 10.0)] * 3 + [FLOATS]))
    size = draw(st.integers(1, 5))
    steps = draw(st.lists(st.integers(1, 10 ** 9), min_size=size, max_size=size))
    positions = draw(st.lists(st.lists(values, min_size=3, max_size=3), min_size=size,
                              max_size=size))
    velocities = draw(st.one_of(st.just(None), st.lists(
        st.lists(values, min_size=3, max_size=3), min_size=size, max_size=size)))
    return trajectory(names=names, times=np.cumsum(steps) * 1e-9, positions=positions,
                      velocities=velocities, stamp=draw(st.sampled_from([0, int(T0)])))


@settings(max_examples=500, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(states=ANY_JOINT_STATES, commands=ANY_JOINT_STATES,
       references=st.lists(st.one_of(joint_trajectories(), plausible_joint_trajectories()),
                           max_size=3),
       need_tau=st.booleans())
def test_property_arbitrary_messages_never_raise_and_stay_finite(
        states, commands, references, need_tau):
    buffer = StreamBuffer(JOINTS, 0.01, 5.0, 0.5, need_tau=need_tau, need_desired=True,
                          pair_tolerance=1.0)
    for msg in states:
        result = conv.joint_state_to_arrays(msg, JOINTS, need_effort=need_tau)
        assert result.reason in conv.REJECTION_REASONS if not result.ok else True
        if result.ok:
            assert np.isfinite(result.position).all() and np.isfinite(result.velocity).all()
            buffer.add_state(result.stamp, result.position, result.velocity, result.effort)
        else:
            buffer.count_drop('state', result.reason)
    for msg in commands:
        result = conv.joint_state_to_arrays(msg, JOINTS)
        if result.ok:
            buffer.add_command(result.stamp, result.position, result.velocity)
    for msg in references:
        result = conv.joint_trajectory_to_arrays(msg, JOINTS, now=T0)
        if result.ok:
            assert np.all(np.diff(result.times) > 0.0)
            buffer.add_reference(*result)
        else:
            assert result.reason in conv.REJECTION_REASONS
    for segment in buffer.snapshot():
        for values in (segment.theta, segment.theta_dot, segment.theta_d,
                       segment.theta_d_dot):
            assert np.isfinite(values).all()
        assert np.all(np.diff(segment.t) > 0.0)
    latest = buffer.latest_state()
    if latest is not None:
        assert all(np.isfinite(np.asarray(v)).all() for v in latest)
    reference = buffer.reference_at(T0 + np.linspace(-10.0, 10.0, 9))
    if reference is not None:
        assert np.isfinite(reference[0]).all() and np.isfinite(reference[1]).all()
    stats = buffer.stats()
    assert stats['counters']['resample_failed'] == 0


def _three_passes(raw, need_effort):
    """Read as read_joint_state did, in three passes: strict, then without what is missing."""
    def read(velocity, effort):
        return conv.joint_state_cdr_to_arrays(raw, JOINTS, velocity, effort)
    sample = read(True, True)
    if not sample.ok:
        if sample.reason == 'missing_velocity':
            sample = read(False, True)
            if not sample.ok and sample.reason == 'missing_effort':
                sample = read(False, False)
        elif sample.reason == 'missing_effort':
            sample = read(True, False)
    if sample.ok and need_effort and sample.effort is None:
        return conv.Rejection('missing_effort', 'effort is empty or NaN (case torque)')
    return sample


_FIELD = st.one_of(st.just(()), st.lists(st.sampled_from([0.5, -1.0, math.nan, math.inf]),
                                         min_size=2, max_size=2))


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(velocity=_FIELD, effort=_FIELD, need_effort=st.booleans())
def test_one_pass_read_equals_the_strict_then_relaxed_rule(velocity, effort, need_effort):
    from rkgnn_ros.identification.sources import read_joint_state
    raw = serialize_message(joint_state(velocity=velocity, effort=effort))
    got, expected = read_joint_state(raw, JOINTS, need_effort), _three_passes(raw, need_effort)
    assert got.ok == expected.ok
    if expected.ok:
        for name in ('position', 'velocity', 'effort'):
            a, b = getattr(got, name), getattr(expected, name)
            assert (a is None) == (b is None)
            if a is not None:
                np.testing.assert_array_equal(a, b)
    else:
        assert (got.reason, got.message) == (expected.reason, expected.message)

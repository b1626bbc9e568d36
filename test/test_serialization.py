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

"""The prediction's direct CDR serialization equals the message rclpy would serialize."""

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from rkgnn_ros.conversions import make_joint_trajectory, serialize_joint_trajectory
from trajectory_msgs.msg import JointTrajectory


@pytest.mark.parametrize('names', [['joint1', 'j2', 'elbow_x'], ['a'], ['ab', 'cde'],
                                   ['x' * 5, 'y' * 6, 'z', 'w' * 3], []])
@pytest.mark.parametrize('with_velocities', [True, False])
@pytest.mark.parametrize('k', [0, 1, 2, 3, 201])
def test_bytes_decode_to_the_same_message(names, with_velocities, k):
    rng = np.random.default_rng(k + 7 * len(names))
    n = len(names)
    times = np.arange(k) * 0.01 + 0.003
    positions = rng.standard_normal((k, n)) * 1e3
    velocities = rng.standard_normal((k, n)) if with_velocities else None
    stamp = 1795406535.299744
    msg = make_joint_trajectory(stamp, names, times, positions, velocities)
    data = serialize_joint_trajectory(stamp, names, times, positions, velocities)
    # the CDR decoder is strict about sizes and alignment: equal messages mean equal layout
    assert deserialize_message(data, JointTrajectory) == msg
    # rclpy's own bytes have the same length up to its trailing padding
    assert len(serialize_message(msg)) >= len(data)


def test_special_values_and_unicode_names_survive():
    names = ['schulter', 'ellbögen']
    positions = np.array([[np.nan, np.inf], [-np.inf, 5e-324]])
    data = serialize_joint_trajectory(12.5, names, [0.0, 2.0], positions, positions)
    msg = deserialize_message(data, JointTrajectory)
    assert msg.joint_names == names
    np.testing.assert_array_equal(np.array([p.positions for p in msg.points]), positions)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (12, 500_000_000)
    assert [p.time_from_start.sec for p in msg.points] == [0, 2]


def test_bad_input_is_refused_like_the_message_builder():
    with pytest.raises(ValueError, match='positions have shape'):
        serialize_joint_trajectory(1.0, ['a', 'b'], [0.0, 1.0], np.zeros((2, 3)))
    with pytest.raises(ValueError, match='velocities have shape'):
        serialize_joint_trajectory(1.0, ['a'], [0.0, 1.0], np.zeros((2, 1)), np.zeros((3, 1)))
    with pytest.raises(ValueError, match='strictly increasing'):
        serialize_joint_trajectory(1.0, ['a'], [0.0, 0.0], np.zeros((2, 1)))
    with pytest.raises(ValueError, match='stamp'):
        serialize_joint_trajectory(-1.0, ['a'], [0.0], np.zeros((1, 1)))


def test_a_kept_layout_carries_no_values_from_an_earlier_call():
    names = ['j1', 'j2', 'j3']
    times = np.arange(201) * 0.01
    rng = np.random.default_rng(3)
    for stamp in (5.25, 1795406535.299744, 7.0):  # same layout, new values every call
        positions = rng.standard_normal((201, 3))
        velocities = rng.standard_normal((201, 3))
        data = serialize_joint_trajectory(stamp, names, times, positions, velocities)
        expected = make_joint_trajectory(stamp, names, times, positions, velocities)
        assert deserialize_message(data, JointTrajectory) == expected
    # another horizon and other names get their own layout
    data = serialize_joint_trajectory(1.0, ['a'], times[:3], np.ones((3, 1)))
    assert deserialize_message(data, JointTrajectory) == make_joint_trajectory(
        1.0, ['a'], times[:3], np.ones((3, 1)))

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
Reading a reference JointTrajectory from its CDR bytes, and the size budgets.

The raw path (:func:`~rkgnn_ros.wire.conversions.joint_trajectory_cdr_to_arrays`) must give
exactly what the message path gives on the deserialized message, for any message; any
bytes at all (truncated, corrupted, random) give a result or a rejection, never an
exception; a message over a budget is refused from its first bytes.
"""

import math

from hypothesis import given, HealthCheck, settings, strategies as st
import numpy as np
from rclpy.serialization import serialize_message
from rkgnn_ros.wire.cdr import joint_trajectory_cdr_size, parse_joint_trajectory_cdr
from rkgnn_ros.wire.conversions import (joint_trajectory_cdr_to_arrays, joint_trajectory_to_arrays,
                                        MAX_TRAJECTORY_POINTS, Rejection, REJECTION_REASONS)
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

JOINTS = ('j1', 'j2', 'j3')
_FLOATS = st.one_of(st.floats(allow_nan=True, allow_infinity=True),
                    st.sampled_from([0.0, 1e300, -1e300, 5e-324]))
_NAMES = st.lists(st.sampled_from(['j1', 'j2', 'j3', 'gripper', 'j1 ', 'é']), max_size=5)


@st.composite
def trajectories(draw):
    msg = JointTrajectory(joint_names=draw(_NAMES))
    msg.header.stamp.sec = draw(st.integers(-2 ** 31, 2 ** 31 - 1))
    msg.header.stamp.nanosec = draw(st.integers(0, 999_999_999))
    msg.header.frame_id = draw(st.text(max_size=5))
    for _ in range(draw(st.integers(0, 5))):
        point = JointTrajectoryPoint(positions=draw(st.lists(_FLOATS, max_size=5)),
                                     velocities=draw(st.lists(_FLOATS, max_size=5)),
                                     accelerations=draw(st.lists(_FLOATS, max_size=2)))
        point.time_from_start.sec = draw(st.integers(-2 ** 31, 2 ** 31 - 1))
        point.time_from_start.nanosec = draw(st.integers(0, 999_999_999))
        msg.points.append(point)
    return msg


def _same(a, b):
    assert type(a) is type(b), (a, b)
    if isinstance(a, Rejection):
        assert a == b
        return
    assert a.t0 == b.t0
    for x, y in ((a.times, b.times), (a.positions, b.positions), (a.velocities, b.velocities)):
        if x is None or y is None:
            assert x is None and y is None
        else:
            np.testing.assert_array_equal(x, y)


@settings(max_examples=500, deadline=None, suppress_health_check=list(HealthCheck))
@given(trajectories(), st.sampled_from([None, 1000.0]))
def test_raw_reference_reads_as_the_message_does(msg, now):
    raw = serialize_message(msg)
    _same(joint_trajectory_cdr_to_arrays(raw, JOINTS, now), joint_trajectory_to_arrays(
        msg, JOINTS, now))


@settings(max_examples=500, deadline=None, suppress_health_check=list(HealthCheck))
@given(trajectories(), st.integers(0, 400), st.binary(max_size=8), st.booleans())
def test_any_bytes_give_a_result_or_a_rejection(msg, at, junk, cut):
    raw = serialize_message(msg)
    raw = raw[:at] if cut else raw[:at] + junk + raw[at + len(junk):]
    result = joint_trajectory_cdr_to_arrays(raw, JOINTS, 1000.0)
    assert result is None or result.ok or result.reason in REJECTION_REASONS
    joint_trajectory_cdr_size(raw)
    parse_joint_trajectory_cdr(raw)


def test_the_point_budget_is_read_from_the_first_bytes():
    msg = JointTrajectory(joint_names=list(JOINTS))
    msg.header.stamp.sec = 5
    for k in range(MAX_TRAJECTORY_POINTS + 1):
        point = JointTrajectoryPoint(positions=[0.0, 0.0, 0.0])
        point.time_from_start.sec = k
        msg.points.append(point)
    raw = serialize_message(msg)
    assert joint_trajectory_cdr_size(raw) == (JOINTS, MAX_TRAJECTORY_POINTS + 1)
    result = joint_trajectory_cdr_to_arrays(raw[:200], JOINTS)  # the points need not be there
    assert result.reason == 'over_budget' and str(MAX_TRAJECTORY_POINTS) in result.message
    assert joint_trajectory_to_arrays(msg, JOINTS).reason == 'over_budget'
    msg.points.pop()
    result = joint_trajectory_cdr_to_arrays(serialize_message(msg), JOINTS)
    assert result.ok and result.times.size == MAX_TRAJECTORY_POINTS
    assert math.isclose(result.times[-1], MAX_TRAJECTORY_POINTS - 1)

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
CDR both ways, against rclpy's own (de)serialization.

The prediction's direct serialization equals the message rclpy would serialize, and the
identifier's direct reading of a raw JointState gives what reading the deserialized
message gives.
"""

import math
import struct

from builtin_interfaces.msg import Time
from hypothesis import given, HealthCheck, settings
from hypothesis import strategies as st
import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from rkgnn_ros.wire.conversions import (joint_state_cdr_to_arrays, joint_state_to_arrays,
                                        make_joint_trajectory, parse_joint_state_cdr,
                                        serialize_joint_trajectory)
from sensor_msgs.msg import JointState
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


# ---------------------------------------------------------------- reading raw JointState

JOINTS = ('joint1', 'joint2', 'joint3')


def _joint_state(names=JOINTS, position=(0.1, 0.2, 0.3), velocity=(1.0, 2.0, 3.0),
                 effort=(4.0, 5.0, 6.0), sec=1795406535, nanosec=299744000, frame_id=''):
    msg = JointState(name=list(names), position=[float(v) for v in position],
                     velocity=[float(v) for v in velocity], effort=[float(v) for v in effort])
    msg.header.stamp = Time(sec=sec, nanosec=nanosec)
    msg.header.frame_id = frame_id
    return msg


def _cdr(msg: JointState, big_endian: bool = False) -> bytes:
    """Write ``msg`` as XCDR1 by hand, in either byte order (an independent writer)."""
    order = '>' if big_endian else '<'
    out = bytearray(b'\x00\x00\x00\x00' if big_endian else b'\x00\x01\x00\x00')

    def put(fmt, *values):
        size = struct.calcsize(fmt[-1])
        out.extend(bytes(-(len(out) - 4) % size))
        out.extend(struct.pack(order + fmt, *values))

    def put_string(text):
        data = text.encode('utf-8') + b'\x00'
        put('I', len(data))
        out.extend(data)

    put('iI', msg.header.stamp.sec, msg.header.stamp.nanosec)
    put_string(msg.header.frame_id)
    put('I', len(msg.name))
    for name in msg.name:
        put_string(name)
    for values in (msg.position, msg.velocity, msg.effort):
        put('I', len(values))
        if len(values):
            put(f'{len(values)}d', *values)
    return bytes(out)


def _same_result(a, b):
    assert type(a) is type(b), (a, b)
    if not a.ok:
        assert a == b
        return
    assert a.stamp == b.stamp and a.sec_nanosec == b.sec_nanosec
    for x, y in zip(a[1:4], b[1:4]):
        if x is None or y is None:
            assert x is None and y is None
        else:
            np.testing.assert_array_equal(x, y)


def test_hand_written_cdr_is_what_rclpy_writes():
    # guards the reference writer the tests below rely on
    for msg in (_joint_state(), _joint_state(names=['a', 'ellbögen'], position=[1, 2],
                                             velocity=[], effort=[3, 4], frame_id='base')):
        # (rclpy leaves its alignment padding uninitialised, so bytes are not compared)
        ours, theirs = _cdr(msg), serialize_message(msg)
        assert deserialize_message(ours, JointState) == msg
        assert len(ours) <= len(theirs) <= len(ours) + 8


@pytest.mark.parametrize('big_endian', [False, True])
def test_raw_reading_gives_the_fields(big_endian):
    msg = _joint_state(names=('joint2', 'gripper', 'joint1', 'joint3'),
                       position=(0.2, 9.0, 0.1, 0.3), velocity=(), effort=(-1, -2, -3, -4),
                       frame_id='world')
    sec, nanosec, names, position, velocity, effort = parse_joint_state_cdr(
        _cdr(msg, big_endian))
    assert (sec, nanosec) == (1795406535, 299744000)
    assert names == ('joint2', 'gripper', 'joint1', 'joint3')
    np.testing.assert_array_equal(position, [0.2, 9.0, 0.1, 0.3])
    assert velocity.size == 0
    np.testing.assert_array_equal(effort, [-1.0, -2.0, -3.0, -4.0])
    sample = joint_state_cdr_to_arrays(_cdr(msg, big_endian), JOINTS, need_velocity=False,
                                       need_effort=True)
    np.testing.assert_array_equal(sample.position, [0.1, 0.2, 0.3])
    np.testing.assert_array_equal(sample.effort, [-3.0, -1.0, -4.0])
    assert sample.velocity is None and sample.sec_nanosec == (1795406535, 299744000)


def test_samples_are_copies_not_views_of_the_bytes():
    sample = joint_state_cdr_to_arrays(serialize_message(_joint_state()), JOINTS,
                                       need_effort=True)
    for values in sample[1:4]:
        assert values.flags.writeable and values.base is None or values.base.base is None


def test_what_it_cannot_read_is_left_to_rclpy():
    data = serialize_message(_joint_state())
    end = len(_cdr(_joint_state()))  # rclpy's bytes carry 8 spare bytes after the message
    assert parse_joint_state_cdr(data[:end]) is not None
    # another encapsulation (XCDR2), a truncation inside any field, a string without its
    # NUL, a count beyond the end, bytes that are not UTF-8
    unreadable = [b'\x00\x07' + data[2:], b'', b'\x00\x01']
    unreadable += [data[:cut] for cut in range(end)]
    no_nul = bytearray(data)
    no_nul[24:28] = b'\x06\x00\x00\x00'  # first name 'joint1' without its NUL
    huge = bytearray(data)
    huge[20:24] = b'\xff\xff\xff\x7f'  # 2**31 names
    latin = serialize_message(_joint_state(names=('joint1', 'joint2', 'jointX')))
    latin = latin.replace(b'jointX', b'joint\xe9')
    unreadable += [bytes(no_nul), bytes(huge), latin]
    for raw in unreadable:
        assert parse_joint_state_cdr(raw) is None, raw
        assert joint_state_cdr_to_arrays(raw, JOINTS) is None


def test_any_byte_string_is_read_or_left_never_raised():
    data = serialize_message(_joint_state())
    rng = np.random.default_rng(3)
    for _ in range(3000):
        raw = bytearray(data)
        for at in rng.integers(0, len(raw), size=rng.integers(1, 4)):
            raw[at] = int(rng.integers(0, 256))
        result = joint_state_cdr_to_arrays(bytes(raw), JOINTS, need_effort=True)
        assert result is None or result.ok in (True, False)
        if result is not None and result.ok:  # what it read, rclpy reads the same way
            _same_result(result, joint_state_to_arrays(
                deserialize_message(bytes(raw), JointState), JOINTS, need_effort=True))


_NAMES = st.one_of(st.sampled_from(['joint1', 'joint2', 'joint3', 'gripper', '']),
                   st.text(st.characters(blacklist_categories=('Cs',),
                                         blacklist_characters='\x00'), max_size=8))
_FLOATS = st.one_of(st.floats(allow_nan=True, allow_infinity=True),
                    st.sampled_from([0.0, -0.0, 1e308, 5e-324, math.nan]))


@st.composite
def _any_joint_state(draw):
    names = draw(st.one_of(st.lists(_NAMES, max_size=5), st.permutations(
        ['joint1', 'joint2', 'joint3', 'gripper'])))
    same = st.lists(_FLOATS, min_size=len(names), max_size=len(names))
    fields = [draw(st.one_of(same, same, st.lists(_FLOATS, max_size=5))) for _ in range(3)]
    return _joint_state(names, *fields, sec=draw(st.integers(-2 ** 31, 2 ** 31 - 1)),
                        nanosec=draw(st.integers(0, 2 ** 32 - 1)),
                        frame_id=draw(st.sampled_from(['', 'base_link', 'wörld'])))


@settings(max_examples=500, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(msg=_any_joint_state(), need_velocity=st.booleans(), need_effort=st.booleans(),
       big_endian=st.booleans())
def test_raw_reading_equals_reading_the_message(msg, need_velocity, need_effort,
                                                big_endian):
    expected = joint_state_to_arrays(msg, JOINTS, need_velocity, need_effort)
    for raw in (serialize_message(msg), _cdr(msg, big_endian)):
        _same_result(joint_state_cdr_to_arrays(raw, JOINTS, need_velocity, need_effort),
                     expected)

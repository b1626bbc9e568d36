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
The one boundary between ROS 2 messages and numpy arrays.

Incoming messages become arrays here, once, and outgoing arrays become messages here. The
module imports message classes only (never rclpy), so it is tested with plain pytest.

Parsing never raises on message content. :func:`joint_state_to_arrays` and
:func:`joint_trajectory_to_arrays` return either a result tuple (``result.ok`` is True) or
a :class:`Rejection` (``result.ok`` is False) carrying a stable reason code from
:data:`REJECTION_REASONS` and a human message naming the sizes or the joint involved. The
caller logs the message (throttled) and counts the reason.

JointState policy
-----------------
Values are mapped by name to the configured joint order; extra joints (a gripper) are
ignored, a duplicate name anywhere in the message is rejected. The checks run in this
order, and the first failing one gives the reason:

1. ``'empty'``: ``name`` or ``position`` is empty.
2. ``'size_mismatch'``: ``position``, or a non-empty ``velocity`` or ``effort``, has a
   length different from ``name`` (a malformed message, whatever fields are needed).
3. ``'duplicate_name'``, then ``'missing_joint'`` (the first configured joint absent).
4. ``'zero_stamp'``: a stamp of exactly zero (``use_sim_time`` before the first clock
   message); ``'invalid_stamp'``: a negative stamp.
5. ``'non_finite'``: NaN or inf in the position of a configured joint.
6. Velocity, when ``need_velocity``: empty, or NaN for a configured joint, means *missing*
   (NaN is the ROS convention for "not filled"), rejected as ``'missing_velocity'``; the
   sample is dropped, velocities are never estimated from positions here. An infinite
   velocity is ``'non_finite'``. When velocity is not needed, a missing or non-finite
   velocity is returned as None and never causes a rejection. With ``need_velocity`` set
   to :data:`IF_PRESENT`, a missing velocity is None and an infinite one ``'non_finite'``
   (the first non-finite value decides which).
7. Effort, when ``need_effort``: the same rule with ``'missing_effort'``.

Any other failure (an object that is not a JointState at all) is ``'malformed'``.

Size budgets
------------
Before anything is built from a message, its size is checked against
:data:`MAX_STATE_BYTES` (a serialized JointState), :data:`MAX_TRAJECTORY_BYTES` and
:data:`MAX_TRAJECTORY_POINTS` (a reference JointTrajectory), :data:`MAX_MESSAGE_JOINTS`
(names in either) and :data:`MAX_NAME_BYTES` (one name); a message over any of them is
``'over_budget'``, first of all the reasons. A real arm's messages are far below them (a
3-joint JointState is about 150 bytes; a 10 s plan at 100 Hz for 7 joints about 1.3 MB).

The CDR wire form of the two messages the 1 kHz paths handle (a JointState read from raw
bytes, a prediction written as bytes) is in :mod:`rkgnn_ros.wire.cdr`; outgoing messages are
built in :mod:`rkgnn_ros.wire.messages` (re-exported here).
"""

from functools import lru_cache
from typing import NamedTuple, Optional, Sequence, Tuple, Union

import numpy as np
from rkgnn_ros.wire.cdr import (is_plain_cdr, joint_trajectory_cdr_size, parse_joint_state_cdr,
                                parse_joint_trajectory_cdr)
from rkgnn_ros.wire.messages import (duration_to_seconds, make_float64_multiarray,
                                     make_joint_state, make_joint_trajectory, seconds_of,
                                     seconds_to_duration, seconds_to_stamp,
                                     serialize_joint_trajectory, stamp_to_seconds)
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory

__all__ = [
    'REJECTION_REASONS', 'IF_PRESENT', 'Rejection', 'JointSample', 'TrajectorySample',
    'MAX_MESSAGE_JOINTS', 'MAX_NAME_BYTES', 'MAX_STATE_BYTES', 'MAX_TRAJECTORY_BYTES',
    'MAX_TRAJECTORY_POINTS',
    'joint_state_to_arrays', 'joint_state_cdr_to_arrays', 'parse_joint_state_cdr',
    'joint_trajectory_to_arrays', 'joint_trajectory_cdr_to_arrays', 'make_joint_state',
    'make_joint_trajectory', 'serialize_joint_trajectory', 'make_float64_multiarray',
    'stamp_to_seconds',
    'seconds_to_stamp', 'duration_to_seconds', 'seconds_to_duration',
]

#: Every reason code the parsing functions can return.
REJECTION_REASONS = (
    'empty',             # no names, no positions, or (trajectory) no points
    'size_mismatch',     # an array's length differs from the number of names
    'duplicate_name',    # a joint name appears twice in one message
    'missing_joint',     # a configured joint is absent
    'zero_stamp',        # header stamp exactly zero
    'invalid_stamp',     # negative stamp
    'non_finite',        # NaN/inf in a used position, inf in a used velocity/effort
    'missing_velocity',  # velocity needed but empty or NaN
    'missing_effort',    # effort needed but empty or NaN
    'non_increasing_time',  # trajectory time_from_start negative or not increasing
    'malformed',         # not the expected message at all
    'over_budget',       # larger than a size budget (bytes, points, joints, name bytes)
)

#: Size budgets of input messages (see *Size budgets* above).
MAX_MESSAGE_JOINTS = 256
MAX_NAME_BYTES = 256
MAX_STATE_BYTES = 64 * 1024
MAX_TRAJECTORY_POINTS = 10_000
MAX_TRAJECTORY_BYTES = 8 * 1024 * 1024


class Rejection(NamedTuple):
    """
    Why a message was not turned into arrays.

    ``reason`` is a stable code from :data:`REJECTION_REASONS` (for counters), ``message``
    a sentence for the log naming sizes or the joint.
    """

    reason: str
    message: str

    @property
    def ok(self) -> bool:
        """Return False: a rejection carries no data."""
        return False


class JointSample(NamedTuple):
    """
    One JointState as arrays in the configured joint order.

    ``stamp`` is in seconds; ``position`` has shape (n,); ``velocity`` and ``effort`` have
    shape (n,) or are None when not available (only possible when not needed).
    """

    stamp: float
    position: np.ndarray
    velocity: Optional[np.ndarray]
    effort: Optional[np.ndarray]
    #: the header stamp as it came, ``(sec, nanosec)``, for stamping what derives from it
    sec_nanosec: Tuple[int, int] = (0, 0)

    @property
    def ok(self) -> bool:
        """Return True: the message was converted."""
        return True


class TrajectorySample(NamedTuple):
    """
    A JointTrajectory as arrays in the configured joint order.

    ``t0`` is the header stamp in seconds, ``times`` (K,) the strictly increasing
    ``time_from_start`` values, ``positions`` (K, n), ``velocities`` (K, n) or None when
    the points carry no (or NaN) velocities.
    """

    t0: float
    times: np.ndarray
    positions: np.ndarray
    velocities: Optional[np.ndarray]

    @property
    def ok(self) -> bool:
        """Return True: the message was converted."""
        return True


@lru_cache(maxsize=64)
def _name_index(names: Tuple[str, ...], joints: Tuple[str, ...]):
    """
    Map configured joints to their columns in a message.

    Returns ``(index array, None)`` or ``(None, Rejection)``. Cached: a stream normally
    repeats the same name list in every message.
    """
    lookup = {}
    for i, name in enumerate(names):
        if name in lookup:
            return None, Rejection('duplicate_name', f'duplicate joint name {name!r}')
        lookup[name] = i
    index = []
    for joint in joints:
        if joint not in lookup:
            return None, Rejection(
                'missing_joint', f'missing joint {joint!r} (message has {list(names)})')
        index.append(lookup[joint])
    return np.asarray(index, dtype=np.intp), None


def _bytes_rejection(raw, limit: int, what: str) -> Optional[Rejection]:
    size = len(raw)
    if size > limit:
        return Rejection('over_budget', f'{what} of {size} bytes is over the budget of '
                                        f'{limit} bytes')
    return None


#: ``need_velocity`` / ``need_effort`` value: a missing field is None, an infinite one rejects.
IF_PRESENT = 'if_present'


@lru_cache(maxsize=64)
def _names_rejection(names: Tuple[str, ...]) -> Optional[Rejection]:
    """Return the rejection of joint names over the budgets, else None (cached as above)."""
    if len(names) > MAX_MESSAGE_JOINTS:
        return Rejection('over_budget', f'{len(names)} joint names are over the budget of '
                                        f'{MAX_MESSAGE_JOINTS}')
    for name in names:
        size = len(name.encode('utf-8', 'surrogatepass'))
        if size > MAX_NAME_BYTES:
            return Rejection('over_budget', f'a joint name of {size} bytes is over the budget '
                                            f'of {MAX_NAME_BYTES} bytes')
    return None


def _stamp_rejection(seconds: float) -> Optional[Rejection]:
    if seconds == 0.0:
        return Rejection('zero_stamp', 'stamp is zero (no clock yet under use_sim_time?)')
    if not seconds > 0.0:
        return Rejection('invalid_stamp', f'stamp {seconds} s is negative')
    return None


def _optional_field(values, index, joints, field_name, needed, missing_reason):
    """
    Pick a velocity/effort field; returns ``(array or None, Rejection or None)``.

    Empty or NaN means missing; inf is non-finite. A needed field (True) rejects either; a
    field that is not (False) is None then; :data:`IF_PRESENT`: missing is None, inf rejects.
    """
    if values.size == 0:
        if needed and needed is not IF_PRESENT:
            return None, Rejection(missing_reason, f'{field_name} is empty')
        return None, None
    used = values[index]
    finite = np.isfinite(used)
    if finite.all():
        return used, None
    if not needed:
        return None, None
    bad = int(np.flatnonzero(~finite)[0])
    if np.isnan(used[bad]):
        if needed is IF_PRESENT:
            return None, None
        return None, Rejection(missing_reason, f'{field_name} is NaN for joint {joints[bad]!r}')
    return None, Rejection(
        'non_finite', f'{field_name} is {used[bad]} for joint {joints[bad]!r}')


def joint_state_to_arrays(
        msg: JointState, joints: Sequence[str], need_velocity: bool = True,
        need_effort: bool = False) -> Union[JointSample, Rejection]:
    """
    Turn a JointState into arrays ordered as ``joints``, or say why not.

    Parameters
    ----------
    msg : sensor_msgs.msg.JointState
        The incoming message (θ in position, θ̇ in velocity, τ in effort).
    joints : sequence of str
        The configured joint names, in column order (n of them).
    need_velocity, need_effort : bool
        Whether a missing velocity / effort rejects the sample.

    Returns
    -------
    JointSample or Rejection
        ``JointSample(stamp, position (n,), velocity (n,) or None, effort (n,) or None)``
        or ``Rejection(reason, message)``; see the module docstring for the rules. Never
        raises on message content.

    """
    try:
        stamp = msg.header.stamp
        return _joint_sample(tuple(msg.name), np.asarray(msg.position, dtype=float),
                             np.asarray(msg.velocity, dtype=float),
                             np.asarray(msg.effort, dtype=float), (stamp.sec, stamp.nanosec),
                             tuple(joints), need_velocity, need_effort)
    except Exception as error:  # last resort: parsing must never raise
        return Rejection('malformed', f'cannot read JointState: {error!r}')


def joint_state_cdr_to_arrays(
        raw: bytes, joints: Sequence[str], need_velocity: bool = True,
        need_effort: bool = False) -> Union[JointSample, Rejection, None]:
    """
    Do what :func:`joint_state_to_arrays` does, from the serialized JointState (CDR).

    For a subscription created with ``raw=True``: taking the bytes and reading them here
    costs a fifth of what rclpy's building of a JointState object costs (about 10 against
    50 µs per message on the development machine), which matters at 1 kHz. Same rules,
    reasons and results as :func:`joint_state_to_arrays` on the deserialized message (a
    property test holds the two equal).

    Returns None when ``raw`` is not plain CDR this parser reads (another encapsulation,
    or bytes that do not form a JointState); the nodes refuse those as ``'malformed'``
    (:func:`~rkgnn_ros.wire.cdr.encapsulation_problem` says why), never handing them to rclpy's
    deserializer, which prints a line on stderr for each malformed message. Bytes over
    :data:`MAX_STATE_BYTES` are ``'over_budget'`` without being read.
    """
    try:
        rejection = _bytes_rejection(raw, MAX_STATE_BYTES, 'a JointState')
        if rejection is not None:
            return rejection
        parsed = parse_joint_state_cdr(raw)
    except Exception:  # noqa: B902 - never raises; unreadable here means "ask rclpy"
        return None
    if parsed is None:
        return None
    sec, nanosec, names, position, velocity, effort = parsed
    try:
        return _joint_sample(names, position, velocity, effort, (sec, nanosec),
                             tuple(joints), need_velocity, need_effort)
    except Exception as error:  # last resort: parsing must never raise
        return Rejection('malformed', f'cannot read JointState: {error!r}')


def _joint_sample(names, position, velocity, effort, stamp, joints, need_velocity,
                  need_effort) -> Union[JointSample, Rejection]:
    """Apply the JointState rules of the module docstring to fields already read."""
    sec, nanosec = stamp     # the header's stamp: (s, ns)
    rejection = _names_rejection(names)
    if rejection is not None:
        return rejection
    if not names or position.size == 0:
        return Rejection(
            'empty', f'empty JointState: {len(names)} names, {position.size} positions')
    for field_name, values, may_be_empty in (('position', position, False),
                                             ('velocity', velocity, True),
                                             ('effort', effort, True)):
        if values.ndim != 1 or (values.size != len(names)
                                and not (may_be_empty and values.size == 0)):
            return Rejection(
                'size_mismatch',
                f'{field_name} has {values.size} values for {len(names)} names')
    index, rejection = _name_index(names, joints)
    if rejection is not None:
        return rejection
    stamp = seconds_of(sec, nanosec)
    rejection = _stamp_rejection(stamp)
    if rejection is not None:
        return rejection
    pos = position[index]
    finite = np.isfinite(pos)
    if not finite.all():
        bad = int(np.flatnonzero(~finite)[0])
        return Rejection('non_finite', f'position is {pos[bad]} for joint {joints[bad]!r}')
    vel, rejection = _optional_field(
        velocity, index, joints, 'velocity', need_velocity, 'missing_velocity')
    if rejection is not None:
        return rejection
    eff, rejection = _optional_field(
        effort, index, joints, 'effort', need_effort, 'missing_effort')
    if rejection is not None:
        return rejection
    return JointSample(stamp, pos, vel, eff, (int(sec), int(nanosec)))


def joint_trajectory_to_arrays(
        msg: JointTrajectory, joints: Sequence[str],
        now: Optional[float] = None) -> Union[TrajectorySample, Rejection]:
    """
    Turn a JointTrajectory (the planned reference) into arrays, or say why not.

    Parameters
    ----------
    msg : trajectory_msgs.msg.JointTrajectory
        The reference: θd in ``positions``, θ̇d in ``velocities`` of each point.
    joints : sequence of str
        The configured joint names, in column order (n of them).
    now : float, optional
        A zero header stamp means "start now" (the joint_trajectory_controller
        convention); it is replaced by ``now`` when given, else rejected as
        ``'zero_stamp'``.

    Returns
    -------
    TrajectorySample or Rejection
        ``TrajectorySample(t0, times (K,), positions (K, n), velocities (K, n) or None)``.
        Rejected: no names or no points (``'empty'``), ``'duplicate_name'``,
        ``'missing_joint'``, a point whose positions (or non-empty velocities) differ in
        size from ``joint_names`` (``'size_mismatch'``, naming the point), a negative or
        non-increasing ``time_from_start`` (``'non_increasing_time'``, naming the point),
        NaN/inf in a used position or inf in a used velocity (``'non_finite'``). Velocities
        that are empty in every point, or NaN anywhere, are returned as None (missing);
        empty in some points only is ``'size_mismatch'``. More than
        :data:`MAX_TRAJECTORY_POINTS` points or a name over the budgets is
        ``'over_budget'``, checked first. Never raises on message content.

    """
    try:
        rejection = _points_rejection(len(msg.points))
        if rejection is not None:  # before a point is read
            return rejection
        points = [(np.asarray(point.positions, dtype=float),
                   np.asarray(point.velocities, dtype=float),
                   duration_to_seconds(point.time_from_start)) for point in msg.points]
        stamp = msg.header.stamp
        return _trajectory_sample(tuple(msg.joint_names), stamp.sec, stamp.nanosec, points,
                                  tuple(joints), now)
    except Exception as error:  # last resort: parsing must never raise
        return Rejection('malformed', f'cannot read JointTrajectory: {error!r}')


def joint_trajectory_cdr_to_arrays(
        raw: bytes, joints: Sequence[str],
        now: Optional[float] = None) -> Union[TrajectorySample, Rejection, None]:
    """
    Do what :func:`joint_trajectory_to_arrays` does, from the serialized JointTrajectory.

    The size budgets come first and cost nothing per point: bytes over
    :data:`MAX_TRAJECTORY_BYTES` are not read, and the number of points and the names are
    read from the message's first bytes (:func:`~rkgnn_ros.wire.cdr.joint_trajectory_cdr_size`).
    Then the same rules, reasons and results as :func:`joint_trajectory_to_arrays` on the
    deserialized message (a property test holds the two equal). Plain CDR that does not
    form a JointTrajectory is ``'malformed'``; None means another encapsulation, which the
    nodes refuse too (:func:`~rkgnn_ros.wire.cdr.encapsulation_problem`).
    """
    try:
        rejection = _bytes_rejection(raw, MAX_TRAJECTORY_BYTES, 'a JointTrajectory')
        if rejection is not None:
            return rejection
        raw = bytes(raw)
        if not is_plain_cdr(raw):
            return None
        size = joint_trajectory_cdr_size(raw)
        if size is not None:
            rejection = _names_rejection(size[0]) or _points_rejection(size[1])
            if rejection is not None:
                return rejection
        parsed = parse_joint_trajectory_cdr(raw)
        if parsed is None:
            return Rejection('malformed', f'{len(raw)} bytes of CDR that do not form a '
                                          'JointTrajectory')
        sec, nanosec, names, points = parsed
        return _trajectory_sample(names, sec, nanosec, points, tuple(joints), now)
    except Exception as error:  # last resort: parsing must never raise
        return Rejection('malformed', f'cannot read JointTrajectory: {error!r}')


def _points_rejection(count: int) -> Optional[Rejection]:
    if count > MAX_TRAJECTORY_POINTS:
        return Rejection('over_budget', f'{count} points are over the budget of '
                                        f'{MAX_TRAJECTORY_POINTS}')
    return None


def _trajectory_sample(names, sec, nanosec, points, joints, now):
    """
    Apply the JointTrajectory rules to fields already read.

    ``points`` is a sequence of ``(positions, velocities, time_from_start seconds)``.
    """
    rejection = _names_rejection(names) or _points_rejection(len(points))
    if rejection is not None:
        return rejection
    if not names or not points:
        return Rejection(
            'empty', f'empty JointTrajectory: {len(names)} joint names, '
            f'{len(points)} points')
    index, rejection = _name_index(names, joints)
    if rejection is not None:
        return rejection
    t0 = seconds_of(sec, nanosec)
    if t0 == 0.0 and now is not None:
        t0 = float(now)
    rejection = _stamp_rejection(t0)
    if rejection is not None:
        return rejection
    n_names = len(names)
    times = np.empty(len(points))
    positions = np.empty((len(points), len(joints)))
    velocities = np.empty((len(points), len(joints)))
    velocity_sizes = set()
    for k, (pos, vel, t) in enumerate(points):
        if pos.ndim != 1 or pos.size != n_names:
            return Rejection(
                'size_mismatch',
                f'point {k} has {pos.size} positions for {n_names} joint names')
        if vel.ndim != 1 or vel.size not in (0, n_names):
            return Rejection(
                'size_mismatch',
                f'point {k} has {vel.size} velocities for {n_names} joint names')
        velocity_sizes.add(vel.size)
        times[k] = t
        if not (times[k] >= 0.0 and (k == 0 or times[k] > times[k - 1])):
            previous = f' after {times[k - 1]} s' if k else ''
            return Rejection(
                'non_increasing_time',
                f'point {k} has time_from_start {times[k]} s{previous}; times must be '
                '>= 0 and strictly increasing')
        positions[k] = pos[index]
        if vel.size:
            velocities[k] = vel[index]
    if len(velocity_sizes) > 1:
        return Rejection(
            'size_mismatch', 'velocities are given in some points and empty in others')
    finite = np.isfinite(positions)
    if not finite.all():
        k, j = np.argwhere(~finite)[0]
        return Rejection(
            'non_finite',
            f'point {k} position is {positions[k, j]} for joint {joints[j]!r}')
    if velocity_sizes == {0} or np.isnan(velocities).any():
        velocities = None
    elif not np.isfinite(velocities).all():
        k, j = np.argwhere(~np.isfinite(velocities))[0]
        return Rejection(
            'non_finite',
            f'point {k} velocity is {velocities[k, j]} for joint {joints[j]!r}')
    return TrajectorySample(t0, times, positions, velocities)

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
Outgoing messages built from numpy arrays, and the stamps and durations of both directions.

The other half of the boundary of :mod:`rkgnn_ros.wire.conversions` (which parses what comes in
and re-exports these names, the one import path callers use). Imports message classes
only, never rclpy.
"""

import math
from typing import Sequence

from builtin_interfaces.msg import Duration, Time
import numpy as np
from rkgnn_ros.wire.cdr import joint_trajectory_cdr, split_seconds
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, MultiArrayDimension
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

__all__ = ['make_joint_state', 'make_joint_trajectory', 'serialize_joint_trajectory',
           'make_float64_multiarray', 'stamp_to_seconds', 'seconds_to_stamp',
           'duration_to_seconds', 'seconds_to_duration']


def stamp_to_seconds(stamp) -> float:
    """Return a ``builtin_interfaces`` Time (or Duration) as float seconds."""
    return seconds_of(stamp.sec, stamp.nanosec)


def seconds_of(sec, nanosec) -> float:
    """Return a stamp's two fields as float seconds."""
    return float(sec) + float(nanosec) * 1e-9


def duration_to_seconds(duration) -> float:
    """Return a ``builtin_interfaces`` Duration as float seconds."""
    return stamp_to_seconds(duration)


def seconds_to_stamp(seconds: float) -> Time:
    """Return float seconds (finite, >= 0) as a ``builtin_interfaces`` Time."""
    if not seconds >= 0.0:
        raise ValueError(f'a stamp must be >= 0, got {seconds}')
    sec, nanosec = split_seconds(seconds, 'stamp')
    return Time(sec=sec, nanosec=nanosec)


def seconds_to_duration(seconds: float) -> Duration:
    """Return finite float seconds as a ``builtin_interfaces`` Duration."""
    sec, nanosec = split_seconds(seconds, 'duration')
    return Duration(sec=sec, nanosec=nanosec)


def _stamp(stamp) -> Time:
    if isinstance(stamp, Time):
        return stamp
    return seconds_to_stamp(stamp)


def _column(values, n: int, what: str) -> list:
    """Return ``values`` (n,) as a float list; None gives NaN (a field we cannot fill)."""
    if values is None:
        return [math.nan] * n
    arr = np.asarray(values, dtype=float).reshape(-1)
    if arr.size != n:
        raise ValueError(f'{what} has {arr.size} values for {n} names')
    return arr.tolist()


def make_joint_state(stamp, names: Sequence[str], position,
                     velocity=None, effort=None) -> JointState:
    """
    Build a JointState.

    ``stamp`` is float seconds or a Time message. Each of ``position``, ``velocity``,
    ``effort`` is an array (n,) or None; None becomes NaN in every entry (a field we
    cannot fill), never zeros. Raises ValueError on a size mismatch (a programming
    error: our own data has the wrong shape).
    """
    names = [str(name) for name in names]
    msg = JointState()
    msg.header.stamp = _stamp(stamp)
    msg.name = names
    msg.position = _column(position, len(names), 'position')
    msg.velocity = _column(velocity, len(names), 'velocity')
    msg.effort = _column(effort, len(names), 'effort')
    return msg


def make_joint_trajectory(stamp, names: Sequence[str], times, positions,
                          velocities=None, frame_id: str = '') -> JointTrajectory:
    """
    Build a JointTrajectory.

    ``times`` (K,) are seconds from ``stamp`` (>= 0, strictly increasing), written as
    ``time_from_start`` Durations; ``positions`` and ``velocities`` have shape (K, n).
    ``velocities=None`` leaves each point's velocities empty ("not specified" in the
    message definition). ``frame_id`` goes into the header. Raises ValueError on bad
    shapes or times.
    """
    names = [str(name) for name in names]
    times = np.asarray(times, dtype=float).reshape(-1)
    positions = np.asarray(positions, dtype=float)
    if positions.shape != (times.size, len(names)):
        raise ValueError(
            f'positions have shape {positions.shape}, expected {(times.size, len(names))}')
    if velocities is not None:
        velocities = np.asarray(velocities, dtype=float)
        if velocities.shape != positions.shape:
            raise ValueError(
                f'velocities have shape {velocities.shape}, expected {positions.shape}')
    if times.size and not (times[0] >= 0.0 and np.all(np.diff(times) > 0.0)):
        raise ValueError('times must be >= 0 and strictly increasing')
    msg = JointTrajectory()
    msg.header.stamp = _stamp(stamp)
    msg.header.frame_id = str(frame_id)
    msg.joint_names = names
    points = []
    for k in range(times.size):
        point = JointTrajectoryPoint()
        point.time_from_start = seconds_to_duration(times[k])
        point.positions = positions[k].tolist()
        if velocities is not None:
            point.velocities = velocities[k].tolist()
        points.append(point)
    msg.points = points
    return msg


def serialize_joint_trajectory(stamp, names: Sequence[str], times, positions,
                               velocities=None, frame_id: str = '') -> bytes:
    """
    Return the JointTrajectory of :func:`make_joint_trajectory` already serialized (CDR).

    The same message, written straight into its little-endian CDR wire form (what
    ``rclpy.serialization.serialize_message`` produces, without its trailing zero padding)
    for ``Publisher.publish(bytes)``: building 201 ``JointTrajectoryPoint`` objects costs
    about 2 ms of Python per prediction, this a few numpy operations. The byte layout of a
    given (names, times, with velocities) is built once and kept
    (:func:`rkgnn_ros.wire.cdr.joint_trajectory_cdr`); each call copies it and scatters the
    stamp, positions and velocities into it. Same
    arguments and errors as :func:`make_joint_trajectory`; tests hold the two equal.
    """
    names = tuple(str(name) for name in names)
    times = np.asarray(times, dtype=float).reshape(-1)
    positions = np.asarray(positions, dtype=float)
    k, n = times.size, len(names)
    if positions.shape != (k, n):
        raise ValueError(f'positions have shape {positions.shape}, expected {(k, n)}')
    if velocities is not None:
        velocities = np.asarray(velocities, dtype=float)
        if velocities.shape != positions.shape:
            raise ValueError(
                f'velocities have shape {velocities.shape}, expected {positions.shape}')
    if k and not (times[0] >= 0.0 and np.all(np.diff(times) > 0.0)):
        raise ValueError('times must be >= 0 and strictly increasing')
    header = _stamp(stamp)
    return joint_trajectory_cdr(header.sec, header.nanosec, names, times, positions,
                                velocities, frame_id)


def make_float64_multiarray(values, labels: Sequence[str]) -> Float64MultiArray:
    """
    Build a Float64MultiArray whose layout names its fields.

    Layout
    ------
    ``values`` of shape (F,) (one record) gives one dimension whose ``label`` is the
    comma-joined field names, e.g. ``'generation,best_cost,mean_cost,spread,evaluations,
    validation_nrmse'``, with ``size = stride = F``. ``values`` of shape (R, F) (R records,
    row-major) gives two dimensions: ``('rows', R, R*F)`` then ``(fields, F, F)``.
    ``data_offset`` is 0. Raises ValueError when ``len(labels) != F`` or a label contains
    a comma.
    """
    labels = [str(label) for label in labels]
    if any(',' in label for label in labels):
        raise ValueError(f'labels must not contain commas: {labels}')
    arr = np.asarray(values, dtype=float)
    if arr.ndim not in (1, 2) or arr.shape[-1] != len(labels):
        raise ValueError(
            f'values of shape {arr.shape} do not match {len(labels)} labels')
    msg = Float64MultiArray()
    dims = []
    if arr.ndim == 2:
        dims.append(MultiArrayDimension(
            label='rows', size=arr.shape[0], stride=arr.shape[0] * arr.shape[1]))
    dims.append(MultiArrayDimension(
        label=','.join(labels), size=len(labels), stride=len(labels)))
    msg.layout.dim = dims
    msg.layout.data_offset = 0
    msg.data = arr.reshape(-1).tolist()
    return msg

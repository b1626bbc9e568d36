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
The CDR wire form of the two messages the 1 kHz paths handle, read and written directly.

At 1 kHz, building and reading message objects costs more Python than the rest of a
message's handling: a JointState is read straight from the bytes a raw subscription
delivers (:func:`parse_joint_state_cdr`), and a prediction's JointTrajectory is written
straight into the bytes ``Publisher.publish`` takes (:func:`joint_trajectory_cdr`). A
reference JointTrajectory is read from its bytes too (:func:`joint_trajectory_cdr_size`,
:func:`parse_joint_trajectory_cdr`): its size is known from its first bytes, before a
100,000-point message becomes 100,000 Python objects, and malformed bytes never reach
rclpy's deserializer, which prints a line on stderr for each.
:mod:`rkgnn_ros.wire.conversions` applies the message rules on top; tests hold both directions
equal to rclpy's own serialization. No ROS import: the layout is the OMG CDR encoding
(XCDR1) that every ROS 2 middleware uses for these types.
"""

from functools import lru_cache
import math
import struct
from typing import Optional, Sequence, Tuple

import numpy as np

__all__ = ['encapsulation_problem', 'is_plain_cdr', 'joint_trajectory_cdr',
           'joint_trajectory_cdr_size', 'parse_joint_state_cdr', 'parse_joint_trajectory_cdr',
           'parse_trajectory_efforts_cdr', 'split_seconds']

_CDR_LE = b'\x00\x01\x00\x00'  # CDR encapsulation: plain CDR, little endian
_NANO = 1_000_000_000


def split_seconds(seconds: float, what: str) -> Tuple[int, int]:
    """Split finite seconds into (sec, nanosec) with ``0 <= nanosec < 1e9``."""
    seconds = float(seconds)
    if not math.isfinite(seconds):
        raise ValueError(f'{what} must be finite, got {seconds}')
    sec = math.floor(seconds)
    nanosec = int(round((seconds - sec) * _NANO))
    if nanosec >= _NANO:
        sec, nanosec = sec + 1, nanosec - _NANO
    if not -2 ** 31 <= sec < 2 ** 31:
        raise ValueError(f'{what} {seconds} s does not fit a 32-bit seconds field')
    return int(sec), nanosec


_CDR_HEADER = {1: struct.Struct('<iII'), 0: struct.Struct('>iII')}
_CDR_U32 = {1: struct.Struct('<I'), 0: struct.Struct('>I')}
_CDR_F8 = {1: np.dtype('<f8'), 0: np.dtype('>f8')}


def is_plain_cdr(raw: bytes) -> bool:
    """Return whether ``raw`` starts with the encapsulation of plain CDR (either order)."""
    return len(raw) >= 4 and raw[0] == 0 and raw[1] in (0, 1)


#: The encapsulation identifiers of the DDS-XTypes specification (byte 1, byte 0 zero).
_ENCAPSULATIONS = {2: 'PL_CDR, big endian', 3: 'PL_CDR, little endian',
                   6: 'XCDR2, big endian', 7: 'XCDR2, little endian',
                   8: 'delimited XCDR2, big endian', 9: 'delimited XCDR2, little endian',
                   10: 'PL_CDR2, big endian', 11: 'PL_CDR2, little endian'}


def encapsulation_problem(raw: bytes, what: str) -> Optional[str]:
    """
    Return why ``raw`` is not read as a ``what`` message, or None for plain CDR.

    The nodes read plain CDR (XCDR1, either byte order), which every ROS 2 middleware
    sends for these types. Bytes of any other encapsulation are refused without being
    handed to rclpy's deserializer: for XCDR2 and the others it prints a line on stderr for
    every malformed message ("sequence size exceeds remaining buffer"), one per message.
    """
    if is_plain_cdr(raw):
        return None
    if len(raw) < 4:
        return f'{len(raw)} bytes: too short for a {what}'
    code = raw[0] << 8 | raw[1]
    name = _ENCAPSULATIONS.get(code, 'not a CDR encapsulation')
    return (f'{len(raw)} bytes with encapsulation 0x{code:04x} ({name}): a {what} is read '
            'as plain CDR (XCDR1), what ROS 2 middlewares send')


def parse_joint_state_cdr(raw: bytes):
    """
    Read a JointState from its CDR bytes (XCDR1, either byte order).

    Returns ``(sec, nanosec, names tuple, position, velocity, effort)`` (float64 arrays,
    read-only views of ``raw``), or None when ``raw`` is not plain CDR or does not hold
    a JointState (truncated, a count beyond the end, a string without its terminating NUL
    or not UTF-8). Bytes after the message are ignored, as rclpy's deserializer does
    (``serialize_message`` itself leaves up to 8 spare bytes at the end).

    Layout (offsets count from the end of the 4-byte encapsulation header, every
    primitive aligned to its size): header.stamp (int32 sec, uint32 nanosec),
    header.frame_id (string: uint32 length with the NUL, the bytes, NUL), name (uint32
    count, that many strings), then position, velocity, effort (uint32 count, float64
    elements).
    """
    try:
        return _parse_joint_state_cdr(bytes(raw))
    except (UnicodeDecodeError, struct.error, ValueError):
        return None


def _parse_joint_state_cdr(raw: bytes):
    size = len(raw)
    if size < 16 or raw[0] != 0 or raw[1] not in (0, 1):
        return None
    order = raw[1]
    sec, nanosec, length = _CDR_HEADER[order].unpack_from(raw, 4)
    at = 16 + length
    if length == 0 or at > size or raw[at - 1] != 0:
        return None
    raw[16:at - 1].decode('utf-8')  # header.frame_id: not used, but must be text
    u32 = _CDR_U32[order].unpack_from
    at += -(at - 4) % 4
    if at + 4 > size:
        return None
    (count,) = u32(raw, at)
    at += 4
    if count > (size - at) // 5:  # each name takes at least 5 bytes
        return None
    names = []
    for _ in range(count):
        at += -(at - 4) % 4
        if at + 4 > size:
            return None
        (length,) = u32(raw, at)
        end = at + 4 + length
        if length == 0 or end > size or raw[end - 1] != 0:
            return None
        names.append(raw[at + 4:end - 1].decode('utf-8'))
        at = end
    dtype = _CDR_F8[order]
    arrays = []
    for _ in range(3):
        at += -(at - 4) % 4
        if at + 4 > size:
            return None
        (count,) = u32(raw, at)
        at += 4
        if count:
            at += -(at - 4) % 8
            if at + 8 * count > size:
                return None
            arrays.append(np.frombuffer(raw, dtype=dtype, count=count, offset=at))
            at += 8 * count
        else:
            arrays.append(_EMPTY)
    return (sec, nanosec, tuple(names)) + tuple(arrays)


_EMPTY = np.zeros(0)


class _Reader:
    """Reads aligned CDR primitives from ``raw``; every read raises ValueError past the end."""

    def __init__(self, raw: bytes, order: int):
        self.raw, self.size, self.at = raw, len(raw), 4
        self._u32 = _CDR_U32[order].unpack_from
        self._f8 = _CDR_F8[order]

    def _align(self, size: int) -> None:
        self.at += -(self.at - 4) % size

    def u32(self) -> int:
        self._align(4)
        if self.at + 4 > self.size:
            raise ValueError('truncated')
        (value,) = self._u32(self.raw, self.at)
        self.at += 4
        return value

    def count(self, least_bytes: int) -> int:
        """Read a sequence count whose elements take at least ``least_bytes`` each."""
        count = self.u32()
        if count > (self.size - self.at) // least_bytes:
            raise ValueError('a count beyond the end')
        return count

    def string(self) -> str:
        length = self.u32()
        end = self.at + length
        if length == 0 or end > self.size or self.raw[end - 1] != 0:
            raise ValueError('not a string')
        text = self.raw[self.at:end - 1].decode('utf-8')
        self.at = end
        return text

    def doubles(self) -> np.ndarray:
        count = self.u32()
        if not count:
            return _EMPTY
        self._align(8)
        if self.at + 8 * count > self.size:
            raise ValueError('truncated')
        values = np.frombuffer(self.raw, dtype=self._f8, count=count, offset=self.at)
        self.at += 8 * count
        return values

    def stamp(self) -> Tuple[int, int]:
        sec = self.u32()
        return sec - (1 << 32) if sec >= 1 << 31 else sec, self.u32()


def _trajectory_reader(raw: bytes):
    """Return a reader past the header and the names: ``(reader, sec, nanosec, names)``."""
    if len(raw) < 16 or raw[0] != 0 or raw[1] not in (0, 1):
        raise ValueError('not plain CDR')
    reader = _Reader(raw, raw[1])
    sec, nanosec = reader.stamp()
    reader.string()  # header.frame_id: not used, but must be text
    names = tuple(reader.string() for _ in range(reader.count(5)))
    return reader, sec, nanosec, names


def joint_trajectory_cdr_size(raw: bytes):
    """
    Return ``(joint names, number of points)`` of a JointTrajectory's CDR bytes, or None.

    Reads only the header, the names and the count of points the message claims: what a
    size budget needs before anything is built from the points (which need not even be
    there). None when ``raw`` is not plain CDR or its beginning does not hold a
    JointTrajectory.
    """
    try:
        reader, _, _, names = _trajectory_reader(bytes(raw))
        return names, reader.u32()  # the count the message claims, the points unread
    except (UnicodeDecodeError, struct.error, ValueError):
        return None


def parse_joint_trajectory_cdr(raw: bytes):
    """
    Read a JointTrajectory from its CDR bytes (XCDR1, either byte order).

    Returns ``(sec, nanosec, names tuple, points)``, each point ``(positions, velocities,
    seconds)`` (float64 arrays, read-only views of ``raw``; ``seconds`` its
    ``time_from_start``), or None when ``raw`` is not plain CDR or does not hold a
    JointTrajectory (truncated, a count beyond the end, a string without its NUL or not
    UTF-8). Every byte of every point is checked here, so that rclpy's deserializer (which
    prints a line on stderr for each malformed message) is never handed such bytes.

    Layout after the header and names (as :func:`parse_joint_state_cdr`): points (uint32
    count; each point positions, velocities, accelerations, effort as float64 sequences,
    then time_from_start as int32 sec, uint32 nanosec).
    """
    try:
        reader, sec, nanosec, names = _trajectory_reader(bytes(raw))
        points = []
        for _ in range(reader.count(24)):
            positions, velocities = reader.doubles(), reader.doubles()
            reader.doubles()  # accelerations
            reader.doubles()  # effort
            t_sec, t_nanosec = reader.stamp()
            points.append((positions, velocities, t_sec + t_nanosec * 1e-9))
        return sec, nanosec, names, points
    except (UnicodeDecodeError, struct.error, ValueError):
        return None


def parse_trajectory_efforts_cdr(raw: bytes):
    """
    Read a JointTrajectory's stamp, names, point times and efforts from its CDR bytes.

    Returns ``(sec, nanosec, names tuple, times (K,), efforts)``, ``efforts`` a (K, m) float
    array when every point has m efforts, else a list of K arrays; or None when ``raw`` is
    not plain CDR or does not hold a JointTrajectory (every byte is checked, as
    :func:`parse_joint_trajectory_cdr` does). Points laid out alike (the same number of
    positions, velocities, accelerations and efforts in each, as every publisher sends
    them) are read with numpy as strided views of the bytes: a 10,000-point trajectory in a
    few milliseconds instead of a tenth of a second point by point.
    """
    try:
        raw = bytes(raw)
        reader, sec, nanosec, names = _trajectory_reader(raw)
        count = reader.count(24)
        start = reader.at
        alike = _alike_points(reader, count)
        if alike is not None:
            return (sec, nanosec, names) + alike
        reader.at = start
        times, efforts = np.empty(count), []
        for k in range(count):
            for _ in range(3):  # positions, velocities, accelerations
                reader.doubles()
            efforts.append(reader.doubles())
            t_sec, t_nanosec = reader.stamp()
            times[k] = t_sec + t_nanosec * 1e-9
        return sec, nanosec, names, times, efforts
    except (UnicodeDecodeError, struct.error, ValueError):
        return None


def _point_layout(reader):
    """Read one point; return (counts, count offsets, data offsets, time offset), absolute."""
    counts, count_at, data_at = [], [], []
    for _ in range(4):
        reader._align(4)
        count_at.append(reader.at)
        values = reader.doubles()
        counts.append(values.size)
        data_at.append(reader.at - 8 * values.size)
    reader._align(4)
    time_at = reader.at
    reader.stamp()
    return counts, count_at, data_at, time_at


def _alike_points(reader, count: int):
    """
    Return ``(times, efforts)`` of ``count`` points laid out alike, read with numpy.

    None when they are not (fewer than 4 points, or counts that differ between points).

    A point's sequences align by their offsets from byte 4, so its padding depends on
    where it starts modulo 8: points alike repeat with a period of two points at most,
    whose length is a multiple of 8, once the first point (which may start at the other
    offset) is past. Each parity is then one strided view of the bytes.
    """
    if count < 4:
        return None
    head = None
    s0 = reader.at
    first = _point_layout(reader)
    s1 = reader.at
    second = _point_layout(reader)
    s2 = reader.at
    if first[0] != second[0]:
        return None
    if (s2 - s0) % 8:  # the first point alone starts 4 bytes off: lay out from the second
        head = first
        s0, first = s1, second
        second = _point_layout(reader)
        s1, s2 = s2, reader.at
        count -= 1
        if first[0] != second[0] or (s2 - s0) % 8:
            return None
    raw = reader.raw
    period, order, counts = s2 - s0, '<' if raw[1] == 1 else '>', first[0]
    last = count - 1
    if last % 2 == 0:
        end = s0 + last // 2 * period + (s1 - s0)
    else:
        end = s1 + last // 2 * period + (s2 - s1)
    if end > len(raw):
        return None

    def view(offset, dtype, shape, strides):
        return np.ndarray(shape, dtype=np.dtype(dtype).newbyteorder(order), buffer=raw,
                          offset=offset, strides=strides)

    times = np.empty(count)
    efforts = np.empty((count, counts[3]))
    for parity, (layout, size) in enumerate(((first, (count + 1) // 2), (second, count // 2))):
        _, count_at, data_at, time_at = layout
        for j in range(4):
            if np.any(view(count_at[j], 'u4', (size,), (period,)) != counts[j]):
                return None
        sec = view(time_at, 'i4', (size,), (period,)).astype(float)
        times[parity::2] = sec + view(time_at + 4, 'u4', (size,), (period,)) * 1e-9
        if counts[3]:
            efforts[parity::2] = view(data_at[3], 'f8', (size, counts[3]), (period, 8))
    reader.at = end
    if head is not None:
        if head[0] != counts:
            return None
        _, _, data_at, time_at = head
        sec, nanosec = (view(time_at, 'i4', (1,), (4,))[0],
                        view(time_at + 4, 'u4', (1,), (4,))[0])
        times = np.concatenate([[float(sec) + nanosec * 1e-9], times])
        efforts = np.vstack([view(data_at[3], 'f8', (1, counts[3]), (8, 8)), efforts])
    return times, efforts


def joint_trajectory_cdr(sec: int, nanosec: int, names: Sequence[str], times: np.ndarray,
                         positions: np.ndarray, velocities=None, frame_id: str = '') -> bytes:
    """
    Return the CDR bytes of a JointTrajectory (little endian), from checked arrays.

    ``times`` (K,) are the points' ``time_from_start`` (s), ``positions`` and
    ``velocities`` (None: empty) have shape (K, n) for the n ``names``; the header stamp
    is ``(sec, nanosec)`` and ``frame_id`` empty. The layout of given (names, times,
    velocities or not) is built once and kept; each call copies it and scatters the stamp
    and the values into it.
    """
    names = tuple(names)
    template, stamp_at, position_bytes, velocity_bytes = _trajectory_layout(
        names, np.asarray(times, dtype=float).tobytes(), velocities is not None,
        str(frame_id))
    out = template.copy()
    out[stamp_at:stamp_at + 8] = np.frombuffer(struct.pack('<iI', sec, nanosec),
                                               dtype=np.uint8)
    if position_bytes.size:
        out[position_bytes] = _le_bytes(positions)
        if velocities is not None:
            out[velocity_bytes] = _le_bytes(velocities)
    return out.tobytes()


def _le_bytes(values: np.ndarray) -> np.ndarray:
    """Return the little-endian float64 bytes of ``values``, row-major, flat (uint8)."""
    return np.ascontiguousarray(values, dtype='<f8').reshape(-1).view(np.uint8)


@lru_cache(maxsize=8)
def _trajectory_layout(names: Tuple[str, ...], times_bytes: bytes, with_velocities: bool,
                       frame_id: str = ''):
    """
    Return the CDR bytes of a JointTrajectory with zero stamp and values, and their places.

    Returns (template uint8 array, offset of the stamp, indices of the position bytes,
    indices of the velocity bytes), the indices in the order of ``_le_bytes`` of a
    (k, n) array. CDR aligns every primitive to its size counted from the end of the
    4-byte encapsulation header; a sequence is a uint32 count and its elements.
    """
    times = np.frombuffer(times_bytes, dtype=float)
    n = len(names)
    out = bytearray(_CDR_LE)

    def align(size):
        out.extend(bytes(-(len(out) - len(_CDR_LE)) % size))

    def string(text):
        data = text.encode('utf-8')
        align(4)
        out.extend(struct.pack('<I', len(data) + 1) + data + b'\x00')

    def doubles(count):  # a float64 sequence of ``count`` zeros: return where its data sit
        align(4)
        out.extend(struct.pack('<I', count))
        if not count:
            return None
        align(8)
        at = len(out)
        out.extend(bytes(8 * count))
        return at

    align(4)
    stamp_at = len(out)
    out.extend(bytes(8))
    string(frame_id)
    align(4)
    out.extend(struct.pack('<I', n))
    for name in names:
        string(name)
    align(4)
    out.extend(struct.pack('<I', times.size))
    position_at, velocity_at = [], []
    for t in times.tolist():
        position_at.append(doubles(n))
        velocity_at.append(doubles(n if with_velocities else 0))
        doubles(0)  # accelerations
        doubles(0)  # effort
        sec, nanosec = split_seconds(t, 'duration')
        align(4)
        out.extend(struct.pack('<iI', sec, nanosec))
    span = np.arange(8 * n)

    def indices(starts):
        if not n or not starts or starts[0] is None:
            return np.zeros(0, dtype=np.intp)
        return (np.asarray(starts, dtype=np.intp)[:, None] + span).reshape(-1)

    template = np.frombuffer(bytes(out), dtype=np.uint8)
    template.flags.writeable = False
    return template, stamp_at, indices(position_at), indices(velocity_at)

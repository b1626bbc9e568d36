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
An MCAP file read record by record from its start, for recordings that lost their end.

``ros2 bag record`` writes an MCAP file's index and footer when it stops; a recorder that
was killed, or a disk that filled, leaves a file without them, which readers that start
from the footer (``rosbags``) refuse. The records themselves are still there in order:
:class:`McapScan` reads them from the start (schemas, channels, messages, chunks
uncompressed, zstd or lz4) until the file ends or a record is cut, and offers the part of
the reader interface :mod:`rkgnn_ros.recordings.reader` uses. ``broken`` says where and why it
stopped, if it did.
"""

import mmap
import struct
from typing import Dict, Iterator, List, NamedTuple, Optional, Tuple

__all__ = ['McapScan']

MAGIC = b'\x89MCAP0\r\n'
#: Largest chunk decompressed (bytes); ros2 bag writes chunks of about 1 MiB.
MAX_CHUNK_BYTES = 256 * 1024 * 1024
_SCHEMA, _CHANNEL, _MESSAGE, _CHUNK, _FOOTER = 0x03, 0x04, 0x05, 0x06, 0x02


class Connection(NamedTuple):
    """A channel, as the reader interface names it."""

    channel_id: int
    topic: str
    msgtype: str
    msgcount: int
    msgdef: str


def _string(data, at: int) -> Tuple[str, int]:
    (size,) = struct.unpack_from('<I', data, at)
    return bytes(data[at + 4:at + 4 + size]).decode('utf-8'), at + 4 + size


def _decompress(compression: str, data, size: int):
    if size > MAX_CHUNK_BYTES:
        raise ValueError(f'a chunk of {size} bytes, over the limit of {MAX_CHUNK_BYTES}')
    if compression == '':
        return data
    if compression == 'zstd':
        try:
            from compression import zstd
        except ImportError:
            from backports import zstd
        return zstd.decompress(data)
    if compression == 'lz4':
        import lz4.frame
        return lz4.frame.decompress(data)
    raise ValueError(f'unknown chunk compression {compression!r}')


class McapScan:
    """
    The records of an MCAP file in file order, read without its index.

    Parameters
    ----------
    path : str
        The ``.mcap`` file.

    Raises
    ------
    ValueError
        If the file does not start with the MCAP magic.

    """

    def __init__(self, path: str):
        self.broken = ''
        self._schemas: Dict[int, Tuple[str, str]] = {}
        self._channels: Dict[int, Tuple[str, int]] = {}
        self._messages: List[Tuple[int, int, bytes]] = []  # (channel, log_time, data)
        with open(path, 'rb') as f:
            if f.read(len(MAGIC)) != MAGIC:
                raise ValueError('not an MCAP file (no MCAP magic at its start)')
            # mapped, not read: what the scan does not reach is never loaded
            mapped = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
        try:
            self._scan(memoryview(mapped), len(MAGIC), top=True)
        finally:
            try:
                mapped.close()
            except BufferError:  # a view still held (a traceback's frame): unmapped later
                pass
        counts: Dict[int, int] = {}
        for channel, _, _ in self._messages:
            counts[channel] = counts.get(channel, 0) + 1
        self.connections = [
            Connection(cid, topic, self._schemas.get(sid, ('', ''))[0], counts.get(cid, 0),
                       self._schemas.get(sid, ('', ''))[1])
            for cid, (topic, sid) in self._channels.items()]
        self._typestore = None

    def _scan(self, data: bytes, at: int, top: bool) -> None:
        end = len(data)
        while at < end:
            if end - at < 9:
                if top and data[at:] != MAGIC[:end - at]:
                    self.broken = f'a record header is cut at byte {at}'
                return
            opcode = data[at]
            (length,) = struct.unpack_from('<Q', data, at + 1)
            body_at = at + 9
            if body_at + length > end:
                if opcode == _CHUNK:  # an uncompressed chunk keeps its whole records
                    self._partial_chunk(data[body_at:end])
                self.broken = f'a record of {length} bytes is cut at byte {at}'
                return
            body = data[body_at:body_at + length]
            try:
                self._record(opcode, body)
            except Exception as error:  # noqa: B902 - a bad record ends the scan
                self.broken = f'record 0x{opcode:02x} at byte {at} is unreadable: {error}'
                return
            if opcode == _FOOTER:
                return
            at = body_at + length

    def _record(self, opcode: int, body: bytes) -> None:
        if opcode == _SCHEMA:
            (sid,) = struct.unpack_from('<H', body, 0)
            name, at = _string(body, 2)
            _, at = _string(body, at)                 # encoding
            (size,) = struct.unpack_from('<I', body, at)
            text = bytes(body[at + 4:at + 4 + size]).decode('utf-8', 'replace')
            self._schemas[sid] = (name, text)
        elif opcode == _CHANNEL:
            cid, sid = struct.unpack_from('<HH', body, 0)
            topic, _ = _string(body, 4)
            self._channels[cid] = (topic, sid)
        elif opcode == _MESSAGE:
            cid, _, log_time, _ = struct.unpack_from('<HIQQ', body, 0)
            self._messages.append((cid, log_time, bytes(body[22:])))
        elif opcode == _CHUNK:
            _, _, size, _ = struct.unpack_from('<QQQI', body, 0)
            compression, at = _string(body, 28)
            (records_size,) = struct.unpack_from('<Q', body, at)
            records = body[at + 8:at + 8 + records_size]
            self._scan(_decompress(compression, records, size), 0, top=False)

    def _partial_chunk(self, body: bytes) -> None:
        """Read the whole records of a chunk cut short (uncompressed chunks only)."""
        try:
            compression, at = _string(body, 28)
        except struct.error:
            return
        if compression == '':
            self._scan(body[at + 8:], 0, top=False)

    def messages(self, connections=()) -> Iterator[Tuple[Connection, int, bytes]]:
        """Yield ``(connection, log time ns, data)`` of the chosen connections in file order."""
        wanted = {c.channel_id: c for c in (connections or self.connections)}
        for cid, log_time, data in self._messages:
            if cid in wanted:
                yield wanted[cid], log_time, data

    def deserialize(self, raw: bytes, msgtype: str):
        """Deserialize with the file's own definitions (rosbags' type system)."""
        if self._typestore is None:
            from rosbags.typesys import get_types_from_msg, get_typestore, Stores
            store = get_typestore(Stores.ROS2_JAZZY)
            types = {}
            for name, text in self._schemas.values():
                if name and text:
                    try:
                        types.update(get_types_from_msg(text, name))
                    except Exception:  # noqa: B902 - a definition it cannot parse: skip it
                        continue
            store.register(types)
            self._typestore = store
        return self._typestore.deserialize_cdr(raw, msgtype)

    def close(self) -> None:
        """Forget the file's contents."""
        self._messages = []


def scan_target(path) -> Optional[str]:
    """Return the .mcap file to scan for ``path`` (a file or a bag folder), else None."""
    import pathlib
    where = pathlib.Path(path)
    if where.suffix == '.mcap' and where.is_file():
        return str(where)
    if where.is_dir():
        files = sorted(where.glob('*.mcap'))
        if len(files) == 1:
            return str(files[0])
    return None

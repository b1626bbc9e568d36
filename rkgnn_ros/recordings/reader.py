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
A rosbag2 recording read for identification: topics found, messages in order, faults named.

``ros2 bag record`` writes MCAP (Jazzy's default) or sqlite3; the pure-Python ``rosbags``
library reads both, a bag folder or a single ``.mcap`` / ``.db3`` file, with no ROS
install. :func:`open_recording` opens one and turns every way it can fail (no such path,
an unknown storage format, a corrupt or truncated file) into a :class:`RecordingError`
whose one-line message names the file. :func:`find_topics` picks the joint streams by type
and name (``joint_states``, ``joint_commands``, a joint_trajectory_controller's
``controller_state``, the online identifier's ``model``), or takes them as given, and says
what is missing. :func:`read_messages` returns them in recording order; a file that breaks
part way is read up to there and says where.

Messages stay serialized (CDR, what the node's ingestion takes) except controller states:
``control_msgs`` is not needed to read them, the bag's own message definitions decode
them (:func:`controller_state_command`).
"""

from dataclasses import dataclass, field
import os
from pathlib import Path
from typing import Dict, List, NamedTuple, Optional, Tuple

from rkgnn_ros.core.input_files import file_problem

__all__ = ['RecordingError', 'Topics', 'Message', 'Recording', 'RecordingWriter',
           'open_recording', 'find_topics', 'read_messages', 'JOINT_STATE',
           'CONTROLLER_STATES']

JOINT_STATE = 'sensor_msgs/msg/JointState'
STRING = 'std_msgs/msg/String'
#: Largest metadata.yaml read (bytes); ros2 bag writes a few kB.
MAX_METADATA_BYTES = 16 * 1024 * 1024
#: Controller state types whose reference (θd, θ̇d) can stand in for joint_commands.
CONTROLLER_STATES = ('control_msgs/msg/JointTrajectoryControllerState',)


class RecordingError(Exception):
    """A recording that cannot be used; the message is one line naming the file."""


class Topics(NamedTuple):
    """The topics identification reads ('' where there is none)."""

    states: str
    commands: str = ''
    controller_state: str = ''
    model: str = ''


class Message(NamedTuple):
    """One recorded message."""

    topic: str
    log_ns: int      # when the recorder received it
    raw: bytes       # serialized (CDR)


@dataclass
class Recording:
    """An open recording: its reader, path, topics and their types and counts."""

    path: str
    reader: object
    types: Dict[str, str] = field(default_factory=dict)
    counts: Dict[str, int] = field(default_factory=dict)
    storage: str = ''
    note: str = ''   # how it was read when not whole (an MCAP without its index)

    def close(self) -> None:
        """Close the reader (errors at close are not the caller's concern)."""
        try:
            self.reader.close()
        except Exception:  # noqa: B902 - closing a broken file may fail too
            pass

    def decode(self, message: Message):
        """Return the message deserialized with the bag's own definitions."""
        return self.reader.deserialize(message.raw, self.types[message.topic])


def _check_files(path: str, where: Path) -> None:
    """
    Refuse a recording whose files are not regular files, before anything opens them.

    A FIFO would block its reader forever and a device never ends. A folder must hold a
    ``metadata.yaml`` (what ``ros2 bag record`` writes) of at most
    :data:`MAX_METADATA_BYTES`.
    """
    if not where.is_dir():
        problem = file_problem(str(where))
        if problem is not None:
            raise RecordingError(f'{path}: {problem}')
        return
    metadata = where / 'metadata.yaml'
    if not os.path.lexists(metadata):
        inside = sorted(p.name for p in where.iterdir() if p.suffix in ('.mcap', '.db3'))
        hint = f'; it holds {", ".join(inside[:3])}: give that file' if inside else ''
        raise RecordingError(f'{path}: a folder without metadata.yaml is not a rosbag2 '
                             f'recording{hint}')
    problem = file_problem(str(metadata), MAX_METADATA_BYTES)
    if problem is not None:
        raise RecordingError(f'{path}: metadata.yaml: {problem}')
    for entry in sorted(where.iterdir()):
        if entry.suffix in ('.mcap', '.db3', '.zstd'):
            problem = file_problem(str(entry))
            if problem is not None:
                raise RecordingError(f'{path}: {entry.name}: {problem}')


def _storage_of(path: Path) -> str:
    if path.is_dir():
        metadata = path / 'metadata.yaml'
        if metadata.exists():
            text = metadata.read_text(encoding='utf-8', errors='replace')
            for name in ('mcap', 'sqlite3'):
                if name in text:
                    return name
        return 'a folder'
    return {'.mcap': 'mcap', '.db3': 'sqlite3'}.get(path.suffix, path.suffix or 'no suffix')


def open_recording(path: str) -> Recording:
    """
    Open a rosbag2 recording (a folder, or one ``.mcap`` or ``.db3`` file).

    Raises
    ------
    RecordingError
        No such path, an unknown storage format, or a file that cannot be opened (corrupt,
        truncated, not a bag): the message names the file and the problem.

    """
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import get_typestore, Stores
    where = Path(os.path.expanduser(path))
    if not where.exists():
        raise RecordingError(f'{path}: no such file or folder')
    _check_files(path, where)
    storage = _storage_of(where)
    if not where.is_dir() and where.suffix not in ('.mcap', '.db3'):
        raise RecordingError(f'{path}: unknown storage format {storage!r} (a rosbag2 folder, '
                             'an .mcap or a .db3 file)')
    note = ''
    try:
        reader = AnyReader([where], default_typestore=get_typestore(Stores.ROS2_JAZZY))
        reader.open()
    except Exception as error:  # noqa: B902 - rosbags and its storages raise many types
        reader, note = _scan_instead(where, storage, error)
        if reader is None:
            raise RecordingError(f'{path}: cannot open the {storage} recording: '
                                 f'{_one_line(error)}') from None
    recording = Recording(str(path), reader, storage=storage, note=note)
    for connection in reader.connections:
        recording.types.setdefault(connection.topic, connection.msgtype)
        recording.counts[connection.topic] = (recording.counts.get(connection.topic, 0)
                                              + connection.msgcount)
    return recording


def _scan_instead(where: Path, storage: str, error: BaseException):
    """Return an MCAP read from its start when its index is gone, with a note (or None)."""
    from rkgnn_ros.recordings.mcap_scan import McapScan, scan_target
    target = scan_target(where) if storage in ('mcap', 'a folder') else None
    if target is None:
        return None, ''
    try:
        scan = McapScan(target)
    except (OSError, ValueError):
        return None, ''
    if not scan.connections:
        return None, ''
    note = (f'the mcap file has no index ({_one_line(error)}): read record by record'
            + (f', {scan.broken}' if scan.broken else ''))
    return scan, note


def _one_line(error: BaseException) -> str:
    text = ' '.join(str(error).split()) or type(error).__name__
    return text if len(text) <= 300 else text[:297] + '...'


def _pick(recording: Recording, kinds: Tuple[str, ...], suffix: str, namespace: str,
          what: str) -> str:
    """Return the one topic of a type in ``kinds`` ending in ``suffix`` ('' if none)."""
    candidates = [topic for topic, kind in recording.types.items() if kind in kinds
                  and topic.startswith(namespace) and topic.rsplit('/', 1)[-1] == suffix]
    if len(candidates) > 1:
        raise RecordingError(f'{recording.path}: several {what} topics {sorted(candidates)}: '
                             f'choose one (--{what.replace("_", "-")} or --namespace)')
    return candidates[0] if candidates else ''


def _given(recording: Recording, topic: str, kinds: Tuple[str, ...], what: str) -> str:
    if topic not in recording.types:
        raise RecordingError(f'{recording.path}: no topic {topic!r} ({what}); it has '
                             f'{sorted(recording.types)}')
    if recording.types[topic] not in kinds:
        raise RecordingError(f'{recording.path}: topic {topic!r} is '
                             f'{recording.types[topic]}, not {" or ".join(kinds)} ({what})')
    return topic


def find_topics(recording: Recording, namespace: str = '', states: str = '',
                commands: str = '', controller_state: str = '', model: str = '') -> Topics:
    """
    Return the topics to read: those given, else found by type and name.

    Found: the JointState topic named ``joint_states``, the JointState ``joint_commands``,
    a controller state named ``controller_state``, the String topic ``model`` (the online
    identifier's ``~/model``), each under ``namespace`` if given.

    Raises
    ------
    RecordingError
        A given topic is absent or of another type, no joint_states topic, or several
        candidates for one role.

    """
    namespace = namespace.rstrip('/') + '/' if namespace else ''
    if states:
        states = _given(recording, states, (JOINT_STATE,), 'joint states')
    else:
        states = _pick(recording, (JOINT_STATE,), 'joint_states', namespace, 'joint_states')
    if not states:
        raise RecordingError(
            f'{recording.path}: no sensor_msgs/msg/JointState topic named joint_states'
            f'{" under " + namespace if namespace else ""}; it has '
            + ', '.join(f'{t} ({k})' for t, k in sorted(recording.types.items()))
            + ' (choose one with --joint-states)')
    if commands:
        commands = _given(recording, commands, (JOINT_STATE,), 'joint commands')
    else:
        commands = _pick(recording, (JOINT_STATE,), 'joint_commands', namespace,
                         'joint_commands')
    if controller_state:
        controller_state = _given(recording, controller_state, CONTROLLER_STATES,
                                  'controller state')
    else:
        controller_state = _pick(recording, CONTROLLER_STATES, 'controller_state', namespace,
                                 'controller_state')
    if model:
        model = _given(recording, model, (STRING,), 'identified model')
    else:
        model = _pick(recording, (STRING,), 'model', namespace, 'model')
    return Topics(states, commands, controller_state, model)


def read_messages(recording: Recording, topics) -> Tuple[List[Message], str]:
    """
    Return the messages of ``topics`` in recording order, and why reading stopped early.

    ``topics`` is a :class:`Topics` or any sequence of topic names ('' ignored).

    The second value is '' when the whole file was read; otherwise it says where and why
    it broke (a truncated or corrupt file), and the messages before are returned.
    """
    wanted = {topic for topic in topics if topic}
    connections = [c for c in recording.reader.connections if c.topic in wanted]
    messages: List[Message] = []
    try:
        for connection, log_ns, raw in recording.reader.messages(connections=connections):
            messages.append(Message(connection.topic, int(log_ns), bytes(raw)))
    except Exception as error:  # noqa: B902 - a broken file ends the reading, not the run
        at = (f'after {len(messages)} messages ({messages[-1].log_ns * 1e-9:.3f} s)'
              if messages else 'before the first message')
        return messages, f'the recording breaks {at}: {_one_line(error)}'
    return messages, ''


class RecordingWriter:
    """
    Write serialized messages into a new rosbag2 recording (what ``ros2 bag record`` makes).

    For benchmarks and tests: ``with RecordingWriter(path) as bag: bag.write(topic, type,
    t_ns, raw)``. Types come from the Jazzy message definitions ``rosbags`` ships, or from
    ``definitions`` ({type: .msg text}) for types it has not (e.g. control_msgs).

    Parameters
    ----------
    path : str
        The folder to create (it must not exist).
    storage : {'mcap', 'sqlite3'}
        The storage plugin.
    definitions : dict, optional
        Extra message definitions by type name.

    """

    def __init__(self, path: str, storage: str = 'mcap',
                 definitions: Optional[Dict[str, str]] = None):
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.typesys import get_types_from_msg, get_typestore, Stores
        plugins = {'mcap': StoragePlugin.MCAP, 'sqlite3': StoragePlugin.SQLITE3}
        if storage not in plugins:
            raise ValueError(f'storage must be one of {sorted(plugins)}, got {storage!r}')
        self._typestore = get_typestore(Stores.ROS2_JAZZY)
        for name, text in (definitions or {}).items():
            self._typestore.register(get_types_from_msg(text, name))
        self._writer = Writer(path, version=9, storage_plugin=plugins[storage])
        self._connections: Dict[str, object] = {}

    def __enter__(self) -> 'RecordingWriter':
        self._writer.open()
        return self

    def __exit__(self, *exc) -> None:
        self._writer.close()

    def write(self, topic: str, msgtype: str, log_ns: int, raw: bytes) -> None:
        """Write one serialized message of ``msgtype`` received at ``log_ns``."""
        connection = self._connections.get(topic)
        if connection is None:
            connection = self._writer.add_connection(topic, msgtype, typestore=self._typestore)
            self._connections[topic] = connection
        self._writer.write(connection, int(log_ns), bytes(raw))

    def serialize(self, message, msgtype: str) -> bytes:
        """Return a message object of ``rosbags``' own types serialized as CDR."""
        return bytes(self._typestore.serialize_cdr(message, msgtype))

    def types(self):
        """Return the message classes of the type store, by name ('pkg/msg/Name')."""
        return self._typestore.types

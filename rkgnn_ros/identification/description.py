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
The arm's robot description: where the identifier takes it and how it becomes a structure.

Sources, first that is set wins: the ``robot_description`` parameter (the URDF's XML, a
file path, or ``example-robot-data:<path under robots/>``), else the newest message on the
``robot_description`` topic (std_msgs/String, reliable, transient local, as
robot_state_publisher and ``sim_arm`` publish it). Without either the identifier works as
without kinematics.

:meth:`RobotDescription.structure` turns the description into the
:class:`~rkgnn_ros.core.rigid.structure.RigidStructure` of the identifier's joints (called
by the worker thread: Pinocchio's parse and the base parameters take a fraction of a
second, once per description and joint list). Joints are matched by name; movable URDF
joints the identifier does not identify are locked at ``urdf.locked_positions`` or else
at 0 clipped into their limits (said in the log); an identified joint the URDF lacks, or
one that is not revolute with limits, is refused with a message naming it. A description
over :data:`MAX_DESCRIPTION_BYTES`, with a document type declaration (entities: an
expansion bomb), that does not parse, or whose inertias are not finite is refused with a
clear message, once; the node goes on without kinematics.
"""

import hashlib
import threading
from typing import Callable, Optional, Sequence, Tuple

from rkgnn_ros.core.rigid.structure import DescriptionError, RigidStructure
from rkgnn_ros.core.rigid.urdf import read_description, reduce_urdf, UrdfError

__all__ = ['MAX_DESCRIPTION_BYTES', 'RobotDescription', 'description_text']

#: Largest robot description taken (bytes of XML).
MAX_DESCRIPTION_BYTES = 8 * 1024 * 1024


def _check_text(text: str, source: str) -> None:
    if len(text.encode('utf-8', 'replace')) > MAX_DESCRIPTION_BYTES:
        raise DescriptionError(f'{source}: {len(text)} characters, more than the '
                               f'{MAX_DESCRIPTION_BYTES} bytes a robot description may have')
    head = text[:65536].upper()
    if '<!DOCTYPE' in head or '<!ENTITY' in text.upper():
        raise DescriptionError(f'{source}: a document type declaration or an entity is not '
                               'allowed in a robot description (a URDF needs neither)')


def description_text(raw: bytes) -> str:
    """
    Return the text of a raw std_msgs/String ``robot_description`` message.

    Raises ValueError when it is over :data:`MAX_DESCRIPTION_BYTES` (checked on the bytes,
    before anything is decoded) or does not decode.
    """
    if len(raw) > MAX_DESCRIPTION_BYTES + 64:
        raise ValueError(f'a robot_description message of {len(raw)} bytes, more than the '
                         f'{MAX_DESCRIPTION_BYTES} taken: ignored')
    from rclpy.serialization import deserialize_message
    from std_msgs.msg import String
    try:
        return deserialize_message(raw, String).data
    except Exception as exc:  # noqa: B902 - any decoding failure is a malformed message
        raise ValueError(f'a robot_description message that does not decode: {exc}') from None


class RobotDescription:
    """
    The description in use and the structure it gives for a joint list (module docstring).

    Parameters
    ----------
    log : callable
        ``log(level, text)``, thread-safe (the node's outbox).

    """

    def __init__(self, log: Callable[[str, str], None]):
        self._log = log
        self._lock = threading.Lock()
        self._parameter = ''
        self._topic: Optional[str] = None
        self._locked: Tuple[Tuple[str, float], ...] = ()
        self._gravity = 9.81
        self._key = None
        self._structure: Optional[RigidStructure] = None
        self.status = 'none given'

    def configure(self, parameter: str, locked_joints: Sequence[str],
                  locked_positions: Sequence[float], gravity: float) -> None:
        """Take the node's parameters (they are checked by the parameter table)."""
        with self._lock:
            self._parameter = parameter or ''
            self._locked = tuple(zip(locked_joints, locked_positions))
            self._gravity = float(gravity)

    def take_message(self, text: str) -> None:
        """Take a ``robot_description`` message (used while the parameter is empty)."""
        with self._lock:
            self._topic = text

    def structure(self, joints: Optional[Sequence[str]]) -> Optional[RigidStructure]:
        """Return the structure for ``joints`` (None: no description, or it was refused)."""
        if joints is None:
            return None
        with self._lock:
            text = self._parameter.strip() or (self._topic or '').strip()
            from_topic = not self._parameter.strip()
            locked, gravity = self._locked, self._gravity
        if not text:
            self.status = 'none given'
            return None
        digest = hashlib.sha1(text.encode('utf-8', 'replace')).hexdigest()
        key = (digest, tuple(joints), locked, gravity)
        if key == self._key:
            return self._structure
        self._key, self._structure = key, None
        source = 'the robot_description topic' if from_topic else 'parameter robot_description'
        try:
            self._structure = self._build(text, source, tuple(joints), dict(locked), gravity)
        except (DescriptionError, UrdfError, ValueError) as problem:
            self.status = f'refused: {problem}'
            self._log('error', f'robot description not used ({problem}); identifying without '
                               'kinematics')
        return self._structure

    def _build(self, text, source, joints, locked, gravity) -> RigidStructure:
        _check_text(text, source)
        if text.startswith('<'):
            xml, where = text, source
        else:
            xml, where = read_description(text)
            _check_text(xml, where)
        urdf, moving, positions = reduce_urdf(xml, joints, locked, where)
        structure = RigidStructure(urdf, moving, gravity, where)
        held = ', '.join(f'{name} = {value:g}' for name, value in positions.items())
        self.status = f'in use: {structure.describe()}'
        self._log('info', f'robot description in use: {structure.describe()}'
                          + (f'; held still: {held}' if held else ''))
        return structure

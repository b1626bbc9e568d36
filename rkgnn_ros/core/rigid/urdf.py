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
URDF text: where a ``robot_description`` comes from, and the arm that moves in it.

Shared by the identifier (the rigid body it identifies, :mod:`.structure`) and ``sim_arm``
(the arm it simulates, :mod:`rkgnn_ros.core.sim.urdf_arm`). :func:`read_description`
takes the value of a ``robot_description`` (the XML, a file path, or
``example-robot-data:<path under robots/>``) and returns the XML, reading a file only if it
is a regular file within :data:`MAX_URDF_BYTES`. :func:`reduce_urdf` makes every joint but
the moving ones fixed at its locked position (its origin absorbs the motion), so that the
XML describes exactly the arm that moves; it refuses, with a :class:`UrdfError` naming the
source and the problem, XML that does not parse or is not a URDF, moving joints that do not
exist or are not revolute with limits, and an ``<inertial>`` no rigid body has (NaN or inf
in it, a negative mass: urdfdom, which Pinocchio parses with, would drop it with a line on
stderr and simulate the arm without that body).
"""

import importlib.metadata
import math
import os
from typing import Mapping, Optional, Sequence, Tuple
import xml.etree.ElementTree as ElementTree

import numpy as np

from ..input_files import InputFileError, read_bounded

__all__ = ['EXAMPLE_ROBOT_PREFIX', 'MAX_URDF_BYTES', 'UrdfError', 'example_robot_urdf',
           'read_description', 'reduce_urdf']

#: Prefix of a ``robot_description`` that names a URDF shipped by example-robot-data,
#: e.g. ``example-robot-data:ur_description/urdf/ur5_robot.urdf``.
EXAMPLE_ROBOT_PREFIX = 'example-robot-data:'

#: Largest URDF read (bytes): example-robot-data's largest (a two-armed mobile robot) has
#: about 0.2 MB.
MAX_URDF_BYTES = 16 * 1024 * 1024

_MOVABLE = ('revolute', 'continuous', 'prismatic')


class UrdfError(ValueError):
    """A URDF that cannot be simulated; the message names the source and the problem."""


def example_robot_urdf(relative: str) -> str:
    """
    Return the path of a URDF shipped by the ``example-robot-data`` wheel.

    Parameters
    ----------
    relative : str
        Path under its ``robots/`` folder, e.g. ``'ur_description/urdf/ur5_robot.urdf'``.

    Raises
    ------
    UrdfError
        If the package is not installed or has no such file.

    """
    try:
        files = importlib.metadata.files('example-robot-data') or []
    except importlib.metadata.PackageNotFoundError:
        raise UrdfError('example-robot-data is not installed (pip install '
                        'example-robot-data)') from None
    suffix = '/robots/' + relative.lstrip('/')
    for entry in files:
        if str(entry).endswith(suffix):
            return str(entry.locate())
    raise UrdfError(f'example-robot-data has no robots/{relative.lstrip("/")}')


def read_description(description: str) -> Tuple[str, str]:
    """
    Return ``(xml, source)`` of a ``robot_description`` value.

    The value is the URDF's XML itself (it starts with ``<``), a file path, or
    ``example-robot-data:<path under robots/>``; ``source`` names it for messages. A file
    must be a regular file (a FIFO is refused, not waited on) of at most
    :data:`MAX_URDF_BYTES`, read no further than that.

    Raises
    ------
    UrdfError
        If the value is empty, too long, or the file cannot be read.

    """
    text = (description or '').strip()
    if not text:
        raise UrdfError('robot_description is empty')
    if text.startswith('<'):
        if len(text) > MAX_URDF_BYTES:
            raise UrdfError(f'robot_description (XML) has {len(text)} characters, more than '
                            f'the limit of {MAX_URDF_BYTES}')
        return text, 'robot_description (XML)'
    path = text
    if text.startswith(EXAMPLE_ROBOT_PREFIX):
        path = example_robot_urdf(text[len(EXAMPLE_ROBOT_PREFIX):])
    try:
        return read_bounded(os.path.expanduser(path), MAX_URDF_BYTES).decode('utf-8'), path
    except (InputFileError, UnicodeDecodeError) as error:
        raise UrdfError(f'robot_description: cannot read {path!r}: {error}') from None


def _floats(text: Optional[str], count: int, default: float, where: str) -> np.ndarray:
    if text is None:
        return np.full(count, default)
    try:
        values = np.array([float(v) for v in text.split()])
    except ValueError:
        raise UrdfError(f'{where}: {text!r} is not {count} numbers') from None
    if values.shape != (count,) or not np.all(np.isfinite(values)):
        raise UrdfError(f'{where}: {text!r} is not {count} finite numbers')
    return values


def _check_inertials(root, source: str) -> None:
    """
    Refuse an ``<inertial>`` no rigid body has: NaN or inf in it, a negative mass.

    Checked here because urdfdom, which Pinocchio parses with, prints an error for such an
    element and drops it: the arm simulated would silently miss that body.
    """
    for link in root.findall('link'):
        inertial = link.find('inertial')
        if inertial is None:
            continue
        where = f"{source}: link {link.get('name')!r}"
        mass = inertial.find('mass')
        value = _floats(None if mass is None else mass.get('value'), 1, 0.0,
                        f'{where}: <mass value>')[0]
        if value < 0.0:
            raise UrdfError(f'{where}: <mass value> {value:g} is negative')
        origin = inertial.find('origin')
        if origin is not None:
            _floats(origin.get('xyz'), 3, 0.0, f'{where}: inertial <origin xyz>')
            _floats(origin.get('rpy'), 3, 0.0, f'{where}: inertial <origin rpy>')
        tensor = inertial.find('inertia')
        if tensor is None:
            continue
        for key in ('ixx', 'ixy', 'ixz', 'iyy', 'iyz', 'izz'):
            _floats(tensor.get(key, '0'), 1, 0.0, f'{where}: <inertia {key}>')


def _rotation(rpy: np.ndarray) -> np.ndarray:
    """Return the rotation matrix of URDF roll-pitch-yaw angles (R = Rz(y) Ry(p) Rx(r))."""
    cr, sr = math.cos(rpy[0]), math.sin(rpy[0])
    cp, sp = math.cos(rpy[1]), math.sin(rpy[1])
    cy, sy = math.cos(rpy[2]), math.sin(rpy[2])
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def _rpy(rotation: np.ndarray) -> np.ndarray:
    """Return URDF roll-pitch-yaw angles of a rotation matrix (inverse of :func:`_rotation`)."""
    pitch = math.atan2(-rotation[2, 0], math.hypot(rotation[0, 0], rotation[1, 0]))
    if abs(math.cos(pitch)) > 1e-9:
        roll = math.atan2(rotation[2, 1], rotation[2, 2])
        yaw = math.atan2(rotation[1, 0], rotation[0, 0])
    else:  # gimbal lock: put the whole remaining rotation in yaw
        roll = 0.0
        yaw = math.atan2(-rotation[0, 1], rotation[1, 1])
    return np.array([roll, pitch, yaw])


def _axis_rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """Return the rotation by ``angle`` about the unit ``axis`` (Rodrigues)."""
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]],
                  [-axis[1], axis[0], 0.0]])
    return np.eye(3) + math.sin(angle) * k + (1.0 - math.cos(angle)) * (k @ k)


def _limits(joint) -> Tuple[float, float]:
    limit = joint.find('limit')
    if limit is None or limit.get('lower') is None or limit.get('upper') is None:
        return -math.inf, math.inf
    return float(limit.get('lower')), float(limit.get('upper'))


def _lock(joint, position: float, source: str) -> None:
    """Make ``joint`` fixed at ``position``: its origin absorbs the motion."""
    name = joint.get('name')
    origin = joint.find('origin')
    if origin is None:
        origin = ElementTree.SubElement(joint, 'origin')
    xyz = _floats(origin.get('xyz'), 3, 0.0, f'{source}: joint {name!r} origin xyz')
    rpy = _floats(origin.get('rpy'), 3, 0.0, f'{source}: joint {name!r} origin rpy')
    axis_element = joint.find('axis')
    axis = _floats(None if axis_element is None else axis_element.get('xyz'), 3, 0.0,
                   f'{source}: joint {name!r} axis')
    if axis_element is None:
        axis[0] = 1.0                       # the URDF default axis
    norm = float(np.linalg.norm(axis))
    rotation = _rotation(rpy)
    if joint.get('type') in ('revolute', 'continuous') and norm > 0.0:
        rotation = rotation @ _axis_rotation(axis / norm, position)
    elif joint.get('type') == 'prismatic' and norm > 0.0:
        xyz = xyz + rotation @ (axis / norm) * position
    origin.set('xyz', ' '.join(repr(float(v)) for v in xyz))
    origin.set('rpy', ' '.join(repr(float(v)) for v in _rpy(rotation)))
    for tag in ('axis', 'limit', 'mimic', 'dynamics', 'calibration', 'safety_controller'):
        for child in joint.findall(tag):
            joint.remove(child)
    joint.set('type', 'fixed')


def reduce_urdf(xml: str, joints: Optional[Sequence[str]] = None,
                locked: Optional[Mapping[str, float]] = None,
                source: str = 'URDF') -> Tuple[str, Tuple[str, ...], dict]:
    """
    Return the URDF with every joint but ``joints`` fixed at its locked position.

    Parameters
    ----------
    xml : str
        The URDF.
    joints : sequence of str, optional
        The joints that move, in the order of the arm's joint vector. Default: every
        revolute joint, in the order of the file.
    locked : mapping of str to float, optional
        Positions (rad, or m for a prismatic joint) of movable joints that are locked.
        Default for each: 0 clipped into its limits.
    source : str
        Names the URDF in messages.

    Returns
    -------
    xml : str
        The reduced URDF (only ``joints`` move).
    joints : tuple of str
        The moving joints.
    locked : dict
        The position each locked joint was fixed at.

    Raises
    ------
    UrdfError
        If the XML does not parse, is not a URDF, an ``<inertial>`` is not a rigid body's, a
        moving joint does not exist, is not revolute or has no limits, a locked position
        names an unknown or fixed joint or is not finite.

    """
    try:
        root = ElementTree.fromstring(xml)
    except ElementTree.ParseError as error:
        raise UrdfError(f'{source}: not valid XML ({error})') from None
    if root.tag != 'robot':
        raise UrdfError(f'{source}: not a URDF (root element <{root.tag}>, not <robot>)')
    _check_inertials(root, source)
    by_name = {joint.get('name'): joint for joint in root.findall('joint')}
    movable = [name for name, joint in by_name.items() if joint.get('type') in _MOVABLE]
    if joints is None or len(joints) == 0:
        joints = [name for name in movable if by_name[name].get('type') == 'revolute']
        if not joints:
            raise UrdfError(f'{source}: no revolute joint with limits to move')
    joints = tuple(str(name) for name in joints)
    if len(set(joints)) != len(joints):
        raise UrdfError(f'{source}: the moving joints repeat a name: {list(joints)}')
    missing = [name for name in joints if name not in by_name]
    if missing:
        raise UrdfError(f'{source}: no joint named {", ".join(map(repr, missing))}; its '
                        f'movable joints are {movable}')
    for name in joints:
        kind = by_name[name].get('type')
        if kind == 'continuous':
            raise UrdfError(f'{source}: joint {name!r} is continuous (no position limits): '
                            'only revolute joints with limits can be moved')
        if kind != 'revolute':
            raise UrdfError(f'{source}: joint {name!r} is {kind}: only revolute joints can be '
                            'moved')
        lower, upper = _limits(by_name[name])
        if not (math.isfinite(lower) and math.isfinite(upper) and lower < upper):
            raise UrdfError(f'{source}: joint {name!r} has no usable <limit lower upper> '
                            f'(got {lower}, {upper})')
    locked = dict(locked or {})
    for name, value in locked.items():
        if name not in by_name or name in joints or by_name[name].get('type') not in _MOVABLE:
            raise UrdfError(f'{source}: cannot lock {name!r}: not a movable joint that is '
                            f'not moving; those are {[n for n in movable if n not in joints]}')
        if not math.isfinite(float(value)):
            raise UrdfError(f'{source}: locked position of {name!r} is not finite')
    positions = {}
    for name in movable:
        if name in joints:
            continue
        lower, upper = _limits(by_name[name])
        value = float(locked.get(name, min(max(0.0, lower), upper)))
        _lock(by_name[name], value, source)
        positions[name] = value
    return ElementTree.tostring(root, encoding='unicode'), joints, positions

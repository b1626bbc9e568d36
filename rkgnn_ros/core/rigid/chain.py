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
A serial chain of revolute joints from its numbers alone: no robot description needed.

A :class:`Chain` holds, per joint, the fixed pose of its frame in the previous joint's
frame at θ = 0 (the first joint's in the base frame) and its unit axis in its own frame,
plus gravity in the base frame: the arrays of a :class:`~.kernels.Tree` without the tree.
:func:`from_dh` builds one from modified Denavit-Hartenberg numbers (Craig's: the frame of
joint i is placed by Rx(α) Tx(a) Rz(offset) Tz(d) from the previous one, its axis z).
:class:`ChainStructure` is a :class:`~.structure.RigidStructure` built from a chain instead
of a URDF, so the kernels, the base parameters, :func:`~.solve.fit_consistent` and every
``rigid_fit`` function take it unchanged; :func:`chain_urdf` writes the chain as a URDF
(a ``world`` link with gravity along its -z, the base under it, one link per joint) whose
Pinocchio model has exactly these joint frames, so
:func:`~.urdf_out.identified_urdf` fills in the identified inertials.

:func:`lines` gives each joint axis as a line in the base frame at θ = 0 (unit direction,
the line's point nearest the base origin): what a chain means physically, whatever its
numbers. :func:`axis_errors` compares two chains' axes up to the symmetries of the
dynamics: a rigid motion of the whole arm, and a mirror image through a vertical plane with
every axis turned (the Lagrangian is unchanged: on the axes, a pseudo-vector each, the two
together act as one rotation, so the best rotation between the axis sets covers both).
"""

import math
from typing import NamedTuple, Optional, Sequence

import numpy as np

from .kernels import N_INERTIAL, N_JOINT, Tree
from .structure import COULOMB_VELOCITY, RigidStructure

__all__ = ['Chain', 'ChainStructure', 'DH', 'axis_errors', 'chain_of', 'chain_tree',
           'chain_urdf', 'default_prior', 'dh_of_lines', 'from_dh', 'lines', 'poses',
           'rotation_x', 'rotation_z']


class Chain(NamedTuple):
    """
    A serial revolute chain (module docstring); n joints.

    Attributes
    ----------
    rot : ndarray, shape (n, 3, 3)
        Joint i's frame in joint i-1's frame at θ = 0 (child to parent; joint 0's in the
        base frame).
    pos : ndarray, shape (n, 3)
        Its origin there (m).
    axis : ndarray, shape (n, 3)
        Unit joint axis in the joint's own frame.
    gravity : ndarray, shape (3,)
        Gravitational acceleration in the base frame (m/s²).

    """

    rot: np.ndarray
    pos: np.ndarray
    axis: np.ndarray
    gravity: np.ndarray

    @property
    def n_joints(self) -> int:
        """Return the number of joints n."""
        return self.pos.shape[0]


def rotation_x(angle: float) -> np.ndarray:
    """Return the rotation by ``angle`` (rad) about x."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rotation_z(angle: float) -> np.ndarray:
    """Return the rotation by ``angle`` (rad) about z."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def from_dh(alpha, a, offset, d, gravity) -> Chain:
    """
    Return the chain of modified DH numbers, each (n,) (rad, m, rad, m).

    Joint i's frame is Rx(α_i) Tx(a_i) Rz(offset_i) Tz(d_i) in joint i-1's (joint 0's in
    the base frame), its axis z. ``gravity`` (3,) in the base frame (m/s²).
    """
    alpha, a, offset, d = (np.asarray(v, dtype=float).reshape(-1) for v in (alpha, a, offset, d))
    n = alpha.size
    if not (a.size == offset.size == d.size == n) or n < 1:
        raise ValueError('alpha, a, offset and d must have one value per joint')
    rot = np.empty((n, 3, 3))
    pos = np.empty((n, 3))
    for i in range(n):
        rot[i] = rotation_x(alpha[i]) @ rotation_z(offset[i])
        pos[i] = (a[i], -d[i] * math.sin(alpha[i]), d[i] * math.cos(alpha[i]))
    axis = np.tile([0.0, 0.0, 1.0], (n, 1))
    return Chain(rot, pos, axis, np.asarray(gravity, dtype=float).reshape(3).copy())


def chain_tree(chain: Chain, coulomb_velocity: float = COULOMB_VELOCITY) -> Tree:
    """Return the :class:`~.kernels.Tree` of a chain: body i hangs on body i-1, column i."""
    n = chain.n_joints
    axis = np.asarray(chain.axis, dtype=float)
    norm = np.linalg.norm(axis, axis=1)
    if not (np.all(np.isfinite(norm)) and np.all(norm > 0.0)):
        raise ValueError('every joint needs a finite, non-zero axis')
    return Tree(np.arange(-1, n - 1, dtype=np.int64), np.arange(n, dtype=np.int64),
                np.ascontiguousarray(chain.rot, dtype=float),
                np.ascontiguousarray(chain.pos, dtype=float),
                np.ascontiguousarray(axis / norm[:, None]),
                np.ascontiguousarray(chain.gravity, dtype=float), float(coulomb_velocity))


def chain_of(structure: RigidStructure) -> Chain:
    """
    Return the chain of a structure whose moving joints form one serial chain.

    Raises
    ------
    ValueError
        If a body's parent is not the body driven by the previous column.

    """
    tree = structure.tree
    order = np.argsort(tree.col)
    for k, body in enumerate(order):
        parent = tree.parent[body]
        if (k == 0 and parent != -1) or (k > 0 and parent != order[k - 1]):
            raise ValueError(f'{structure.source}: the moving joints are not one serial chain')
    return Chain(tree.rot[order].copy(), tree.pos[order].copy(), tree.axis[order].copy(),
                 np.asarray(tree.gravity, dtype=float).copy())


def poses(chain: Chain):
    """Return each joint frame's rotation (n, 3, 3) and origin (n, 3) in the base at θ = 0."""
    n = chain.n_joints
    rot = np.empty((n, 3, 3))
    origin = np.empty((n, 3))
    r, p = np.eye(3), np.zeros(3)
    for i in range(n):
        p = p + r @ chain.pos[i]
        r = r @ chain.rot[i]
        rot[i], origin[i] = r, p
    return rot, origin


def lines(chain: Chain):
    """Return each axis at θ = 0 in the base frame: unit directions and nearest points (n, 3)."""
    rot, origin = poses(chain)
    axes = np.einsum('nij,nj->ni', rot, chain.axis)
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    points = origin - np.sum(origin * axes, axis=1, keepdims=True) * axes
    return axes, points


class DH(NamedTuple):
    """
    Modified DH numbers of a chain in the base frame they fix (:func:`dh_of_lines`).

    ``alpha``, ``a``, ``offset``, ``d`` (n,) as :func:`from_dh` takes them; ``gravity`` (3,)
    in that base frame; ``rotation`` (3, 3), ``origin`` (3,): that base frame in the frame
    the lines were given in.
    """

    alpha: np.ndarray
    a: np.ndarray
    offset: np.ndarray
    d: np.ndarray
    gravity: np.ndarray
    rotation: np.ndarray
    origin: np.ndarray

    def chain(self) -> Chain:
        """Return the chain of these numbers (in their own base frame)."""
        return from_dh(self.alpha, self.a, self.offset, self.d, self.gravity)


#: Below this sine two axes count as parallel (their common normal is then chosen).
PARALLEL = 1e-9


def _normal(origin, z, x_now, point, w):
    """
    Return the common normal from the line (origin, z) to the line (point, w).

    (foot on the first line, unit direction x, length a >= 0); for parallel lines the
    normal through ``origin`` (along ``x_now`` if the lines coincide).
    """
    c = np.cross(z, w)
    sine = float(np.linalg.norm(c))
    offset = point - origin
    if sine > PARALLEL:
        foot = origin + (float(np.cross(offset, w) @ c) / sine ** 2) * z
        x = c / sine
        a = float(offset @ x)
        if a < 0.0:
            x, a = -x, -a
        return foot, x, a
    v = offset - float(offset @ z) * z
    a = float(np.linalg.norm(v))
    return origin, (v / a if a > PARALLEL else x_now), a


def dh_of_lines(axes, points, gravity) -> DH:
    """
    Return the modified DH numbers of the axes' lines (module docstring) and gravity.

    ``axes`` (n, 3) unit directions, ``points`` (n, 3) a point of each line, ``gravity``
    (3,), all in one frame. The base frame the numbers fix has the first axis as z, its
    origin where the first common normal meets it and that normal as x, so the first
    joint's numbers are zero; the last joint's offset and d are zero (its frame along its
    axis is free). Parallel neighbours take the common normal through the previous one.
    """
    axes = np.asarray(axes, dtype=float).reshape(-1, 3)
    axes = axes / np.linalg.norm(axes, axis=1, keepdims=True)
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    n = axes.shape[0]
    alpha, a, offset, d = (np.zeros(n) for _ in range(4))
    z = axes[0]
    helper = np.eye(3)[int(np.argmin(np.abs(z)))]
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    origin = points[0]
    if n > 1:
        origin, x, _ = _normal(points[0], z, x, points[1], axes[1])
    rotation = np.stack([x, np.cross(z, x), z], axis=1)
    base_origin = origin.copy()
    for i in range(1, n):
        w = axes[i]
        if i > 1:
            # frame i-1 turns and slides along its axis onto the normal to line i
            foot, x_new, length = _normal(origin, z, x, points[i], w)
            offset[i - 1] = math.atan2(float(np.cross(x, x_new) @ z), float(x @ x_new))
            d[i - 1] = float((foot - origin) @ z)
            origin, x = foot, x_new
        else:
            length = float((points[1] - origin) @ x)
        a[i] = length
        alpha[i] = math.atan2(float(np.cross(z, w) @ x), float(z @ w))
        origin = origin + length * x
        z = w
    return DH(alpha, a, offset, d, rotation.T @ np.asarray(gravity, dtype=float).reshape(3),
              rotation, base_origin)


def _kabsch(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Return the rotation R minimising Σ |R s_i − t_i|² (rows of ``source``, ``target``)."""
    u, _, vt = np.linalg.svd(target.T @ source)
    sign = np.sign(np.linalg.det(u @ vt)) or 1.0
    return u @ np.diag([1.0, 1.0, sign]) @ vt


def _angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Return the angle (deg) between rows of unit vectors a and b."""
    cross = np.linalg.norm(np.cross(a, b), axis=-1)
    return np.degrees(np.arctan2(cross, np.sum(a * b, axis=-1)))


def axis_errors(learned: Chain, true: Chain) -> dict:
    """
    Return how far the learned axes are from the true ones, up to the symmetries (degrees).

    ``aligned_deg`` (n,): each axis's angle to the true one after the one rotation that
    best maps the learned axes onto the true ones (module docstring: a rigid motion or a
    mirror image of the arm); ``aligned_deg_max``; ``pairwise_deg_max``: the largest error
    of the angle between two axes, over every pair (no alignment at all); ``gravity_deg``:
    the error of the angle between gravity and the first axis, taken as its supplement
    when the alignment is a mirror image's.
    """
    a, _ = lines(learned)
    b, _ = lines(true)
    if a.shape != b.shape:
        raise ValueError(f'{a.shape[0]} learned axes against {b.shape[0]} true ones')
    r = _kabsch(a, b)
    aligned = _angle(a @ r.T, b)
    ia, ib = np.triu_indices(a.shape[0], 1)
    pairs = np.abs(_angle(a[ia], a[ib]) - _angle(b[ia], b[ib])) if ia.size else np.zeros(1)
    ga = learned.gravity / np.linalg.norm(learned.gravity)
    gb = true.gravity / np.linalg.norm(true.gravity)
    tilt_a = float(_angle(a[0], ga))
    tilt_b = float(_angle(b[0], gb))
    # the mirror image keeps gravity and turns the axes: their angle to it becomes 180° - it
    mirrored = float(_angle(r @ ga, gb)) > 90.0
    gravity = abs((180.0 - tilt_a if mirrored else tilt_a) - tilt_b)
    return {'aligned_deg': aligned.tolist(), 'aligned_deg_max': float(np.max(aligned)),
            'pairwise_deg_max': float(np.max(pairs)), 'gravity_deg': gravity,
            'mirrored': mirrored}


def _rpy(r: np.ndarray):
    """Return URDF roll, pitch, yaw of a rotation (R = Rz(yaw) Ry(pitch) Rx(roll))."""
    pitch = math.atan2(-r[2, 0], math.hypot(r[0, 0], r[1, 0]))
    if math.hypot(r[0, 0], r[1, 0]) > 1e-12:
        return math.atan2(r[2, 1], r[2, 2]), pitch, math.atan2(r[1, 0], r[0, 0])
    return math.atan2(-r[1, 2], r[1, 1]), pitch, 0.0


def _levelling(gravity: np.ndarray) -> np.ndarray:
    """Return the smallest rotation R with R ĝ = -z (base to world)."""
    g = gravity / np.linalg.norm(gravity)
    down = np.array([0.0, 0.0, -1.0])
    axis = np.cross(g, down)
    s, c = float(np.linalg.norm(axis)), float(g @ down)
    if s < 1e-12:
        return np.eye(3) if c > 0.0 else np.diag([1.0, -1.0, -1.0])
    k = axis / s
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    angle = math.atan2(s, c)
    return np.eye(3) + math.sin(angle) * kx + (1.0 - math.cos(angle)) * kx @ kx


def _numbers(values) -> str:
    return ' '.join(repr(float(v)) for v in values)


def chain_urdf(chain: Chain, joint_names: Sequence[str], name: str = 'learned_chain',
               limit: float = math.pi) -> str:
    """
    Return the chain as URDF XML (module docstring), links without inertials.

    Joint limits are ±``limit`` (rad). The base hangs on a fixed joint from ``world`` that
    turns the chain's gravity to world -z, as a URDF's gravity is.
    """
    import xml.etree.ElementTree as ElementTree
    if len(joint_names) != chain.n_joints:
        raise ValueError(f'{chain.n_joints} joint names expected, got {len(joint_names)}')
    robot = ElementTree.Element('robot', name=name)
    links = ['world', 'chain_base'] + [f'chain_link{i + 1}' for i in range(chain.n_joints)]
    for link in links:
        ElementTree.SubElement(robot, 'link', name=link)
    fixed = ElementTree.SubElement(robot, 'joint', name='chain_base_joint', type='fixed')
    ElementTree.SubElement(fixed, 'parent', link='world')
    ElementTree.SubElement(fixed, 'child', link='chain_base')
    ElementTree.SubElement(fixed, 'origin', xyz='0 0 0',
                           rpy=_numbers(_rpy(_levelling(chain.gravity))))
    for i, joint_name in enumerate(joint_names):
        joint = ElementTree.SubElement(robot, 'joint', name=str(joint_name), type='revolute')
        ElementTree.SubElement(joint, 'parent', link=links[i + 1])
        ElementTree.SubElement(joint, 'child', link=links[i + 2])
        ElementTree.SubElement(joint, 'origin', xyz=_numbers(chain.pos[i]),
                               rpy=_numbers(_rpy(chain.rot[i])))
        axis = chain.axis[i] / np.linalg.norm(chain.axis[i])
        ElementTree.SubElement(joint, 'axis', xyz=_numbers(axis))
        ElementTree.SubElement(joint, 'limit', lower=repr(-limit), upper=repr(limit),
                               effort='1000', velocity='10')
    return ElementTree.tostring(robot, encoding='unicode')


def default_prior(n: int, mass: float = 1.0, radius: float = 0.05) -> np.ndarray:
    """
    Return a weak prior of full parameters: bodies of ``mass`` (kg) at their joint frames.

    Each body a ball of ``radius`` (m), the joint terms zero: where the data decide nothing
    (a body's parameters that no torque depends on), the fit keeps these.
    """
    body = np.zeros(N_INERTIAL)
    body[0] = mass
    body[4:7] = 0.4 * mass * radius ** 2
    return np.concatenate([np.tile(body, n), np.zeros(N_JOINT * n)])


class ChainStructure(RigidStructure):
    """
    The rigid-body structure of a :class:`Chain` (module docstring): no URDF, no Pinocchio.

    Parameters
    ----------
    chain : Chain
        The kinematics.
    joint_names : sequence of str, optional
        Names of the joint vector's columns (default joint1 ... jointn).
    prior : array_like, shape (P,), optional
        Parameters the consistent fit falls back on (default :func:`default_prior`).
    source : str
        Names the structure in messages.

    """

    def __init__(self, chain: Chain, joint_names: Optional[Sequence[str]] = None,
                 prior=None, source: str = 'learned chain',
                 coulomb_velocity: float = COULOMB_VELOCITY):
        n = chain.n_joints
        self.chain = chain
        self.source = source
        names = [f'joint{i + 1}' for i in range(n)] if joint_names is None else joint_names
        self.joint_names = tuple(str(v) for v in names)
        if len(self.joint_names) != n:
            raise ValueError(f'{n} joint names expected, got {len(self.joint_names)}')
        self.tree = chain_tree(chain, coulomb_velocity)
        self.gravity = float(np.linalg.norm(chain.gravity))
        self.prior = (default_prior(n) if prior is None
                      else np.asarray(prior, dtype=float).reshape(-1).copy())
        if self.prior.size != self.n_parameters:
            raise ValueError(f'a prior of {self.n_parameters} parameters expected')
        self.lower = np.full(n, -math.pi)
        self.upper = np.full(n, math.pi)
        self._base = None
        self._urdf = None

    @property
    def urdf(self) -> str:
        """Return the chain as URDF (:func:`chain_urdf`), written at the first call."""
        if self._urdf is None:
            self._urdf = chain_urdf(self.chain, self.joint_names)
        return self._urdf

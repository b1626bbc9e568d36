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
An arm's rigid-body structure from its robot description: what identification may trust.

A URDF's kinematics (each joint's placement and axis) are right; its inertial values are
CAD guesses at best and its friction is usually absent. :class:`RigidStructure` keeps the
first as the :class:`~.kernels.Tree` the compiled kernels take, and the second only as a
prior (:attr:`RigidStructure.prior`): the full parameter vector of :mod:`.kernels` (ten
inertial parameters per moving body, links rigidly attached to it merged in, then four per
joint: rotor inertia, viscous and Coulomb friction, torque offset).

Not every parameter changes the torque: a body's mass on a joint that only turns it about
its own axis, for one. :class:`BaseParameters` finds the identifiable combinations (the
base parameters, Gautier's) numerically: the regressor at random states, a QR
factorisation with column pivoting, its rank r; the r independent columns B span every
other column D as Y_D = Y_B K, so τ = Y_B (π_B + K π_D). Least squares determines
π_B + K π_D and nothing else.

Pinocchio (``pin``) parses the URDF and merges fixed links; the kernels and every fit are
this package's own. Moving joints must be revolute (or continuous); the bodies keep
Pinocchio's order (parents first), the joint vector keeps the caller's (``joint_names``),
and :attr:`Tree.col` maps one to the other.
"""

import math
from typing import Sequence

import numpy as np

from . import kernels
from .kernels import N_INERTIAL, N_JOINT, Tree

__all__ = ['BaseParameters', 'DescriptionError', 'RigidStructure', 'from_pinocchio_order',
           'to_pinocchio_order']

#: Smoothing velocity v_c of the Coulomb term tanh(θ̇ / v_c) (rad/s).
COULOMB_VELOCITY = 0.05

#: Pinocchio's revolute joint kinds (the unbounded ``RUB*`` are URDF continuous joints).
_REVOLUTE = {'JointModelRX': (1.0, 0.0, 0.0), 'JointModelRY': (0.0, 1.0, 0.0),
             'JointModelRZ': (0.0, 0.0, 1.0), 'JointModelRUBX': (1.0, 0.0, 0.0),
             'JointModelRUBY': (0.0, 1.0, 0.0), 'JointModelRUBZ': (0.0, 0.0, 1.0)}

# Pinocchio's dynamic parameters [m, mc, Ixx, Ixy, Iyy, Ixz, Iyz, Izz] in this package's
# order [m, mc, Ixx, Iyy, Izz, Ixy, Ixz, Iyz]
_FROM_PIN = np.array([0, 1, 2, 3, 4, 6, 9, 5, 7, 8])


class DescriptionError(ValueError):
    """A robot description that cannot give a rigid-body model; the message says why."""


def from_pinocchio_order(dynamic_parameters) -> np.ndarray:
    """Return Pinocchio's ``toDynamicParameters`` (10,) in this package's order."""
    return np.asarray(dynamic_parameters, dtype=float).reshape(-1)[_FROM_PIN]


def to_pinocchio_order(parameters) -> np.ndarray:
    """Return this package's ten inertial parameters in Pinocchio's order."""
    out = np.empty(N_INERTIAL)
    out[_FROM_PIN] = np.asarray(parameters, dtype=float).reshape(-1)
    return out


def _check_inertials(urdf: str, source: str) -> None:
    """
    Refuse a URDF whose masses or inertias are not finite numbers, or whose mass is < 0.

    urdfdom drops an ``<inertial>`` it cannot read (a link with mass "nan" becomes massless,
    with a line on stderr only), so the values are read here first.
    """
    import xml.etree.ElementTree as ElementTree
    try:
        root = ElementTree.fromstring(urdf)
    except ElementTree.ParseError as error:
        raise DescriptionError(f'{source}: not valid XML ({error})') from None
    for link in root.iter('link'):
        inertial = link.find('inertial')
        if inertial is None:
            continue
        name = link.get('name')
        values = []
        mass = inertial.find('mass')
        if mass is not None:
            values.append(('mass', mass.get('value')))
        inertia = inertial.find('inertia')
        if inertia is not None:
            keys = ('ixx', 'ixy', 'ixz', 'iyy', 'iyz', 'izz')
            values += [(key, inertia.get(key)) for key in keys]
        for key, text in values:
            try:
                value = float(text)
            except (TypeError, ValueError):
                value = math.nan
            if not math.isfinite(value):
                raise DescriptionError(f'{source}: link {name!r} has {key} {text!r}, not a '
                                       'finite number')
            if key == 'mass' and value < 0.0:
                raise DescriptionError(f'{source}: link {name!r} has a negative mass '
                                       f'({value:g} kg)')


class RigidStructure:
    """
    The kinematic tree of an arm's moving joints and the prior its URDF gives.

    Parameters
    ----------
    urdf : str
        URDF XML in which exactly ``joint_names`` move (others fixed: see
        :func:`rkgnn_ros.core.sim.urdf_arm.reduce_urdf`).
    joint_names : sequence of str
        The moving joints in the order of the joint vector (the data's columns).
    gravity : float
        Gravitational acceleration (m/s²) along -z of the root link, >= 0.
    source : str
        Names the description in messages.

    Raises
    ------
    DescriptionError
        If Pinocchio cannot build the model, its moving joints differ from
        ``joint_names``, a moving joint is not revolute, or an inertial value is not finite.

    """

    def __init__(self, urdf: str, joint_names: Sequence[str], gravity: float = 9.81,
                 source: str = 'robot_description'):
        import pinocchio
        self.source = source
        self.joint_names = tuple(str(name) for name in joint_names)
        gravity = float(gravity)
        if not (math.isfinite(gravity) and gravity >= 0.0):
            raise DescriptionError(f'gravity must be finite and >= 0, got {gravity}')
        _check_inertials(urdf, source)
        try:
            model = pinocchio.buildModelFromXML(urdf)
        except Exception as error:  # noqa: B902 - Pinocchio raises several types
            raise DescriptionError(f'{source}: Pinocchio cannot build the model: '
                                   f'{error}') from None
        names = [model.names[i] for i in range(1, model.njoints)]
        if sorted(names) != sorted(self.joint_names) or len(names) != len(self.joint_names):
            raise DescriptionError(f'{source}: its moving joints are {names}, the arm moves '
                                   f'{list(self.joint_names)}')
        nb = len(names)
        parent = np.empty(nb, dtype=np.int64)
        col = np.empty(nb, dtype=np.int64)
        rot = np.empty((nb, 3, 3))
        pos = np.empty((nb, 3))
        axis = np.empty((nb, 3))
        prior = np.zeros(N_INERTIAL * nb + N_JOINT * nb)
        for i in range(1, model.njoints):
            joint = model.joints[i]
            kind = joint.shortname()
            if kind in _REVOLUTE:
                a = np.array(_REVOLUTE[kind])
            elif kind in ('JointModelRevoluteUnaligned', 'JointModelRevoluteUnboundedUnaligned'):
                a = np.asarray(joint.extract().axis, dtype=float).reshape(3)
            else:
                raise DescriptionError(f'{source}: joint {model.names[i]!r} is a {kind}: only '
                                       'revolute joints are identified')
            norm = float(np.linalg.norm(a))
            if not (math.isfinite(norm) and norm > 0.0):
                raise DescriptionError(f'{source}: joint {model.names[i]!r} has no axis')
            b = i - 1
            parent[b] = model.parents[i] - 1
            col[b] = self.joint_names.index(model.names[i])
            placement = model.jointPlacements[i]
            rot[b] = np.asarray(placement.rotation, dtype=float)
            pos[b] = np.asarray(placement.translation, dtype=float)
            axis[b] = a / norm
            inertial = from_pinocchio_order(model.inertias[i].toDynamicParameters())
            if not np.all(np.isfinite(inertial)):
                raise DescriptionError(f'{source}: the inertia moved by joint '
                                       f'{model.names[i]!r} is not finite')
            if inertial[0] < 0.0:
                raise DescriptionError(f'{source}: the mass moved by joint '
                                       f'{model.names[i]!r} is negative ({inertial[0]:g} kg)')
            prior[N_INERTIAL * b:N_INERTIAL * (b + 1)] = inertial
        joint_prior = prior[N_INERTIAL * nb:].reshape(nb, N_JOINT)
        for name, values in (('armature', 0), ('damping', 1), ('friction', 2)):
            data = np.asarray(getattr(model, name, np.zeros(nb)), dtype=float).reshape(-1)
            if data.size == nb and np.all(np.isfinite(data)):
                for i in range(nb):
                    joint_prior[col[i], values] = max(0.0, float(data[i]))
        self.tree = Tree(parent, col, np.ascontiguousarray(rot), np.ascontiguousarray(pos),
                         np.ascontiguousarray(axis), np.array([0.0, 0.0, -gravity]),
                         COULOMB_VELOCITY)
        #: the URDF's parameters (full vector; joint terms from <dynamics> where given)
        self.prior = prior
        self.gravity = gravity
        self.urdf = urdf
        self.lower = np.empty(nb)
        self.upper = np.empty(nb)
        for i in range(nb):
            lo = float(model.lowerPositionLimit[i])
            hi = float(model.upperPositionLimit[i])
            c = col[i]
            self.lower[c] = lo if math.isfinite(lo) and hi > lo else -math.pi
            self.upper[c] = hi if math.isfinite(hi) and hi > lo else math.pi
        self._base = None

    # -- sizes ----------------------------------------------------------------------------

    @property
    def n_joints(self) -> int:
        """Return the number of moving joints n (= moving bodies)."""
        return self.tree.parent.shape[0]

    @property
    def n_parameters(self) -> int:
        """Return the size of the full parameter vector, 10 n + 4 n."""
        return (N_INERTIAL + N_JOINT) * self.n_joints

    @property
    def base(self) -> 'BaseParameters':
        """Return the base parameters (computed once)."""
        if self._base is None:
            self._base = BaseParameters(self)
        return self._base

    # -- dynamics ---------------------------------------------------------------------------

    def _args(self):
        t = self.tree
        return t.parent, t.col, t.rot, t.pos, t.axis, t.gravity, t.coulomb_velocity

    def regressor(self, theta, theta_dot, theta_ddot) -> np.ndarray:
        """Return Y at states (K, n), shape (K, n, P): τ = Y π for the full vector π."""
        q, qd, qdd = _states(self.n_joints, theta, theta_dot, theta_ddot)
        return kernels.regressor(*self._args(), q, qd, qdd)

    def rows(self, theta, theta_dot, theta_ddot, columns=None) -> np.ndarray:
        """Return the regressor's ``columns`` (default all) stacked joint-major, (K n, C)."""
        q, qd, qdd = _states(self.n_joints, theta, theta_dot, theta_ddot)
        if columns is None:
            columns = np.arange(self.n_parameters)
        return kernels.regressor_rows(*self._args(), q, qd, qdd,
                                      np.ascontiguousarray(columns, dtype=np.int64))

    def inverse_dynamics(self, parameters, theta, theta_dot, theta_ddot) -> np.ndarray:
        """Return τ = M θ̈ + V + G + F of the full vector ``parameters``, shape (K, n)."""
        q, qd, qdd = _states(self.n_joints, theta, theta_dot, theta_ddot)
        return kernels.inverse_dynamics(*self._args(), self._vector(parameters), q, qd, qdd)

    def mass_matrix(self, parameters, theta) -> np.ndarray:
        """Return M(θ), shape (K, n, n), rotor inertia included."""
        (q,) = _states(self.n_joints, theta)
        t = self.tree
        return kernels.mass_matrix(t.parent, t.col, t.rot, t.pos, t.axis,
                                   self._vector(parameters), q)

    def gravity_torque(self, parameters, theta) -> np.ndarray:
        """Return G(θ) (joint terms' offsets excluded), shape (K, n)."""
        (q,) = _states(self.n_joints, theta)
        pi = self._vector(parameters).copy()
        pi[N_INERTIAL * self.n_joints:] = 0.0
        zeros = np.zeros(q.shape)
        return kernels.inverse_dynamics(*self._args(), pi, q, zeros, zeros)

    def accelerations(self, parameters, theta, theta_dot, tau) -> np.ndarray:
        """Return θ̈ = M⁻¹ (τ − V − G − F), shape (K, n); NaN where M is not positive."""
        q, qd, torque = _states(self.n_joints, theta, theta_dot, tau)
        return kernels.accelerations(*self._args(), self._vector(parameters), q, qd, torque)

    def _vector(self, parameters) -> np.ndarray:
        pi = np.ascontiguousarray(parameters, dtype=float).reshape(-1)
        if pi.size != self.n_parameters:
            raise ValueError(f'expected {self.n_parameters} parameters, got {pi.size}')
        return pi

    def random_states(self, count: int, rng: np.random.Generator):
        """Return ``count`` random (θ, θ̇, θ̈) over the joint ranges, each (count, n)."""
        n = self.n_joints
        theta = rng.uniform(self.lower, self.upper, size=(count, n))
        return theta, rng.normal(0.0, 1.0, (count, n)), rng.normal(0.0, 3.0, (count, n))

    def describe(self) -> str:
        """Return a short description for logs."""
        return (f'{self.n_joints} revolute joints from {self.source}, '
                f'{self.base.rank} base parameters of {self.n_parameters}')


def _states(n: int, *arrays):
    out = []
    for a in arrays:
        arr = np.ascontiguousarray(np.atleast_2d(np.asarray(a, dtype=float)))
        if arr.ndim != 2 or arr.shape[1] != n:
            raise ValueError(f'expected states of shape (K, {n}), got {np.shape(a)}')
        out.append(arr)
    shapes = {a.shape for a in out}
    if len(shapes) != 1:
        raise ValueError(f'the state arrays differ in shape: {sorted(shapes)}')
    return out


class BaseParameters:
    """
    The identifiable combinations of a structure's full parameters (module docstring).

    Attributes
    ----------
    independent : ndarray of int64, shape (r,)
        Columns B of the full regressor that span it.
    dependent : ndarray of int64, shape (P − r,)
        The other columns D.
    combination : ndarray, shape (r, P − r)
        K with Y_D = Y_B K: the base parameters are π_B + K π_D.
    projection : ndarray, shape (r, P)
        The map π ↦ base parameters.

    """

    #: Random states the rank is taken from, per full parameter.
    STATES_PER_PARAMETER = 2

    #: A pivot below this share of the largest is a dependent column.
    RANK_TOLERANCE = 1e-8

    def __init__(self, structure: RigidStructure, seed: int = 0):
        import scipy.linalg
        rng = np.random.default_rng(seed)
        count = max(20, self.STATES_PER_PARAMETER * structure.n_parameters)
        y = structure.rows(*structure.random_states(count, rng))
        scale = np.sqrt(np.mean(y * y, axis=0))
        used = scale > 0.0
        scale[~used] = 1.0
        _, r, pivots = scipy.linalg.qr(y / scale, mode='economic', pivoting=True)
        diag = np.abs(np.diag(r))
        rank = int(np.sum(diag > self.RANK_TOLERANCE * diag[0]))
        independent = np.sort(pivots[:rank])
        dependent = np.sort(np.setdiff1d(np.arange(y.shape[1]), independent))
        # Y_D = Y_B K, by least squares on the same states (exact up to rounding)
        k, *_ = np.linalg.lstsq(y[:, independent], y[:, dependent], rcond=None)
        k[np.abs(k) < 1e-10] = 0.0
        self.independent = independent
        self.dependent = dependent
        self.combination = k
        projection = np.zeros((rank, y.shape[1]))
        projection[np.arange(rank), independent] = 1.0
        projection[:, dependent] = k
        self.projection = projection

    @property
    def rank(self) -> int:
        """Return the number of base parameters r."""
        return self.independent.size

    def of(self, parameters) -> np.ndarray:
        """Return the base parameters (r,) of a full vector (P,)."""
        return self.projection @ np.asarray(parameters, dtype=float)

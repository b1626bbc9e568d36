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
A real arm from its URDF: rigid-body dynamics by Pinocchio, behind the planar arm's interface.

The paper's planar arm (:mod:`.plant`) is a model we wrote; users have arms described by a
URDF. :class:`UrdfArm` takes one (a file or the XML, as in a ``robot_description``), the
joints that move, and a position for every other joint, and offers what the simulator, the
servo and the stability checks use of a :class:`~.plant.PlanarArm`: ``forward_dynamics``
(Pinocchio's articulated-body algorithm, ABA), ``inverse_dynamics`` (recursive
Newton-Euler, RNEA), ``mass_matrix`` (CRBA), ``gravity_terms``, ``velocity_terms``,
``dynamics`` and the closed-loop eigenvalues of a PD servo (from ABA's analytic
derivatives; stiffness and stable step from :class:`.stability.ClosedLoopAnalysis`), each
over leading batch axes. Joint friction, which URDFs rarely carry
usefully, is the planar arm's: ``viscous θ̇ + coulomb tanh(θ̇ / v_c)`` per moving joint.

Locked joints are made fixed in the URDF itself (:func:`~rkgnn_ros.core.rigid.urdf.reduce_urdf`,
with the reading of descriptions): the joint's origin absorbs its locked motion, its type
becomes ``fixed``. The reduced XML is what the
dynamics are built from and what ``sim_arm`` publishes as ``robot_description``, so
robot_state_publisher and rviz show the arm as simulated from the moving joints alone.

For the least-squares peer, :meth:`UrdfArm.regressor` is the joint-torque regressor Y
with ``inverse_dynamics = Y @ parameter_vector()`` (Pinocchio's, ten inertial parameters
per body, with the two friction columns per joint).

A URDF that does not parse, names joints that do not exist, moves a joint that is not a
revolute joint with limits, has an ``<inertial>`` no rigid body has (NaN or inf in it, a
negative mass) or whose moving joints carry no
inertia is refused with a
:class:`UrdfError` naming the source and the problem. Gravity acts along -z of the root
link, as URDFs are drawn.
"""

import math
from typing import Mapping, Optional, Sequence, Union

import numpy as np

from .stability import ClosedLoopAnalysis
from ..rigid.urdf import (EXAMPLE_ROBOT_PREFIX, example_robot_urdf, read_description,
                          reduce_urdf, UrdfError)
from ..servo_law import pd_torque_coupled

__all__ = ['EXAMPLE_ROBOT_PREFIX', 'UrdfArm', 'UrdfError', 'example_robot_urdf',
           'read_description', 'reduce_urdf']

ArrayLike = Union[float, np.ndarray]

#: A moving joint whose inertia (the diagonal of M at the home pose) is below this
#: (kg m^2) moves no mass: the URDF lacks <inertial> elements beyond it.
MIN_JOINT_INERTIA = 1e-9


def _friction(name: str, value, n: int) -> np.ndarray:
    arr = np.asarray(0.0 if value is None else value, dtype=float)
    if arr.ndim == 0:
        arr = np.full(n, float(arr))
    if arr.shape != (n,) or not np.all(np.isfinite(arr)) or np.any(arr < 0.0):
        raise ValueError(f'{name} must be {n} finite values >= 0, got {np.asarray(value)}')
    return arr


class UrdfArm(ClosedLoopAnalysis):
    """
    Rigid-body dynamics of the moving joints of a URDF arm, the others locked.

    Every dynamics method takes arrays with leading batch axes, like
    :class:`~.plant.PlanarArm`: ``theta`` of shape (..., n) gives (..., n) or (..., n, n).

    Parameters
    ----------
    description : str
        The URDF: XML, a file path or ``example-robot-data:<path>``
        (:func:`read_description`).
    joints : sequence of str, optional
        The joints that move (default every revolute joint), in the arm's joint order.
    locked : mapping of str to float, optional
        Positions of the other movable joints (default 0 clipped into their limits).
    gravity : float
        Gravitational acceleration (m/s²) along -z of the root link, >= 0.
    viscous, coulomb : array_like, shape (n,) or scalar, optional
        Joint friction (N m s/rad, N m), default zero.
    coulomb_velocity : float
        Smoothing velocity of the Coulomb term (rad/s), positive.

    Raises
    ------
    UrdfError
        See :func:`reduce_urdf`; also when Pinocchio cannot build the model or a moving
        joint carries no inertia.

    """

    def __init__(self, description: str, joints: Optional[Sequence[str]] = None,
                 locked: Optional[Mapping[str, float]] = None, gravity: float = 9.81,
                 viscous=None, coulomb=None, coulomb_velocity: float = 0.05):
        import pinocchio
        self._pin = pinocchio
        xml, self.source = read_description(description)
        self.urdf, self.joint_names, self.locked = reduce_urdf(xml, joints, locked,
                                                               self.source)
        try:
            model = pinocchio.buildModelFromXML(self.urdf)
        except Exception as error:  # noqa: B902 - Pinocchio raises several types
            raise UrdfError(f'{self.source}: Pinocchio cannot build the model: '
                            f'{error}') from None
        names = tuple(model.names[1:])
        if names != self.joint_names:
            raise UrdfError(f'{self.source}: the moving joints {list(self.joint_names)} are '
                            f'not one serial order of the tree (Pinocchio orders them '
                            f'{list(names)}): list them base to tip')
        gravity = float(gravity)
        if not (math.isfinite(gravity) and gravity >= 0.0):
            raise ValueError(f'gravity must be finite and >= 0, got {gravity}')
        model.gravity.linear = np.array([0.0, 0.0, -gravity])
        self.model = model
        self._data = model.createData()
        self.gravity = gravity
        n = model.nv
        self.lower = np.array(model.lowerPositionLimit, dtype=float)
        self.upper = np.array(model.upperPositionLimit, dtype=float)
        self.effort_limit = np.array(model.effortLimit, dtype=float)
        self.velocity_limit = np.array(model.velocityLimit, dtype=float)
        self.viscous = _friction('viscous', viscous, n)
        self.coulomb = _friction('coulomb', coulomb, n)
        self.coulomb_velocity = float(coulomb_velocity)
        if not (math.isfinite(self.coulomb_velocity) and self.coulomb_velocity > 0.0):
            raise ValueError(f'coulomb_velocity must be positive, got {coulomb_velocity}')
        inertia = np.diag(self.mass_matrix(self.home))
        light = [name for name, value in zip(self.joint_names, inertia)
                 if not value > MIN_JOINT_INERTIA]
        if light:
            raise UrdfError(f'{self.source}: joint(s) {light} move no inertia (the links '
                            'beyond them have no <inertial> mass)')

    def set_friction(self, viscous=None, coulomb=None) -> None:
        """Set the joint friction (N m s/rad, N m): n values each or a scalar, >= 0."""
        n = self.n_joints
        self.viscous = _friction('viscous', viscous, n)
        self.coulomb = _friction('coulomb', coulomb, n)

    def set_armature(self, armature=None) -> None:
        """
        Set each joint's rotor (armature) inertia (kg m²): n values or a scalar, >= 0.

        A geared motor adds its rotor's inertia times the gear ratio squared to the joint's
        own (M's diagonal); URDFs do not carry it. Pinocchio's CRBA and ABA include it.
        """
        self.model.armature = _friction('armature', armature, self.n_joints)

    # -- description ----------------------------------------------------------------------

    @property
    def n_joints(self) -> int:
        """Count of moving joints, n."""
        return self.model.nv

    @property
    def n_states(self) -> int:
        """State dimension 2n of x = [θ, θ̇]."""
        return 2 * self.model.nv

    @property
    def home(self) -> np.ndarray:
        """Return the middle of every moving joint's limits (rad), shape (n,)."""
        return 0.5 * (self.lower + self.upper)

    def describe(self) -> str:
        """Return a short description for logs."""
        return (f'URDF arm {self.model.name!r} from {self.source} ({self.n_joints} moving '
                f'joints, {len(self.locked)} locked)')

    # -- batching -------------------------------------------------------------------------

    def _joint_array(self, name: str, value) -> np.ndarray:
        arr = np.asarray(value, dtype=float)
        if arr.ndim == 0 or arr.shape[-1] != self.n_joints:
            raise ValueError(f'{name} must have shape (..., {self.n_joints}), got {arr.shape}')
        return arr

    def _each(self, function, width: Optional[int], *arrays) -> np.ndarray:
        """Apply ``function`` to every state of the broadcast ``arrays`` (..., n)."""
        arrays = np.broadcast_arrays(*arrays)
        batch = arrays[0].shape[:-1]
        n = self.n_joints
        out = np.empty(batch + ((n,) if width is None else (n, width)))
        for index in np.ndindex(*batch):
            out[index] = function(*(np.ascontiguousarray(a[index]) for a in arrays))
        return out

    # -- dynamics terms -------------------------------------------------------------------

    def mass_matrix(self, theta: ArrayLike) -> np.ndarray:
        """Return M(θ) (CRBA), shape (..., n, n), symmetric positive definite."""
        theta = self._joint_array('theta', theta)
        pin, model, data = self._pin, self.model, self._data

        def one(q):
            m = pin.crba(model, data, q)
            return np.triu(m) + np.triu(m, 1).T

        return self._each(one, self.n_joints, theta)

    def gravity_terms(self, theta: ArrayLike) -> np.ndarray:
        """Return G(θ), shape (..., n)."""
        theta = self._joint_array('theta', theta)
        pin, model, data = self._pin, self.model, self._data
        return self._each(lambda q: pin.computeGeneralizedGravity(model, data, q), None, theta)

    def velocity_terms(self, theta: ArrayLike, theta_dot: ArrayLike) -> np.ndarray:
        """Return the Coriolis and centrifugal vector V(θ, θ̇) = C(θ, θ̇) θ̇, shape (..., n)."""
        theta = self._joint_array('theta', theta)
        theta_dot = self._joint_array('theta_dot', theta_dot)
        pin, model, data = self._pin, self.model, self._data
        return self._each(lambda q, v: (pin.nonLinearEffects(model, data, q, v)
                                        - pin.computeGeneralizedGravity(model, data, q)),
                          None, theta, theta_dot)

    def friction_terms(self, theta_dot: ArrayLike) -> np.ndarray:
        """Return the friction torque ``viscous θ̇ + coulomb tanh(θ̇ / v_c)``, shape (..., n)."""
        theta_dot = self._joint_array('theta_dot', theta_dot)
        return (self.viscous * theta_dot
                + self.coulomb * np.tanh(theta_dot / self.coulomb_velocity))

    def inverse_dynamics(self, theta: ArrayLike, theta_dot: ArrayLike,
                         theta_ddot: ArrayLike) -> np.ndarray:
        """Return τ = M θ̈ + V + G + F (RNEA and friction), shape (..., n)."""
        theta = self._joint_array('theta', theta)
        theta_dot = self._joint_array('theta_dot', theta_dot)
        theta_ddot = self._joint_array('theta_ddot', theta_ddot)
        pin, model, data = self._pin, self.model, self._data
        tau = self._each(lambda q, v, a: pin.rnea(model, data, q, v, a), None, theta,
                         theta_dot, theta_ddot)
        return tau + self.friction_terms(theta_dot)

    def forward_dynamics(self, theta: ArrayLike, theta_dot: ArrayLike,
                         tau: ArrayLike) -> np.ndarray:
        """Return θ̈ = M⁻¹ (τ - V - G - F) (ABA), shape (..., n)."""
        theta = np.asarray(theta, dtype=float)
        theta_dot = np.asarray(theta_dot, dtype=float)
        tau = np.asarray(tau, dtype=float)
        n = self.n_joints
        if theta.shape == theta_dot.shape == tau.shape == (n,):   # the simulator's hot path
            return self._pin.aba(self.model, self._data, theta, theta_dot,
                                 tau - self.friction_terms(theta_dot)).copy()
        theta = self._joint_array('theta', theta)
        theta_dot = self._joint_array('theta_dot', theta_dot)
        tau = self._joint_array('tau', tau)
        pin, model, data = self._pin, self.model, self._data
        net = tau - self.friction_terms(theta_dot)
        return self._each(lambda q, v, t: pin.aba(model, data, q, v, t), None, theta,
                          theta_dot, net)

    def dynamics(self, x: ArrayLike, tau: ArrayLike) -> np.ndarray:
        """Return ẋ = [θ̇, θ̈] of x = [θ, θ̇], shape (..., 2n)."""
        x = np.asarray(x, dtype=float)
        n = self.n_joints
        if x.ndim == 0 or x.shape[-1] != 2 * n:
            raise ValueError(f'x must have shape (..., {2 * n}), got {x.shape}')
        theta_ddot = self.forward_dynamics(x[..., :n], x[..., n:], tau)
        theta_dot = np.broadcast_to(x[..., n:], theta_ddot.shape)
        return np.concatenate([theta_dot, theta_ddot], axis=-1)

    # -- linear-in-parameters form --------------------------------------------------------

    def parameter_vector(self) -> np.ndarray:
        """
        Return p with ``inverse_dynamics == regressor @ p``, shape (10 n + 2 n,).

        Per moving body (locked links merged into their parents) its ten inertial
        parameters (m, m c, the inertia about the joint frame's origin: Pinocchio's
        ``toDynamicParameters``), then viscous and Coulomb coefficients per joint.
        """
        inertial = [np.asarray(self.model.inertias[j].toDynamicParameters()).ravel()
                    for j in range(1, self.model.njoints)]
        return np.concatenate(inertial + [self.viscous, self.coulomb])

    def regressor(self, theta: ArrayLike, theta_dot: ArrayLike,
                  theta_ddot: ArrayLike) -> np.ndarray:
        """
        Return Y with ``inverse_dynamics == Y @ parameter_vector()``, shape (..., n, 12 n).

        The inertial columns are Pinocchio's joint-torque regressor; the last 2n are the
        friction's (θ̇ and tanh(θ̇ / v_c) on the diagonal). Like any full inertial
        parametrisation it is rank deficient; least squares still reproduces the torques.
        """
        theta = self._joint_array('theta', theta)
        theta_dot = self._joint_array('theta_dot', theta_dot)
        theta_ddot = self._joint_array('theta_ddot', theta_ddot)
        theta, theta_dot, theta_ddot = np.broadcast_arrays(theta, theta_dot, theta_ddot)
        pin, model, data = self._pin, self.model, self._data
        n = self.n_joints
        batch = theta.shape[:-1]
        out = np.zeros(batch + (n, 12 * n))
        for index in np.ndindex(*batch):
            out[index][:, :10 * n] = pin.computeJointTorqueRegressor(
                model, data, np.ascontiguousarray(theta[index]),
                np.ascontiguousarray(theta_dot[index]),
                np.ascontiguousarray(theta_ddot[index]))
        eye = np.eye(n)
        out[..., 10 * n:11 * n] = eye * theta_dot[..., :, None]
        out[..., 11 * n:] = eye * np.tanh(theta_dot / self.coulomb_velocity)[..., :, None]
        return out

    # -- closed-loop stiffness ------------------------------------------------------------

    def closed_loop_eigenvalues(self, theta: ArrayLike, theta_dot: ArrayLike, kp, kd,
                                theta_d: Optional[ArrayLike] = None,
                                theta_d_dot: Optional[ArrayLike] = None) -> np.ndarray:
        """
        Return the eigenvalues of the PD closed loop's Jacobian at states, (..., 2n) complex.

        As :meth:`.plant.PlanarArm.closed_loop_eigenvalues` (θd, θ̇d frozen, by default on
        the state), from ABA's analytic derivatives: ∂θ̈/∂θ = ∂ABA/∂θ - M⁻¹ Kp and
        ∂θ̈/∂θ̇ = ∂ABA/∂θ̇ - M⁻¹ (Kd + ∂F/∂θ̇).
        """
        n = self.n_joints
        kp, kd, arrays = self._loop_arguments(theta, theta_dot, kp, kd, theta_d, theta_d_dot)
        batch = arrays[0].shape[:-1]
        pin, model, data = self._pin, self.model, self._data
        out = np.empty(batch + (2 * n,), dtype=complex)
        for index in np.ndindex(*batch):
            q, v, qd, vd = (np.ascontiguousarray(a[index]) for a in arrays)
            tau = pd_torque_coupled(kp, kd, qd - q, vd - v) - self.friction_terms(v)
            pin.computeABADerivatives(model, data, q, v, tau)
            minv = np.triu(data.Minv) + np.triu(data.Minv, 1).T
            slope = (self.viscous + self.coulomb / self.coulomb_velocity
                     / np.cosh(v / self.coulomb_velocity) ** 2)
            jac = np.zeros((2 * n, 2 * n))
            jac[:n, n:] = np.eye(n)
            jac[n:, :n] = data.ddq_dq - minv @ kp
            jac[n:, n:] = data.ddq_dv - minv @ (kd + np.diag(slope))
            out[index] = np.linalg.eigvals(jac)
        return out

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
The plant: a planar n-link revolute arm in a vertical plane, and its PD servo controller.

Conventions
-----------
The arm moves in the vertical x-y plane with gravity along -y. The base joint sits at the
origin; θ_1 is measured from the +x axis and θ_i (i > 1) relative to link i-1, so the
absolute link angles are φ_i = θ_1 + ... + θ_i and the hanging pose is θ = (-π/2, 0, ...).

The dynamics are those of the paper, eq. (1)::

    τ = M(θ) θ̈ + V(θ, θ̇) + G(θ) + F(θ̇)

They are derived in absolute angles φ = S θ (S lower-triangular ones). With the link
constants (c_i: distance of the centre of mass of link i from joint i, J_i its inertia about
joint i, μ_i = Σ_{k>i} m_k the mass carried beyond link i)::

    h_i  = m_i c_i + l_i μ_i              (first moment of everything beyond joint i)
    d_ii = J_i + l_i² μ_i                  (inertia of everything about joint i, locked)
    d_ij = l_i h_j  (i < j),  d_ji = d_ij

the kinetic energy is ½ φ̇ᵀ D(φ) φ̇ with D_ij = d_ij cos(φ_i - φ_j), the potential energy is
g Σ h_i sin φ_i, and Lagrange's equations give, with w_i = Σ_j d_ij sin(φ_i - φ_j) φ̇_j²::

    M = Sᵀ D S,   V = Sᵀ w,   G = Sᵀ (g h ∘ cos φ)

All of it is analytic (no finite differences) and vectorised over leading batch axes. The
parameters are in :mod:`.parameters`, the compiled single-state forward dynamics in
:mod:`.plant_kernels`, the closed-loop stability analysis (which step a simulation may take)
in :mod:`.stability`. :class:`PDController` is the arm's servo, eq. (9) of the paper.
"""

from typing import Tuple, Union

import numpy as np

from .parameters import ArmParameters
from .plant_kernels import forward_dynamics_kernel, KernelConstants
from .stability import ClosedLoopAnalysis, gain_matrix
from ..servo_law import pd_torque_coupled

ArrayLike = Union[float, np.ndarray]


def _rcumsum(a: np.ndarray, axis: int = -1) -> np.ndarray:
    """Reverse cumulative sum, ``out[i] = a[i] + a[i+1] + ...`` (multiplication by Sᵀ)."""
    return np.flip(np.cumsum(np.flip(a, axis), axis=axis), axis)


class PlanarArm(ClosedLoopAnalysis):
    """
    Rigid-body dynamics of a planar n-link arm in a vertical plane.

    Every method takes arrays with leading batch axes: ``theta`` of shape (..., n) gives
    results of shape (..., n) or (..., n, n). See the module docstring for the conventions.

    Parameters
    ----------
    params : ArmParameters
        The physical parameters.

    """

    def __init__(self, params: ArmParameters):
        if not isinstance(params, ArmParameters):
            raise TypeError(f'params must be ArmParameters, got {type(params).__name__}')
        self.params = params
        n = params.n_joints
        m, lengths = params.masses, params.lengths
        # μ_i: mass carried beyond link i
        self._beyond = _rcumsum(m) - m
        self._h = params.first_moments + lengths * self._beyond
        d = np.outer(lengths, self._h)          # d_ij = l_i h_j for i < j
        d = np.triu(d, 1)
        d = d + d.T
        d[np.diag_indices(n)] = params.joint_inertias + lengths ** 2 * self._beyond
        self._d = d
        self._gh = params.gravity * self._h

    @classmethod
    def paper(cls, mass_model: str = 'point') -> 'PlanarArm':
        """Return the paper's three-link arm (see :meth:`ArmParameters.paper`)."""
        return cls(ArmParameters.paper(mass_model))

    @property
    def n_joints(self) -> int:
        """Count of joints, n."""
        return self.params.n_joints

    @property
    def n_states(self) -> int:
        """State dimension 2n of x = [θ, θ̇]."""
        return 2 * self.params.n_joints

    # -- validation -----------------------------------------------------------------------

    def _joint_array(self, name: str, value) -> np.ndarray:
        arr = np.asarray(value, dtype=float)
        if arr.ndim == 0 or arr.shape[-1] != self.n_joints:
            raise ValueError(
                f'{name} must have shape (..., {self.n_joints}), got {arr.shape}')
        return arr

    # -- kinematic helpers ----------------------------------------------------------------

    def _angles(self, theta: np.ndarray):
        phi = np.cumsum(theta, axis=-1)
        return np.cos(phi), np.sin(phi)

    @staticmethod
    def _differences(cos_phi, sin_phi):
        """Return cos(φ_i - φ_j) and sin(φ_i - φ_j), shape (..., n, n)."""
        ci, cj = cos_phi[..., :, None], cos_phi[..., None, :]
        si, sj = sin_phi[..., :, None], sin_phi[..., None, :]
        return ci * cj + si * sj, si * cj - ci * sj

    # -- dynamics terms -------------------------------------------------------------------

    def mass_matrix(self, theta: ArrayLike) -> np.ndarray:
        """
        Return the inertia matrix M(θ).

        Parameters
        ----------
        theta : array_like, shape (..., n)
            Joint angles (rad).

        Returns
        -------
        ndarray, shape (..., n, n)
            Symmetric positive definite.

        """
        theta = self._joint_array('theta', theta)
        cos_diff, _ = self._differences(*self._angles(theta))
        return _rcumsum(_rcumsum(self._d * cos_diff, axis=-1), axis=-2)

    def velocity_terms(self, theta: ArrayLike, theta_dot: ArrayLike) -> np.ndarray:
        """
        Return the Coriolis and centrifugal vector V(θ, θ̇), shape (..., n).

        Exactly C(θ, θ̇) θ̇ with C built from the Christoffel symbols of M.
        """
        theta = self._joint_array('theta', theta)
        theta_dot = self._joint_array('theta_dot', theta_dot)
        _, sin_diff = self._differences(*self._angles(theta))
        phi_dot = np.cumsum(theta_dot, axis=-1)
        w = np.einsum('...ij,...j->...i', self._d * sin_diff, phi_dot ** 2)
        return _rcumsum(w)

    def gravity_terms(self, theta: ArrayLike) -> np.ndarray:
        """Return the gravity vector G(θ) = ∂U/∂θ, shape (..., n)."""
        theta = self._joint_array('theta', theta)
        cos_phi, _ = self._angles(theta)
        return _rcumsum(self._gh * cos_phi)

    def friction_terms(self, theta_dot: ArrayLike) -> np.ndarray:
        """Return the friction torque ``viscous θ̇ + coulomb tanh(θ̇ / v_c)``, shape (..., n)."""
        theta_dot = self._joint_array('theta_dot', theta_dot)
        p = self.params
        return p.viscous * theta_dot + p.coulomb * np.tanh(theta_dot / p.coulomb_velocity)

    def inverse_dynamics(self, theta: ArrayLike, theta_dot: ArrayLike,
                         theta_ddot: ArrayLike) -> np.ndarray:
        """
        Return the joint torques τ = M θ̈ + V + G + F.

        Parameters
        ----------
        theta, theta_dot, theta_ddot : array_like, shape (..., n)
            Joint angles, velocities and accelerations (broadcast together).

        Returns
        -------
        ndarray, shape (..., n)

        """
        theta = self._joint_array('theta', theta)
        theta_dot = self._joint_array('theta_dot', theta_dot)
        theta_ddot = self._joint_array('theta_ddot', theta_ddot)
        cos_phi, sin_phi = self._angles(theta)
        cos_diff, sin_diff = self._differences(cos_phi, sin_phi)
        phi_dot = np.cumsum(theta_dot, axis=-1)
        phi_ddot = np.cumsum(theta_ddot, axis=-1)
        u = (np.einsum('...ij,...j->...i', self._d * cos_diff, phi_ddot)
             + np.einsum('...ij,...j->...i', self._d * sin_diff, phi_dot ** 2)
             + self._gh * cos_phi)
        return _rcumsum(u) + self.friction_terms(theta_dot)

    def forward_dynamics(self, theta: ArrayLike, theta_dot: ArrayLike,
                         tau: ArrayLike) -> np.ndarray:
        """
        Return the joint accelerations θ̈ = M⁻¹ (τ - V - G - F).

        Solves the linear system in absolute angles, D(φ) φ̈ = S⁻ᵀ(τ - F) - w - g h cos φ,
        then θ̈ = S⁻¹ φ̈ (never forms an inverse). ``theta``, ``theta_dot`` and the applied
        ``tau`` (..., n) are broadcast together; θ̈ has their shape.
        """
        theta = self._joint_array('theta', theta)
        theta_dot = self._joint_array('theta_dot', theta_dot)
        tau = self._joint_array('tau', tau)
        if theta.ndim == 1 and theta_dot.ndim == 1 and tau.ndim == 1:
            return self._forward_single(theta, theta_dot, tau)
        cos_phi, sin_phi = self._angles(theta)
        cos_diff, sin_diff = self._differences(cos_phi, sin_phi)
        phi_dot = np.cumsum(theta_dot, axis=-1)
        q = tau - self.friction_terms(theta_dot)
        # S⁻ᵀ q: q_i - q_{i+1}
        rhs = q.copy()
        rhs[..., :-1] -= q[..., 1:]
        rhs -= np.einsum('...ij,...j->...i', self._d * sin_diff, phi_dot ** 2)
        rhs -= self._gh * cos_phi
        phi_ddot = np.linalg.solve(self._d * cos_diff, rhs[..., None])[..., 0]
        theta_ddot = phi_ddot.copy()
        theta_ddot[..., 1:] -= phi_ddot[..., :-1]
        return theta_ddot

    def _forward_single(self, theta, theta_dot, tau):
        """Return :meth:`forward_dynamics` for one state, shapes (n,), by the compiled kernel."""
        p = self.params
        return forward_dynamics_kernel(theta, theta_dot, tau, self._d, self._gh, p.viscous,
                                       p.coulomb, p.coulomb_velocity)

    def kernel_constants(self) -> 'KernelConstants':
        """
        Return the constant arrays of the compiled forward-dynamics kernels.

        ``forward_dynamics_kernel(theta, theta_dot, tau, *arm.kernel_constants())`` equals
        ``arm.forward_dynamics(theta, theta_dot, tau)`` for one state (shapes (n,)); see
        :func:`forward_dynamics_kernel` and the allocation-free
        :func:`forward_dynamics_into`. The arrays are fresh C-contiguous float64 copies,
        so a caller may keep them (e.g. in a compiled simulation) without aliasing the arm.
        """
        p = self.params
        return KernelConstants(
            d=np.array(self._d, dtype=float, order='C'),
            gh=np.array(self._gh, dtype=float, order='C'),
            viscous=np.array(p.viscous, dtype=float, order='C'),
            coulomb=np.array(p.coulomb, dtype=float, order='C'),
            coulomb_velocity=float(p.coulomb_velocity))

    def dynamics(self, x: ArrayLike, tau: ArrayLike) -> np.ndarray:
        """
        Return the state derivative ẋ = [θ̇, θ̈] of x = [θ, θ̇].

        Parameters
        ----------
        x : array_like, shape (..., 2n)
            States [θ, θ̇].
        tau : array_like, shape (..., n)
            Applied joint torques.

        Returns
        -------
        ndarray, shape (..., 2n)

        """
        x = np.asarray(x, dtype=float)
        n = self.n_joints
        if x.ndim == 0 or x.shape[-1] != 2 * n:
            raise ValueError(f'x must have shape (..., {2 * n}), got {x.shape}')
        theta, theta_dot = x[..., :n], x[..., n:]
        theta_ddot = self.forward_dynamics(theta, theta_dot, tau)
        theta_dot = np.broadcast_to(theta_dot, theta_ddot.shape)
        return np.concatenate([theta_dot, theta_ddot], axis=-1)

    def energy(self, theta: ArrayLike, theta_dot: ArrayLike) -> np.ndarray:
        """
        Return the total mechanical energy, kinetic plus potential (J).

        The potential energy is zero with all centres of mass on the x axis.

        Parameters
        ----------
        theta, theta_dot : array_like, shape (..., n)
            Joint angles and velocities.

        Returns
        -------
        ndarray, shape (...)

        """
        theta = self._joint_array('theta', theta)
        theta_dot = self._joint_array('theta_dot', theta_dot)
        cos_phi, sin_phi = self._angles(theta)
        cos_diff, _ = self._differences(cos_phi, sin_phi)
        phi_dot = np.cumsum(theta_dot, axis=-1)
        kinetic = 0.5 * np.einsum('...i,...ij,...j->...', phi_dot, self._d * cos_diff, phi_dot)
        return kinetic + np.sum(self._gh * sin_phi, axis=-1)

    # -- linear-in-parameters form --------------------------------------------------------

    def parameter_names(self) -> Tuple[str, ...]:
        """Names of the entries of :meth:`parameter_vector`, shape (5n,)."""
        n = self.n_joints
        groups = ('m', 'mc', 'J', 'fv', 'fc')
        return tuple(f'{g}{i + 1}' for g in groups for i in range(n))

    def parameter_vector(self) -> np.ndarray:
        """
        Return the dynamic parameters p such that τ = Y p, shape (5n,).

        In order: masses m_i, first moments m_i c_i, inertias about the joints
        J_i = m_i c_i² + I_ci, viscous coefficients, Coulomb levels (n each). The Coulomb
        smoothing velocity is a fixed (known) constant, not a parameter.
        """
        p = self.params
        return np.concatenate([p.masses, p.first_moments, p.joint_inertias,
                               p.viscous, p.coulomb])

    def regressor(self, theta: ArrayLike, theta_dot: ArrayLike,
                  theta_ddot: ArrayLike) -> np.ndarray:
        """
        Return the rigid-body regressor Y with ``inverse_dynamics == Y @ parameter_vector()``.

        The full parameter set is rank deficient: the mass columns are combinations of the
        other columns (m_k only enters through h_i and d_ii, see the module docstring), so at
        most 4n of the 5n parameters are identifiable; :meth:`base_regressor` gives them.
        Least squares with ``Y`` still reproduces the torques exactly (a minimum-norm
        solution differs from the true p only in the null space). The arguments are those of
        :meth:`inverse_dynamics`; Y has shape (..., n, 5n).
        """
        theta = self._joint_array('theta', theta)
        theta_dot = self._joint_array('theta_dot', theta_dot)
        theta_ddot = self._joint_array('theta_ddot', theta_ddot)
        theta, theta_dot, theta_ddot = np.broadcast_arrays(theta, theta_dot, theta_ddot)
        n = self.n_joints
        lengths = self.params.lengths
        g = self.params.gravity
        cos_phi, sin_phi = self._angles(theta)
        cos_diff, sin_diff = self._differences(cos_phi, sin_phi)
        phi_dot = np.cumsum(theta_dot, axis=-1)
        phi_ddot = np.cumsum(theta_ddot, axis=-1)
        # q_ij = cos(φi-φj) φ̈j + sin(φi-φj) φ̇j², the coupling of row i to h_j / l
        q = cos_diff * phi_ddot[..., None, :] + sin_diff * phi_dot[..., None, :] ** 2
        upper = np.triu(np.ones((n, n), dtype=bool), 1)
        # u = H h + diag(φ̈) J + (mass terms of d_ii); H_ij = l_i q_ij (j > i),
        # H_ii = Σ_{j<i} l_j q_ij + g cos φ_i
        big_h = np.where(upper, lengths[:, None] * q, 0.0)
        diag = np.sum(np.where(upper.T, q * lengths[None, :], 0.0), axis=-1) + g * cos_phi
        big_h[..., np.arange(n), np.arange(n)] = diag
        eye = np.eye(n)
        y_inertia = eye * phi_ddot[..., :, None]
        # coefficient of m_k in u_i: l_i² φ̈_i [k > i] + Σ_{j<k} H_ij l_j
        hl = big_h * lengths
        y_mass = np.cumsum(hl, axis=-1) - hl
        y_mass = y_mass + np.where(upper, (lengths ** 2 * phi_ddot)[..., :, None], 0.0)
        rigid = _rcumsum(np.concatenate([y_mass, big_h, y_inertia], axis=-1), axis=-2)
        p = self.params
        y_viscous = eye * theta_dot[..., :, None]
        y_coulomb = eye * np.tanh(theta_dot / p.coulomb_velocity)[..., :, None]
        return np.concatenate([rigid, y_viscous, y_coulomb], axis=-1)

    def base_parameter_names(self) -> Tuple[str, ...]:
        """Names of the entries of :meth:`base_parameter_vector`, shape (4n,)."""
        n = self.n_joints
        return tuple(f'{g}{i + 1}' for g in ('h', 'd', 'fv', 'fc') for i in range(n))

    def base_parameter_vector(self) -> np.ndarray:
        """
        Return the base (identifiable) parameters, shape (4n,).

        In order: h_i = m_i c_i + l_i Σ_{k>i} m_k, d_ii = J_i + l_i² Σ_{k>i} m_k, viscous,
        Coulomb. With gravity all 4n are identifiable from sufficiently exciting data; with
        ``gravity == 0`` h_1 does not enter the dynamics at all (its column is zero).
        """
        p = self.params
        return np.concatenate([self._h, np.diag(self._d), p.viscous, p.coulomb])

    def base_regressor(self, theta: ArrayLike, theta_dot: ArrayLike,
                       theta_ddot: ArrayLike) -> np.ndarray:
        """
        Return Y_b with ``inverse_dynamics == Y_b @ base_parameter_vector()``.

        Returns
        -------
        ndarray, shape (..., n, 4n)

        """
        return self.regressor(theta, theta_dot, theta_ddot)[..., self.n_joints:]


class PDController:
    """
    Joint-space PD servo τ = Kp (θd - θ) + Kd (θ̇d - θ̇), eq. (9) of the paper.

    Parameters
    ----------
    kp, kd : array_like, scalar, shape (n,) or (n, n)
        Gains; a vector means a diagonal gain.
    tau_limit : array_like, shape (n,) or scalar, optional
        Symmetric torque saturation |τ_i| <= tau_limit_i (N m). None (default): no limit.

    """

    def __init__(self, kp, kd, tau_limit=None):
        kp_arr = np.asarray(kp, dtype=float)
        n = kp_arr.shape[0] if kp_arr.ndim >= 1 else None
        if n is None:
            raise ValueError('kp must be a vector or matrix so that n is known')
        self.kp = gain_matrix('kp', kp_arr, n)
        self.kd = gain_matrix('kd', kd, n)
        self.tau_limit = None
        if tau_limit is not None:
            limit = np.broadcast_to(np.asarray(tau_limit, dtype=float), (n,)).copy()
            if not (np.all(np.isfinite(limit)) and np.all(limit > 0.0)):
                raise ValueError(f'tau_limit must be positive and finite, got {tau_limit!r}')
            self.tau_limit = limit

    @classmethod
    def paper(cls) -> 'PDController':
        """
        Return the controller with the paper's gains.

        Kp = diag(32.84, 42.05, 42.31) and Kd = diag(42.44, 0.19, 4.86), no torque limit.
        """
        return cls(np.array([32.84, 42.05, 42.31]), np.array([42.44, 0.19, 4.86]))

    @property
    def n_joints(self) -> int:
        """Count of joints, n."""
        return self.kp.shape[0]

    def torque(self, theta: ArrayLike, theta_dot: ArrayLike, theta_d: ArrayLike,
               theta_d_dot: ArrayLike) -> np.ndarray:
        """
        Return the commanded torque.

        Parameters
        ----------
        theta, theta_dot, theta_d, theta_d_dot : array_like, shape (..., n)
            Measured and desired joint angles and velocities.

        Returns
        -------
        ndarray, shape (..., n)

        """
        tau = pd_torque_coupled(self.kp, self.kd, np.asarray(theta_d) - theta,
                                np.asarray(theta_d_dot) - theta_dot)
        if self.tau_limit is not None:
            tau = np.clip(tau, -self.tau_limit, self.tau_limit)
        return tau

    __call__ = torque

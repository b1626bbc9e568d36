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

All of it is analytic (no finite differences) and vectorised over leading batch axes.

For compiled code, :func:`forward_dynamics_kernel` (allocating) and
:func:`forward_dynamics_into` (caller-owned buffers, for inner loops) are numba versions of
``forward_dynamics`` for one state; they take the constants of
:meth:`PlanarArm.kernel_constants`.
"""

from dataclasses import dataclass
import math
from typing import NamedTuple, Optional, Tuple, Union

from numba import njit
import numpy as np

#: Stability limit |hλ| of every 4-stage 4th-order explicit Runge-Kutta method (classical
#: RK4 and Runge-Kutta-Gill share the stability polynomial 1 + z + z²/2 + z³/6 + z⁴/24) on
#: the negative real axis: the real root of z³ + 4z² + 12z + 24 = 0.
RK4_REAL_STABILITY_LIMIT = 2.785293563405282

#: The same limit on the imaginary axis, 2√2.
RK4_IMAG_STABILITY_LIMIT = 2.0 * np.sqrt(2.0)

MASS_MODELS = ('point', 'rod')

ArrayLike = Union[float, np.ndarray]


def _vector(name: str, value, n: Optional[int] = None, *, positive=False,
            nonnegative=False) -> np.ndarray:
    """Validate a finite 1-D float vector (a scalar is broadcast when ``n`` is given)."""
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 0 and n is not None:
        arr = np.full(n, float(arr))
    if arr.ndim != 1:
        raise ValueError(f'{name} must be a 1-D array, got shape {arr.shape}')
    if n is not None and arr.size != n:
        raise ValueError(f'{name} must have {n} entries, got {arr.size}')
    if not np.all(np.isfinite(arr)):
        raise ValueError(f'{name} must be finite, got {arr}')
    if positive and np.any(arr <= 0.0):
        raise ValueError(f'{name} must be positive, got {arr}')
    if nonnegative and np.any(arr < 0.0):
        raise ValueError(f'{name} must be non-negative, got {arr}')
    return arr


def _gain_matrix(name: str, value, n: int) -> np.ndarray:
    """Return a gain as an (n, n) matrix; a scalar or (n,) vector means a diagonal gain."""
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 0:
        arr = np.full(n, float(arr))
    if arr.ndim == 1:
        if arr.size != n:
            raise ValueError(f'{name} must have {n} diagonal entries, got {arr.size}')
        arr = np.diag(arr)
    if arr.shape != (n, n):
        raise ValueError(f'{name} must be a scalar, shape ({n},) or ({n}, {n}), got {arr.shape}')
    if not np.all(np.isfinite(arr)):
        raise ValueError(f'{name} must be finite')
    return arr


def _rcumsum(a: np.ndarray, axis: int = -1) -> np.ndarray:
    """Reverse cumulative sum, ``out[i] = a[i] + a[i+1] + ...`` (multiplication by Sᵀ)."""
    return np.flip(np.cumsum(np.flip(a, axis), axis=axis), axis)


@dataclass(frozen=True, eq=False)
class ArmParameters:
    """
    Physical parameters of a planar n-link arm.

    Attributes
    ----------
    masses : ndarray, shape (n,)
        Link masses m_i (kg), positive.
    lengths : ndarray, shape (n,)
        Link lengths l_i (m), positive.
    mass_model : {'point', 'rod'}
        ``'point'`` (default): each mass is a point at the distal end of its link, c_i = l_i,
        no inertia about the centre of mass (the paper's Table 1 gives only masses and
        lengths). ``'rod'``: uniform slender rods, c_i = l_i / 2, inertia m_i l_i² / 12 about
        the centre of mass.
    gravity : float
        Gravitational acceleration g (m/s²) along -y; the arm moves in a vertical plane.
    viscous : ndarray, shape (n,)
        Viscous friction coefficients (N m s/rad), default zeros.
    coulomb : ndarray, shape (n,)
        Coulomb friction levels (N m), default zeros. The friction torque is
        ``viscous * θ̇ + coulomb * tanh(θ̇ / coulomb_velocity)``.
    coulomb_velocity : float
        Smoothing velocity (rad/s) of the Coulomb term, positive.

    """

    masses: np.ndarray
    lengths: np.ndarray
    mass_model: str = 'point'
    gravity: float = 9.81
    viscous: Optional[np.ndarray] = None
    coulomb: Optional[np.ndarray] = None
    coulomb_velocity: float = 0.05

    def __post_init__(self):
        masses = _vector('masses', self.masses, positive=True)
        n = masses.size
        if n < 1:
            raise ValueError('masses must have at least one entry (n >= 1)')
        lengths = _vector('lengths', self.lengths, n, positive=True)
        if self.mass_model not in MASS_MODELS:
            raise ValueError(f'mass_model must be one of {MASS_MODELS}, got {self.mass_model!r}')
        gravity = float(self.gravity)
        if not np.isfinite(gravity):
            raise ValueError(f'gravity must be finite, got {self.gravity}')
        viscous = _vector('viscous', 0.0 if self.viscous is None else self.viscous, n,
                          nonnegative=True)
        coulomb = _vector('coulomb', 0.0 if self.coulomb is None else self.coulomb, n,
                          nonnegative=True)
        coulomb_velocity = float(self.coulomb_velocity)
        if not (np.isfinite(coulomb_velocity) and coulomb_velocity > 0.0):
            raise ValueError(f'coulomb_velocity must be positive, got {self.coulomb_velocity}')
        for name, value in (('masses', masses), ('lengths', lengths), ('gravity', gravity),
                            ('viscous', viscous), ('coulomb', coulomb),
                            ('coulomb_velocity', coulomb_velocity)):
            object.__setattr__(self, name, value)

    @classmethod
    def paper(cls, mass_model: str = 'point') -> 'ArmParameters':
        """
        Return the three-link arm of the paper's Table 1 with modest friction.

        Masses (6, 4, 3) kg and lengths (0.2, 0.3, 0.1) m are the paper's. The paper gives no
        friction values; these are plausible for small geared joints, decreasing towards the
        wrist: viscous (0.5, 0.3, 0.1) N m s/rad and Coulomb (0.3, 0.2, 0.1) N m, smoothed
        with ``tanh(θ̇ / 0.05 rad/s)``.
        """
        return cls(masses=np.array([6.0, 4.0, 3.0]), lengths=np.array([0.2, 0.3, 0.1]),
                   mass_model=mass_model, gravity=9.81,
                   viscous=np.array([0.5, 0.3, 0.1]), coulomb=np.array([0.3, 0.2, 0.1]),
                   coulomb_velocity=0.05)

    @property
    def n_joints(self) -> int:
        """Count of links and joints, n."""
        return self.masses.size

    @property
    def com_distances(self) -> np.ndarray:
        """Distance c_i of each link's centre of mass from its joint, shape (n,)."""
        return self.lengths if self.mass_model == 'point' else 0.5 * self.lengths

    @property
    def com_inertias(self) -> np.ndarray:
        """Inertia of each link about its own centre of mass (kg m²), shape (n,)."""
        if self.mass_model == 'point':
            return np.zeros(self.n_joints)
        return self.masses * self.lengths ** 2 / 12.0

    @property
    def first_moments(self) -> np.ndarray:
        """First moments m_i c_i of the links about their joints (kg m), shape (n,)."""
        return self.masses * self.com_distances

    @property
    def joint_inertias(self) -> np.ndarray:
        """Inertias J_i = m_i c_i² + I_ci of the links about their joints, shape (n,)."""
        return self.masses * self.com_distances ** 2 + self.com_inertias

    def without_friction(self) -> 'ArmParameters':
        """Return a copy with zero viscous and Coulomb friction."""
        return ArmParameters(self.masses, self.lengths, self.mass_model, self.gravity,
                             coulomb_velocity=self.coulomb_velocity)


class KernelConstants(NamedTuple):
    """
    Constants of the compiled forward-dynamics kernels, in their argument order.

    Attributes
    ----------
    d : ndarray, shape (n, n)
        The symmetric link constants d_ij of the module docstring (D(φ) = d ∘ cos(φ_i - φ_j)).
    gh : ndarray, shape (n,)
        The gravity moments g h_i.
    viscous, coulomb : ndarray, shape (n,)
        Friction coefficients (:class:`ArmParameters`).
    coulomb_velocity : float
        Coulomb smoothing velocity.

    """

    d: np.ndarray
    gh: np.ndarray
    viscous: np.ndarray
    coulomb: np.ndarray
    coulomb_velocity: float


class PlanarArm:
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
        then θ̈ = S⁻¹ φ̈ (never forms an inverse).

        Parameters
        ----------
        theta, theta_dot, tau : array_like, shape (..., n)
            Joint angles, velocities and applied torques (broadcast together).

        Returns
        -------
        ndarray, shape (..., n)

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
        solution differs from the true p only in the null space).

        Parameters
        ----------
        theta, theta_dot, theta_ddot : array_like, shape (..., n)
            Joint angles, velocities and accelerations (broadcast together).

        Returns
        -------
        ndarray, shape (..., n, 5n)

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

    # -- closed-loop stiffness ------------------------------------------------------------

    def closed_loop_eigenvalues(self, theta: ArrayLike, theta_dot: ArrayLike, kp, kd,
                                theta_d: Optional[ArrayLike] = None,
                                theta_d_dot: Optional[ArrayLike] = None,
                                eps: float = 1e-6) -> np.ndarray:
        """
        Return the eigenvalues of the Jacobian ∂f/∂x of the PD closed loop at a state.

        The closed loop is ẋ = f(x) = [θ̇, M⁻¹(Kp(θd - θ) + Kd(θ̇d - θ̇) - V - G - F)] with
        θd, θ̇d frozen (default: equal to θ, θ̇, i.e. on the reference). The Jacobian is
        taken by central differences with relative step ``eps``.

        Parameters
        ----------
        theta, theta_dot : array_like, shape (..., n)
            States at which to linearise.
        kp, kd : array_like, scalar, shape (n,) or (n, n)
            Proportional and derivative gains (a vector means a diagonal gain).
        theta_d, theta_d_dot : array_like, shape (..., n), optional
            Frozen desired trajectory; default ``theta`` and ``theta_dot``.
        eps : float
            Relative finite-difference step.

        Returns
        -------
        ndarray, shape (..., 2n), complex

        """
        n = self.n_joints
        theta = self._joint_array('theta', theta)
        theta_dot = self._joint_array('theta_dot', theta_dot)
        kp = _gain_matrix('kp', kp, n)
        kd = _gain_matrix('kd', kd, n)
        theta_d = theta if theta_d is None else self._joint_array('theta_d', theta_d)
        theta_d_dot = (theta_dot if theta_d_dot is None
                       else self._joint_array('theta_d_dot', theta_d_dot))
        theta, theta_dot, theta_d, theta_d_dot = np.broadcast_arrays(
            theta, theta_dot, theta_d, theta_d_dot)
        x = np.concatenate([theta, theta_dot], axis=-1)             # (..., 2n)
        step = eps * np.maximum(1.0, np.abs(x))                      # (..., 2n)
        delta = np.eye(2 * n) * step[..., None, :]                   # (..., 2n, 2n) rows
        xs = np.concatenate([x[..., None, :] + delta, x[..., None, :] - delta], axis=-2)
        th, thd = xs[..., :n], xs[..., n:]
        ref = theta_d[..., None, :]
        ref_dot = theta_d_dot[..., None, :]
        tau = (ref - th) @ kp.T + (ref_dot - thd) @ kd.T
        f = np.concatenate([thd, self.forward_dynamics(th, thd, tau)], axis=-1)
        jac_t = (f[..., :2 * n, :] - f[..., 2 * n:, :]) / (2.0 * step[..., :, None])
        return np.linalg.eigvals(np.swapaxes(jac_t, -1, -2))

    def closed_loop_stiffness(self, theta: ArrayLike, theta_dot: ArrayLike, kp, kd,
                              **kwargs) -> Union[float, np.ndarray]:
        """
        Return the largest |λ| of the PD closed-loop Jacobian at a state (1/s).

        See :meth:`closed_loop_eigenvalues` for the arguments. A float for a single state,
        otherwise an array of shape (...).
        """
        lam = np.abs(self.closed_loop_eigenvalues(theta, theta_dot, kp, kd, **kwargs))
        out = lam.max(axis=-1)
        return float(out) if out.ndim == 0 else out

    def stable_step(self, kp, kd, theta: ArrayLike, theta_dot: ArrayLike,
                    safety: float = 0.5, **kwargs) -> float:
        """
        Return the largest Runge-Kutta-Gill step that is stable at all the given states.

        For each eigenvalue λ of the closed-loop Jacobian the limit is r(arg λ) / |λ|, where
        r is the distance from the origin to the boundary of the RK4 stability region along
        the ray through λ (2.785 on the negative real axis); the result is ``safety`` times
        the smallest limit. See :func:`rk4_stability_radius`.

        Parameters
        ----------
        kp, kd : array_like
            PD gains, as for :meth:`closed_loop_eigenvalues`.
        theta, theta_dot : array_like, shape (..., n)
            States (e.g. along a reference trajectory).
        safety : float
            Safety factor in (0, 1]; 0.5 by default, since the linearisation is local and the
            trajectory leaves the sampled states.

        """
        if not 0.0 < safety <= 1.0:
            raise ValueError(f'safety must be in (0, 1], got {safety}')
        lam = self.closed_loop_eigenvalues(theta, theta_dot, kp, kd, **kwargs).ravel()
        lam = lam[np.abs(lam) > 0.0]
        if lam.size == 0:
            return float('inf')
        return float(safety * np.min(rk4_stability_radius(lam) / np.abs(lam)))


@njit(cache=True, nogil=True, inline='always')
def _smooth_sign(x):
    """Return tanh(x) from one ``expm1`` (libm's tanh costs about four times as much)."""
    if x > 20.0:
        return 1.0
    if x < -20.0:
        return -1.0
    e = math.expm1(2.0 * x)
    return e / (e + 2.0)


@njit(cache=True, nogil=True, fastmath={'contract'})
def forward_dynamics_into(theta, theta_dot, tau, d, gh, viscous, coulomb, coulomb_velocity,
                          work, out):
    """
    Write θ̈ of one state into ``out``, allocating nothing: compiled forward dynamics.

    The arithmetic of :meth:`PlanarArm.forward_dynamics` for a single state: builds D(φ)
    and the right-hand side in absolute angles, solves by an LDLᵀ factorisation (D is
    symmetric positive definite; n divisions and no square roots), then θ̈ = S⁻¹ φ̈. It
    agrees with the numpy method to rounding (about 1e-15 relative; fused multiply-adds
    are allowed). A numba function (``nogil``), callable from other compiled code in inner
    loops (integrators, population kernels) with caller-owned buffers. The constants come
    from :meth:`PlanarArm.kernel_constants`::

        forward_dynamics_into(theta, theta_dot, tau, *arm.kernel_constants(), work, out)

    Parameters
    ----------
    theta, theta_dot, tau : ndarray, shape (n,)
        Joint angles (rad), velocities (rad/s) and applied torques (N m).
    d : ndarray, shape (n, n)
        The link constants d_ij (see the module docstring).
    gh : ndarray, shape (n,)
        g h_i, the gravity moments.
    viscous, coulomb : ndarray, shape (n,)
        Friction coefficients.
    coulomb_velocity : float
        Coulomb smoothing velocity.
    work : ndarray, shape (n + 3, n)
        Scratch space, overwritten.
    out : ndarray, shape (n,)
        Receives θ̈ (rad/s²). Must not alias the inputs.

    """
    n = theta.shape[0]
    a = work[:n]                # D(φ), then L (below the diagonal) and p (on it)
    c = work[n]                 # cos φ
    s = work[n + 1]             # sin φ
    phi_dot = work[n + 2]
    acc, acc_dot = 0.0, 0.0
    for i in range(n):
        acc += theta[i]
        acc_dot += theta_dot[i]
        c[i] = math.cos(acc)
        s[i] = math.sin(acc)
        phi_dot[i] = acc_dot
    # q = τ - F in out, then (in place, ascending) the right-hand side S⁻ᵀ q - w - g h cos φ
    for i in range(n):
        out[i] = (tau[i] - viscous[i] * theta_dot[i]
                  - coulomb[i] * _smooth_sign(theta_dot[i] / coulomb_velocity))
    for i in range(n):
        r = out[i] - gh[i] * c[i]
        if i + 1 < n:
            r -= out[i + 1]
        for j in range(n):
            r -= d[i, j] * (s[i] * c[j] - c[i] * s[j]) * phi_dot[j] * phi_dot[j]
            a[i, j] = d[i, j] * (c[i] * c[j] + s[i] * s[j])
        out[i] = r
    # LDLᵀ by columns: a[i, j] <- L_ij (i > j), a[j, j] <- p_j, and 1/p_j in the c row,
    # free by now
    inv_p = c
    for j in range(n):
        for i in range(j, n):
            v = a[i, j]
            for k in range(j):
                v -= a[i, k] * a[j, k] * a[k, k]        # L_ik L_jk p_k
            a[i, j] = v
        p = a[j, j]
        inv = 1.0 / p if p > 0.0 else math.nan
        inv_p[j] = inv
        for i in range(j + 1, n):
            a[i, j] *= inv
    for i in range(n):                                  # L z = rhs
        v = out[i]
        for k in range(i):
            v -= a[i, k] * out[k]
        out[i] = v
    for i in range(n - 1, -1, -1):                      # Lᵀ φ̈ = z / p
        v = out[i] * inv_p[i]
        for k in range(i + 1, n):
            v -= a[k, i] * out[k]
        out[i] = v
    # θ̈ = S⁻¹ φ̈ (descending, in place)
    for i in range(n - 1, 0, -1):
        out[i] -= out[i - 1]


@njit(cache=True, nogil=True)
def forward_dynamics_kernel(theta, theta_dot, tau, d, gh, viscous, coulomb,
                            coulomb_velocity):
    """
    Return θ̈ of one state, shape (n,): compiled forward dynamics.

    :func:`forward_dynamics_into` with freshly allocated buffers, for compiled code that
    is not in a hot loop and for use from Python::

        theta_ddot = forward_dynamics_kernel(theta, theta_dot, tau, *arm.kernel_constants())

    The arguments are those of :func:`forward_dynamics_into` without ``work`` and ``out``.
    """
    n = theta.shape[0]
    out = np.empty(n)
    forward_dynamics_into(theta, theta_dot, tau, d, gh, viscous, coulomb, coulomb_velocity,
                          np.empty((n + 3, n)), out)
    return out


#: Former private name of :func:`forward_dynamics_kernel`, kept for existing importers.
_forward_kernel = forward_dynamics_kernel


def rk4_stability_radius(lam: ArrayLike) -> np.ndarray:
    """
    Return the distance r to the RK4 stability boundary along the ray through each λ.

    ``|R(r λ/|λ|)| = 1`` with R(z) = 1 + z + z²/2 + z³/6 + z⁴/24, the stability polynomial of
    classical RK4 and of Runge-Kutta-Gill. For λ in the open left half-plane this is the
    first exit from the stability region (2.785 on the negative real axis). Eigenvalues with
    Re λ >= 0 belong to undamped or growing modes that no step size stabilises; they get
    the imaginary-axis value 2√2 so that the step still resolves their time scale.

    Parameters
    ----------
    lam : array_like, complex, shape (...)
        Non-zero eigenvalues.

    Returns
    -------
    ndarray, shape (...)

    """
    lam = np.asarray(lam, dtype=complex)
    u = lam / np.abs(lam)
    radius = np.full(u.shape, RK4_IMAG_STABILITY_LIMIT)
    left = u.real < -1e-12
    if np.any(left):
        ul = u[left]

        def unstable(r):
            z = r * ul
            return np.abs(1.0 + z * (1.0 + z * (0.5 + z * (1.0 / 6.0 + z / 24.0)))) > 1.0

        # the boundary lies within |z| < 3 in the left half-plane; scan, then bisect
        grid = np.linspace(0.0, 3.0, 601)[1:]
        exits = np.array([unstable(r) for r in grid])               # (601-1, L)
        first = np.where(exits.any(axis=0), exits.argmax(axis=0), grid.size - 1)
        hi = grid[first]
        lo = np.where(first > 0, grid[np.maximum(first - 1, 0)], 0.0)
        for _ in range(50):
            mid = 0.5 * (lo + hi)
            bad = unstable(mid)
            hi = np.where(bad, mid, hi)
            lo = np.where(bad, lo, mid)
        radius[left] = lo
    return radius


def max_stable_rkg_step(arm: PlanarArm, kp, kd, reference, duration: float,
                        t0: float = 0.0, samples: int = 200, safety: float = 0.5) -> float:
    """
    Estimate the largest stable Runge-Kutta-Gill step along a reference trajectory.

    Samples ``samples`` states on the reference (θ = θd(t), θ̇ = θ̇d(t)) over
    ``[t0, t0 + duration]`` and returns :meth:`PlanarArm.stable_step` over all of them. A
    sampling interval dt larger than this needs ``ceil(dt / h)`` RKG sub-steps per sample.

    Parameters
    ----------
    arm : PlanarArm
        The plant.
    kp, kd : array_like
        PD gains (a vector means a diagonal gain).
    reference : Reference
        Anything with ``evaluate(t) -> (theta_d, theta_d_dot)``.
    duration : float
        Time span to sample (s), positive.
    t0 : float
        Start time.
    samples : int
        Number of states.
    safety : float
        Safety factor, 0.5 by default.

    Returns
    -------
    float
        Step h in seconds.

    """
    if not (np.isfinite(duration) and duration > 0.0):
        raise ValueError(f'duration must be positive, got {duration}')
    if samples < 1:
        raise ValueError(f'samples must be >= 1, got {samples}')
    t = t0 + np.linspace(0.0, duration, int(samples))
    theta, theta_dot = reference.evaluate(t)
    return arm.stable_step(kp, kd, theta, theta_dot, safety=safety)


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
        self.kp = _gain_matrix('kp', kp_arr, n)
        self.kd = _gain_matrix('kd', kd, n)
        self.tau_limit = (None if tau_limit is None
                          else _vector('tau_limit', tau_limit, n, positive=True))

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
        tau = ((np.asarray(theta_d) - theta) @ self.kp.T
               + (np.asarray(theta_d_dot) - theta_dot) @ self.kd.T)
        if self.tau_limit is not None:
            tau = np.clip(tau, -self.tau_limit, self.tau_limit)
        return tau

    __call__ = torque

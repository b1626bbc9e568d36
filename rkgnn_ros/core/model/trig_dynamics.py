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
The arm model of the trigonometric basis: M, V, G, F from coefficients, and its regressor.

With M(θ) = Σ_f W_f φ_f(θ) (W_f symmetric, one coefficient per entry and feature of
:class:`~rkgnn_ros.core.model.trig.TrigBasis`, or the entries' coefficients a fixed linear
map of fewer, for the tied planar basis), U(θ) = Σ_f u_f φ_f(θ) and the friction
F = f_v θ̇ + f_c tanh(θ̇ / v_c), Lagrange's equations

    τ = d/dt (M θ̇) - ½ ∂(θ̇ᵀ M θ̇)/∂θ + ∇U + F = M θ̈ + V(θ, θ̇) + G(θ) + F(θ̇)

are linear in every coefficient: τ = Y(θ, θ̇, θ̈) w (:func:`regressor`). The coefficient of
feature f in entry (a, b) acts on joint k as

    δ_ka (φ θ̈_b + φ̇ θ̇_b) + δ_kb (φ θ̈_a + φ̇ θ̇_a) - θ̇_a θ̇_b ∂_k φ      (a ≠ b)
    δ_ka (φ θ̈_a + φ̇ θ̇_a) - ½ θ̇_a² ∂_k φ                               (a = b)

so V comes from the Christoffel symbols of the same M (without friction the model
conserves energy wherever M is above its floor), and G = ∇U is conservative by
construction.

:class:`TrigDynamics` is the model those coefficients make: inverse and forward dynamics,
its terms, RKG rollouts in open or closed loop. Fitting the coefficients is
:class:`rkgnn_ros.core.fitting.linear.LinearDynamics`, a TrigDynamics that learns them; it
also sets the floor under M that :meth:`TrigDynamics.mass_matrix` guards.
"""

import copy
from typing import List, NamedTuple, Optional

import numpy as np

from .trig import TrigBasis
from ..integration.inputs import stage_inputs
from ..integration.rkg import choose_substeps, rkg_step
from ..servo_law import pd_torque

__all__ = ['Layout', 'MAX_SUBSTEPS', 'regressor', 'TrigDynamics', 'unpack_mass']

#: Most RKG steps per interval a rollout takes on its own (the integration.substeps bound of
#: a model file): a model stiffer than that is rolled out at it and diverges, which its
#: caller sees (NaN rows); the stiffness of a model fitted to garbage (10^10 1/s) asked for
#: 5 * 10^7 and an allocation of 37 GiB.
MAX_SUBSTEPS = 64


class Layout(NamedTuple):
    """Slices of the coefficient vector w (and the controller's gains in case 3)."""

    mass: slice
    potential: slice
    viscous: slice
    coulomb: slice
    kp: Optional[slice]
    kd: Optional[slice]
    size: int
    ki: Optional[slice] = None
    bias: Optional[slice] = None

    @classmethod
    def of(cls, basis: TrigBasis, controller: bool = False,
           integral: bool = False) -> 'Layout':
        """Return the layout [M entries | U | f_v | f_c (| Kp | Kd (| Ki | c))] for a basis."""
        n = basis.n_joints
        a = basis.n_mass_coefficients
        b = a + basis.n_potential_coefficients
        kp = slice(b + 2 * n, b + 3 * n) if controller else None
        kd = slice(b + 3 * n, b + 4 * n) if controller else None
        integral = controller and integral
        ki = slice(b + 4 * n, b + 5 * n) if integral else None
        bias = slice(b + 5 * n, b + 6 * n) if integral else None
        return cls(slice(0, a), slice(a, b), slice(b, b + n), slice(b + n, b + 2 * n), kp, kd,
                   b + (6 if integral else 4 if controller else 2) * n, ki, bias)

    def groups(self, basis: TrigBasis) -> List[slice]:
        """Return the coefficient groups the ridge weight is scaled per."""
        out, start = [], 0
        if basis.mass_tie is not None:
            out.append(self.mass)
        else:
            for ix in basis.mass_index:
                out.append(slice(start, start + ix.size))
                start += ix.size
        out += [self.potential, self.viscous, self.coulomb]
        out += [s for s in (self.kp, self.kd, self.ki, self.bias) if s is not None]
        return out


def regressor(basis: TrigBasis, theta, theta_dot, theta_ddot, coulomb_velocity: float,
              error=None, error_rate=None, error_integral=None) -> np.ndarray:
    """
    Return Y with ``Y @ w`` the inverse dynamics M θ̈ + V + G + F of coefficients w.

    Parameters
    ----------
    basis : TrigBasis
        Features of M and U.
    theta, theta_dot, theta_ddot : array_like, shape (N, n)
        Joint angles, velocities and accelerations.
    coulomb_velocity : float
        v_c of the smoothed Coulomb friction.
    error, error_rate : array_like, shape (N, n), optional
        θd - θ and θ̇d - θ̇: appends the controller's columns -diag(e), -diag(ė), so that
        ``Y @ [w, kp, kd]`` is the dynamics minus the PD torque (case 3).
    error_integral : array_like, shape (N, n), optional
        ∫(θd - θ) dt (with ``error``): appends -diag(∫e) and -I, so that
        ``Y @ [w, kp, kd, ki, c]`` is the dynamics minus the PID torque with its constant.

    Returns
    -------
    ndarray, shape (N, n, P)
        Columns in the order of :class:`Layout`.

    """
    theta = np.atleast_2d(np.asarray(theta, dtype=float))
    qd = np.atleast_2d(np.asarray(theta_dot, dtype=float))
    qdd = np.atleast_2d(np.asarray(theta_ddot, dtype=float))
    n_samples, n = theta.shape
    if n != basis.n_joints:
        raise ValueError(f'theta has {n} joints, the basis {basis.n_joints}')
    controller = error is not None
    lay = Layout.of(basis, controller, error_integral is not None)
    out = np.zeros((n_samples, n, lay.size))
    phi, grad = basis.values(theta, gradient=True)              # (N, F), (N, F, n)
    phi_dot = np.einsum('tfk,tk->tf', grad, qd)
    tie = basis.mass_tie
    mass = out if tie is None else np.zeros((n_samples, n, basis.n_entry_features))
    start = 0
    for (a, b), ix in zip(basis.mass_entries, basis.mass_index):
        cols = slice(start, start + ix.size)
        p, pd, g = phi[:, ix], phi_dot[:, ix], grad[:, ix, :]
        mass[:, a, cols] += p * qdd[:, b, None] + pd * qd[:, b, None]
        if a != b:
            mass[:, b, cols] += p * qdd[:, a, None] + pd * qd[:, a, None]
            q = qd[:, a] * qd[:, b]
        else:
            q = 0.5 * qd[:, a] ** 2
        mass[:, :, cols] -= q[:, None, None] * np.swapaxes(g, 1, 2)
        start += ix.size
    if tie is not None:
        out[:, :, lay.mass] = mass @ tie
    out[:, :, lay.potential] = np.swapaxes(grad[:, basis.potential_index, :], 1, 2)
    joints = np.arange(n)
    out[:, joints, lay.viscous.start + joints] = qd
    out[:, joints, lay.coulomb.start + joints] = np.tanh(qd / coulomb_velocity)
    if controller:
        out[:, joints, lay.kp.start + joints] = -np.asarray(error, dtype=float)
        out[:, joints, lay.kd.start + joints] = -np.asarray(error_rate, dtype=float)
    if lay.ki is not None:
        out[:, joints, lay.ki.start + joints] = -np.asarray(error_integral, dtype=float)
        out[:, joints, lay.bias.start + joints] = -1.0
    return out


def unpack_mass(basis: TrigBasis, coefficients) -> np.ndarray:
    """Return the symmetric coefficient matrices W_f of M, shape (F, n, n)."""
    n = basis.n_joints
    if basis.mass_tie is not None:
        coefficients = basis.mass_tie @ np.asarray(coefficients, dtype=float)
    w = np.zeros((basis.n_features, n, n))
    start = 0
    for (a, b), ix in zip(basis.mass_entries, basis.mass_index):
        w[ix, a, b] = coefficients[start:start + ix.size]
        w[ix, b, a] = coefficients[start:start + ix.size]
        start += ix.size
    return w


class TrigDynamics:
    """
    M, V, G, F of an n-joint arm in the trigonometric basis, from given coefficients.

    The model methods refuse until coefficients are set (by a fit, or
    ``LinearDynamics.from_coefficients``).

    Parameters
    ----------
    basis : TrigBasis or int
        The basis, or the number of joints for ``TrigBasis(n)`` (spatial, serial chain).
    coulomb_velocity : float
        v_c of the smoothed Coulomb friction (rad/s).

    Attributes
    ----------
    coef_ : ndarray, shape (P,)
        [M entries | U | f_v | f_c] in the order of :class:`Layout`; None before a fit.
    viscous_, coulomb_ : ndarray, shape (n,)
        Friction coefficients.
    kp_, kd_ : ndarray, shape (n,) or None
        The known or identified PD gains of the arm's controller (None in case 'torque').
    ki_, bias_ : ndarray, shape (n,) or None
        Case 3 with an integral: the identified Ki and the constant c of the controller
        torque Kp e + Kd ė + Ki ∫e + c, ∫e from the start of the fitted data (else None).
    inertia_scale_, min_eigenvalue_ : ndarray, shape (n,) or None; float
        S = diag(inertia_scale_) and ε of the floor λ_min(S M S) >= ε that
        :meth:`mass_matrix` guards (None: no floor).

    """

    def __init__(self, basis, coulomb_velocity: float = 0.05):
        self.basis = basis if isinstance(basis, TrigBasis) else TrigBasis(int(basis))
        if not (np.isfinite(coulomb_velocity) and coulomb_velocity > 0.0):
            raise ValueError(f'coulomb_velocity must be positive, got {coulomb_velocity}')
        self.coulomb_velocity = float(coulomb_velocity)
        self.coef_ = None

    @property
    def n_joints(self) -> int:
        """Return the number of joints n."""
        return self.basis.n_joints

    def _set(self, coef, lay, case, kp, kd):
        """Take the coefficients ``coef`` (:class:`Layout` ``lay``) of a model of ``case``."""
        n = self.n_joints
        self.case_, self.layout_ = case, lay
        self.coef_ = coef[:lay.kp.start] if lay.kp is not None else coef.copy()
        self._w_mass = unpack_mass(self.basis, coef[lay.mass])
        self._w_pot = np.zeros(self.basis.n_features)
        self._w_pot[self.basis.potential_index] = coef[lay.potential]
        self.viscous_ = coef[lay.viscous].copy()
        self.coulomb_ = coef[lay.coulomb].copy()
        self.ki_ = self.bias_ = None
        if lay.ki is not None:
            self.ki_, self.bias_ = coef[lay.ki].copy(), coef[lay.bias].copy()
        if lay.kp is not None:
            self.kp_, self.kd_ = coef[lay.kp].copy(), coef[lay.kd].copy()
        elif case == 'pd_gains':
            self.kp_ = np.broadcast_to(np.asarray(kp, dtype=float), (n,)).copy()
            self.kd_ = np.broadcast_to(np.asarray(kd, dtype=float), (n,)).copy()
        else:
            self.kp_ = self.kd_ = None
        self._full_coef = coef.copy()

    @property
    def full_coefficients(self) -> np.ndarray:
        """Return every coefficient in :class:`Layout` order, the case-3 gains included."""
        self._check()
        return self._full_coef.copy()

    def _check(self):
        if self.coef_ is None:
            raise RuntimeError(f'{type(self).__name__} is not fitted yet: call fit() first')

    def _theta(self, theta):
        theta = np.asarray(theta, dtype=float)
        if theta.ndim == 0 or theta.shape[-1] != self.n_joints:
            raise ValueError(f'theta must have shape (..., {self.n_joints}), got {theta.shape}')
        return theta

    def raw_mass_matrix(self, theta) -> np.ndarray:
        """Return M(θ) = Σ_f W_f φ_f(θ) as fitted (no floor), shape (..., n, n)."""
        self._check()
        phi = self.basis.values(self._theta(theta))
        return np.einsum('...f,fij->...ij', phi, self._w_mass)

    def mass_matrix(self, theta) -> np.ndarray:
        """
        Return the model's M(θ), raised to the floor, shape (..., n, n).

        M + S⁻¹ max(0, ε - λ_min(S M S)) S⁻¹ with M = :meth:`raw_mass_matrix`: symmetric
        positive definite for every θ by construction. The fit enforces the floor on the
        joint range (:mod:`rkgnn_ros.core.fitting.linear`), so this equals the raw M
        wherever that held (everywhere when a fit's ``certificate_`` is certified);
        elsewhere it is the last guard, and V (the raw M's Christoffel symbols) no longer
        matches it exactly.
        """
        return self._lift(self.raw_mass_matrix(theta))

    def potential(self, theta) -> np.ndarray:
        """Return U(θ) (its constant is not identifiable; 0 here), shape (...)."""
        self._check()
        return self.basis.values(self._theta(theta)) @ self._w_pot

    def gravity_terms(self, theta) -> np.ndarray:
        """Return G(θ) = ∇U, shape (..., n)."""
        self._check()
        _, grad = self.basis.values(self._theta(theta), gradient=True)
        return np.einsum('...fk,f->...k', grad, self._w_pot)

    def _terms(self, theta, theta_dot):
        """Return M, V, G at states of shape (..., n), from one feature evaluation."""
        phi, grad = self.basis.values(theta, gradient=True)
        m = np.einsum('...f,fij->...ij', phi, self._w_mass)
        dm = np.einsum('...fk,fij->...kij', grad, self._w_mass)       # ∂_k M
        m_dot = np.einsum('...kij,...k->...ij', dm, theta_dot)
        v = (np.einsum('...ij,...j->...i', m_dot, theta_dot)
             - 0.5 * np.einsum('...kij,...i,...j->...k', dm, theta_dot, theta_dot))
        g = np.einsum('...fk,f->...k', grad, self._w_pot)
        return m, v, g

    def velocity_terms(self, theta, theta_dot) -> np.ndarray:
        """Return V(θ, θ̇) = Ṁ θ̇ - ½ ∂(θ̇ᵀMθ̇)/∂θ, shape (..., n)."""
        self._check()
        theta, theta_dot = np.broadcast_arrays(self._theta(theta), self._theta(theta_dot))
        return self._terms(theta, theta_dot)[1]

    def friction_terms(self, theta_dot) -> np.ndarray:
        """Return F(θ̇) = f_v θ̇ + f_c tanh(θ̇ / v_c), shape (..., n)."""
        self._check()
        qd = self._theta(theta_dot)
        return self.viscous_ * qd + self.coulomb_ * np.tanh(qd / self.coulomb_velocity)

    def inverse_dynamics(self, theta, theta_dot, theta_ddot) -> np.ndarray:
        """Return τ = M θ̈ + V + G + F (M floored, as :meth:`mass_matrix`), shape (..., n)."""
        self._check()
        theta, theta_dot, theta_ddot = np.broadcast_arrays(
            self._theta(theta), self._theta(theta_dot), self._theta(theta_ddot))
        m, v, g = self._terms(theta, theta_dot)
        return (np.einsum('...ij,...j->...i', self._lift(m), theta_ddot) + v + g
                + self.friction_terms(theta_dot))

    def _lift(self, m):
        """Raise M (..., n, n) to the floor (see :meth:`mass_matrix`)."""
        if self.inertia_scale_ is None:
            return m
        s = self.inertia_scale_
        lam = np.linalg.eigvalsh(m * np.outer(s, s))[..., 0]
        lift = np.maximum(0.0, self.min_eigenvalue_ - lam)
        return m + lift[..., None, None] * np.diag(1.0 / s ** 2)

    def forward_dynamics(self, theta, theta_dot, tau) -> np.ndarray:
        """Return θ̈ = M⁻¹ (τ - V - G - F) with the floored M, shape (..., n)."""
        self._check()
        theta, theta_dot, tau = np.broadcast_arrays(
            self._theta(theta), self._theta(theta_dot), self._theta(tau))
        m, v, g = self._terms(theta, theta_dot)
        m = self._lift(m)
        rhs = tau - v - g - self.friction_terms(theta_dot)
        return np.linalg.solve(m, rhs[..., None])[..., 0]

    def controller_torque(self, theta, theta_dot, theta_d, theta_d_dot) -> np.ndarray:
        """Return Kp (θd - θ) + Kd (θ̇d - θ̇) with the known or identified gains."""
        self._check()
        if self.kp_ is None:
            raise ValueError("case 'torque' has no controller: pass the torque")
        return pd_torque(self.kp_, self.kd_, np.asarray(theta_d) - theta,
                         np.asarray(theta_d_dot) - theta_dot)

    def scaled(self, factor: float) -> 'TrigDynamics':
        """
        Return a copy with M, V, G, F (and the gains) multiplied by ``factor``.

        Case 3 fixes the scale by the mean Kp; ``model.scaled(true_mean_kp /
        model.kp_.mean())`` is the physical model once that one number is known.
        """
        self._check()
        out = copy.copy(self)
        out._set(self._full_coef * factor, self.layout_, self.case_,
                 None if self.kp_ is None else self.kp_ * factor,
                 None if self.kd_ is None else self.kd_ * factor)
        if self.inertia_scale_ is not None:
            out.inertia_scale_ = self.inertia_scale_ / np.sqrt(factor)
        return out

    def stiffness(self, theta) -> float:
        """Return the largest |eigenvalue| of the linearised closed loop (or arm) at θ."""
        self._check()
        n = self.n_joints
        m = self.mass_matrix(self._theta(theta))
        damp = np.diag(self.viscous_ + self.coulomb_ / self.coulomb_velocity)
        spring = np.zeros((n, n))
        if self.kp_ is not None:
            damp = damp + np.diag(self.kd_)
            spring = np.diag(self.kp_)
        jac = np.block([[np.zeros((n, n)), np.eye(n)],
                        [-np.linalg.solve(m, spring), -np.linalg.solve(m, damp)]])
        return float(np.max(np.abs(np.linalg.eigvals(jac))))

    def simulate(self, x0, t, tau=None, reference=None, theta_d=None, theta_d_dot=None,
                 substeps: Optional[int] = None) -> np.ndarray:
        """
        Roll the model out with Runge-Kutta-Gill from ``x0`` over the uniform times ``t``.

        Parameters
        ----------
        x0 : array_like, shape (2n,)
            Start state [θ, θ̇].
        t : array_like, shape (N,)
            Uniform output times.
        tau : array_like, shape (N, n), optional
            Open loop: torque samples, linear between samples.
        reference : object, optional
            Closed loop (known or identified gains): ``evaluate(times) -> (θd, θ̇d)``.
        theta_d, theta_d_dot : array_like, shape (N, n), optional
            Closed loop: desired samples instead of ``reference``.
        substeps : int, optional
            RKG steps per interval; default from the stiffness at ``x0`` (half the
            stability limit), at most :data:`MAX_SUBSTEPS`.

        Returns
        -------
        ndarray, shape (N, 2n)
            States; rows after a divergence are NaN.

        """
        self._check()
        n = self.n_joints
        t = np.asarray(t, dtype=float)
        x = np.asarray(x0, dtype=float).copy()
        if x.shape != (2 * n,):
            raise ValueError(f'x0 must have shape ({2 * n},), got {x.shape}')
        dt = (t[-1] - t[0]) / (t.size - 1)
        closed = tau is None
        if closed and self.kp_ is None:
            raise ValueError('pass tau (open loop) or fit a case with a controller')
        if substeps is None:
            stiffness = self.stiffness(x[:n]) if np.all(np.isfinite(x)) else np.inf
            substeps = (MAX_SUBSTEPS if not np.isfinite(stiffness)
                        else min(MAX_SUBSTEPS, choose_substeps(dt, stiffness)))
        u = stage_inputs('pd_gains' if closed else 'torque', t, substeps, tau, theta_d,
                         theta_d_dot, reference, 'linear')

        def f(state, ui):
            theta, theta_dot = state[:n], state[n:]
            if closed:
                torque = self.controller_torque(theta, theta_dot, ui[:n], ui[n:])
            else:
                torque = ui
            return np.concatenate([theta_dot, self.forward_dynamics(theta, theta_dot,
                                                                    torque)])

        out = np.full((t.size, 2 * n), np.nan)
        out[0] = x
        h = dt / substeps
        with np.errstate(all='ignore'):
            for k in range(t.size - 1):
                try:
                    for s in range(substeps):
                        x = rkg_step(f, x, h, u[k, s, 0], u[k, s, 1], u[k, s, 2])
                except np.linalg.LinAlgError:        # a non-finite state reached M
                    break
                if not np.all(np.isfinite(x)) or np.abs(x).max() > 1e6:
                    break
                out[k + 1] = x
        return out

    def energy(self, theta, theta_dot) -> np.ndarray:
        """Return ½ θ̇ᵀ M θ̇ + U with the raw M (U's constant taken as 0), shape (...)."""
        m = self.raw_mass_matrix(theta)
        return (0.5 * np.einsum('...i,...ij,...j->...', theta_dot, m, theta_dot)
                + self.potential(theta))

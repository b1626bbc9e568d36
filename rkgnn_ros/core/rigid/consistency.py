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
Physically consistent inertial parameters: the log-Cholesky parametrisation.

A body's ten parameters π = (m, h = m c, Ī about its frame's origin) are realizable by a
mass distribution exactly when its pseudo-inertia

    J = [[Σ, h], [hᵀ, m]],   Σ = ½ tr(Ī) 1 − Ī   (the second moment of the mass)

is positive semidefinite (Wensing, Kim and Slotine, 2017): that holds the triangle
inequalities of the principal moments and a positive mass at once. Rucker and Wensing
(2022) write every positive definite J as U Uᵀ with

    U = e^α [[e^d1, s12, s13, t1], [0, e^d2, s23, t2], [0, 0, e^d3, t3], [0, 0, 0, 1]],

ten unconstrained numbers φ = (α, d1, d2, d3, s12, s23, s13, t1, t2, t3) per body (α:
half the log mass; t: the centre of mass, m; d, s: the mass's spread, m). Every φ gives a
realizable body and every strictly realizable body has one φ, so a fit over φ cannot leave
the feasible set and needs no constraint: an LMI or SDP solver, or a projection after least
squares (which changes the fitted torque where the data cared), is not needed. Each link's
inertia is then positive definite, so M(θ) = Σ Jᵢᵀ Iᵢ Jᵢ is positive definite everywhere
and a rollout cannot meet a singular M.

:func:`parameters` maps φ to π with its Jacobian (π is quadratic in U), :func:`coordinates`
maps a realizable π back (for the URDF's prior; a body that is not strictly realizable is
first moved just inside), :func:`realizable` checks π.
"""

import numpy as np

__all__ = ['coordinates', 'parameters', 'pseudo_inertia', 'realizable']

#: The smallest eigenvalue :func:`coordinates` gives J, as a share of its largest.
INSIDE = 1e-6

# indices of φ within a body's ten
_ALPHA, _D, _S, _T = 0, slice(1, 4), slice(4, 7), slice(7, 10)
# (row, column) of s12, s23, s13 in U
_S_AT = ((0, 1), (1, 2), (0, 2))


def _u(phi: np.ndarray) -> np.ndarray:
    """Return U (B, 4, 4) of φ (B, 10)."""
    b = phi.shape[0]
    u = np.zeros((b, 4, 4))
    e = np.exp(phi[:, _D])
    for k in range(3):
        u[:, k, k] = e[:, k]
        u[:, k, 3] = phi[:, 7 + k]
    for k, (r, c) in enumerate(_S_AT):
        u[:, r, c] = phi[:, 4 + k]
    u[:, 3, 3] = 1.0
    return u * np.exp(phi[:, _ALPHA])[:, None, None]


def _from_j(j: np.ndarray) -> np.ndarray:
    """Return π (..., 10) of pseudo-inertias J (..., 4, 4)."""
    sigma = j[..., :3, :3]
    trace = np.trace(sigma, axis1=-2, axis2=-1)
    out = np.empty(j.shape[:-2] + (10,))
    out[..., 0] = j[..., 3, 3]
    out[..., 1:4] = j[..., :3, 3]
    # Ī = tr(Σ) 1 − Σ
    out[..., 4] = trace - sigma[..., 0, 0]
    out[..., 5] = trace - sigma[..., 1, 1]
    out[..., 6] = trace - sigma[..., 2, 2]
    out[..., 7] = -sigma[..., 0, 1]
    out[..., 8] = -sigma[..., 0, 2]
    out[..., 9] = -sigma[..., 1, 2]
    return out


def pseudo_inertia(pi) -> np.ndarray:
    """Return J (B, 4, 4) of body parameters ``pi`` (B, 10) (or (10,): (4, 4))."""
    pi = np.asarray(pi, dtype=float)
    one = pi.ndim == 1
    pi = pi.reshape(-1, 10)
    inertia = np.empty((pi.shape[0], 3, 3))
    inertia[:, 0, 0], inertia[:, 1, 1], inertia[:, 2, 2] = pi[:, 4], pi[:, 5], pi[:, 6]
    inertia[:, 0, 1] = inertia[:, 1, 0] = pi[:, 7]
    inertia[:, 0, 2] = inertia[:, 2, 0] = pi[:, 8]
    inertia[:, 1, 2] = inertia[:, 2, 1] = pi[:, 9]
    trace = np.trace(inertia, axis1=1, axis2=2)
    j = np.zeros((pi.shape[0], 4, 4))
    j[:, :3, :3] = 0.5 * trace[:, None, None] * np.eye(3) - inertia
    j[:, :3, 3] = j[:, 3, :3] = pi[:, 1:4]
    j[:, 3, 3] = pi[:, 0]
    return j[0] if one else j


def realizable(pi, tolerance: float = 0.0) -> np.ndarray:
    """Return per body whether J ⪰ −tolerance · max|J| (bodies (B, 10) -> (B,) bool)."""
    j = pseudo_inertia(np.asarray(pi, dtype=float).reshape(-1, 10))
    eig = np.linalg.eigvalsh(j)
    return eig[:, 0] >= -tolerance * np.maximum(np.abs(eig).max(axis=1), 1e-300)


def parameters(phi, jacobian: bool = False):
    """
    Return π (B, 10) of log-Cholesky coordinates φ (B, 10), and dπ/dφ (B, 10, 10).

    The Jacobian's [b, i, k] is ∂π_i / ∂φ_k of body b (bodies are independent).
    """
    phi = np.asarray(phi, dtype=float).reshape(-1, 10)
    u = _u(phi)
    pi = _from_j(u @ np.swapaxes(u, 1, 2))
    if not jacobian:
        return pi
    b = phi.shape[0]
    du = np.zeros((b, 10, 4, 4))
    du[:, _ALPHA] = u
    scale = np.exp(phi[:, _ALPHA])
    for k in range(3):
        du[:, 1 + k, k, k] = u[:, k, k]
        du[:, 7 + k, k, 3] = scale
    for k, (r, c) in enumerate(_S_AT):
        du[:, 4 + k, r, c] = scale
    # dJ = dU Uᵀ + U dUᵀ
    prod = du @ np.swapaxes(u, 1, 2)[:, None]
    dj = prod + np.swapaxes(prod, 2, 3)
    return pi, np.swapaxes(_from_j(dj), 1, 2)


def coordinates(pi) -> np.ndarray:
    """
    Return φ (B, 10) of body parameters ``pi`` (B, 10).

    A body whose J is not positive definite (a point mass, a massless link, an infeasible
    guess) is first moved inside: J's eigenvalues are raised to :data:`INSIDE` times the
    largest (a body with no mass at all becomes a small sphere of 1 g at its origin).
    """
    j = pseudo_inertia(np.asarray(pi, dtype=float).reshape(-1, 10))
    out = np.empty((j.shape[0], 10))
    flip = np.eye(4)[::-1]
    for b in range(j.shape[0]):
        w, v = np.linalg.eigh(j[b])
        top = max(float(w[-1]), 1e-3 * 1e-4)
        floor = INSIDE * top
        if w[0] < floor or not np.all(np.isfinite(w)):
            if not np.all(np.isfinite(w)) or w[-1] <= 0.0:
                w, v = np.array([1e-7, 1e-7, 1e-7, 1e-3]), np.eye(4)
            else:
                w = np.maximum(w, floor)
        jb = (v * w) @ v.T
        # J = U Uᵀ with U upper triangular: the lower Cholesky factor of the flipped J
        low = np.linalg.cholesky(flip @ jb @ flip)
        u = flip @ low @ flip
        alpha = np.log(u[3, 3])
        un = u / u[3, 3]
        out[b, 0] = alpha
        out[b, 1:4] = np.log(np.diag(un)[:3])
        out[b, 4:7] = [un[r, c] for r, c in _S_AT]
        out[b, 7:10] = un[:3, 3]
    return out

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
The plant's forward dynamics for one state, compiled (numba): what simulators call in loops.

:func:`forward_dynamics_kernel` (allocating) and :func:`forward_dynamics_into` (caller-owned
buffers, for inner loops) compute :meth:`.plant.PlanarArm.forward_dynamics` for one state
with the constants of :meth:`.plant.PlanarArm.kernel_constants`; the tests hold them equal
to it. The PD-tuning kernel and the ``sim_arm`` node integrate with them.
"""

import math
from typing import NamedTuple

from numba import njit
import numpy as np


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

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
A spatial serial arm written out by hand, for the tests of the trigonometric basis.

Frames by the modified Denavit-Hartenberg convention: frame k follows frame k-1 by a
rotation α_k about x, a translation a_k along x and d_k along z, then the joint's rotation
θ_k about z. Link k is rigid in frame k: mass m_k, centre of mass c_k and inertia tensor
I_k (about the centre of mass) in that frame. Then

    M(θ) = Σ_l m_l J_vlᵀ J_vl + J_ωlᵀ R_l I_l R_lᵀ J_ωl,   U(θ) = -Σ_l m_l gᵀ p_l,

with the Jacobian columns k <= l: J_v = z_k × (p_l - o_k), J_ω = z_k. Every operation is
analytic, so complex-step differentiation gives ∂M/∂θ and ∇U to rounding, and with them
V (Christoffel symbols) and G: an inverse dynamics independent of the package's code.
"""

import numpy as np

STEP = 1e-30


def _rot_x(a):
    c, s = np.cos(a), np.sin(a)
    one, zero = np.ones_like(c), np.zeros_like(c)
    return np.array([[one, zero, zero], [zero, c, -s], [zero, s, c]])


def _rot_z(a):
    c, s = np.cos(a), np.sin(a)
    one, zero = np.ones_like(c), np.zeros_like(c)
    return np.array([[c, -s, zero], [s, c, zero], [zero, zero, one]])


class SpatialArm:
    """
    A spatial n-joint revolute arm (see the module docstring).

    Parameters
    ----------
    alpha, a, d : array_like, shape (n,)
        Modified DH constants.
    masses : array_like, shape (n,)
    coms : array_like, shape (n, 3)
        Centres of mass in the link frames.
    inertias : array_like, shape (n, 3, 3)
        Inertia tensors about the centres of mass, in the link frames.
    gravity : array_like, shape (3,)
        Gravity acceleration in the base frame.
    viscous, coulomb : array_like, shape (n,), optional
        Friction, ``viscous θ̇ + coulomb tanh(θ̇ / coulomb_velocity)``.

    """

    def __init__(self, alpha, a, d, masses, coms, inertias, gravity=(0.0, 0.0, -9.81),
                 viscous=None, coulomb=None, coulomb_velocity=0.05):
        self.alpha = np.asarray(alpha, dtype=float)
        self.a = np.asarray(a, dtype=float)
        self.d = np.asarray(d, dtype=float)
        self.masses = np.asarray(masses, dtype=float)
        self.coms = np.asarray(coms, dtype=float)
        self.inertias = np.asarray(inertias, dtype=float)
        self.gravity = np.asarray(gravity, dtype=float)
        n = self.n_joints
        self.viscous = np.zeros(n) if viscous is None else np.asarray(viscous, dtype=float)
        self.coulomb = np.zeros(n) if coulomb is None else np.asarray(coulomb, dtype=float)
        self.coulomb_velocity = coulomb_velocity

    @classmethod
    def elbow(cls, gravity=(0.0, -9.81, 0.0), seed=3):
        """
        Return an anthropomorphic 3-joint arm with generic (asymmetric) links.

        Joint 1 about the base z axis, joints 2 and 3 parallel to each other and
        perpendicular to it; centres of mass off the link axes and full inertia tensors.
        The default gravity (-y) is not parallel to joint 1, so U depends on every joint.
        """
        rng = np.random.default_rng(seed)
        inertias = []
        for _ in range(3):
            q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
            inertias.append(q @ np.diag(rng.uniform(0.01, 0.05, 3)) @ q.T)
        return cls(alpha=[0.0, np.pi / 2, 0.0], a=[0.0, 0.05, 0.4], d=[0.3, 0.02, 0.0],
                   masses=[3.0, 2.5, 1.5],
                   coms=[[0.01, 0.02, -0.05], [0.2, 0.01, 0.03], [0.15, -0.02, 0.01]],
                   inertias=inertias, gravity=gravity, viscous=[0.4, 0.3, 0.2],
                   coulomb=[0.2, 0.15, 0.1])

    @property
    def n_joints(self) -> int:
        """Return the number of joints n."""
        return self.masses.size

    def _links(self, theta):
        """Per link: rotation R (3, 3), joint origin o (3,), centre of mass p (3,)."""
        rot = np.eye(3, dtype=theta.dtype)
        pos = np.zeros(3, dtype=theta.dtype)
        out = []
        for k in range(self.n_joints):
            pos = pos + rot @ np.array([self.a[k], 0.0, 0.0])
            rot = rot @ _rot_x(self.alpha[k])
            pos = pos + rot @ np.array([0.0, 0.0, self.d[k]])
            rot = rot @ _rot_z(theta[k])
            out.append((rot, pos, pos + rot @ self.coms[k]))
        return out

    def _mass_matrix_one(self, theta):
        n = self.n_joints
        links = self._links(theta)
        m = np.zeros((n, n), dtype=theta.dtype)
        for link, (rot_l, _, com) in enumerate(links):
            jv = np.zeros((3, n), dtype=theta.dtype)
            jw = np.zeros((3, n), dtype=theta.dtype)
            for k in range(link + 1):
                rot_k, origin, _ = links[k]
                z = rot_k[:, 2]
                jv[:, k] = np.cross(z, com - origin)
                jw[:, k] = z
            inertia = rot_l @ self.inertias[link] @ rot_l.T
            m = m + self.masses[link] * jv.T @ jv + jw.T @ inertia @ jw
        return m

    def mass_matrix(self, theta):
        """Return M(θ), shape (..., n, n), for ``theta`` of shape (..., n)."""
        theta = np.asarray(theta)
        flat = theta.reshape(-1, self.n_joints)
        out = np.array([self._mass_matrix_one(t) for t in flat])
        return out.reshape(theta.shape[:-1] + (self.n_joints, self.n_joints))

    def link_potential(self, theta, link):
        """Return link ``link``'s potential energy -m gᵀ p, shape (...)."""
        theta = np.asarray(theta)
        flat = theta.reshape(-1, self.n_joints)
        out = np.array([-self.masses[link] * self.gravity @ self._links(t)[link][2]
                        for t in flat])
        return out.reshape(theta.shape[:-1])

    def potential(self, theta):
        """Return U(θ), shape (...)."""
        return sum(self.link_potential(theta, k) for k in range(self.n_joints))

    def _complex_step(self, f, theta):
        """Return ∂f/∂θ_k stacked on a new last axis, by complex steps."""
        theta = np.asarray(theta, dtype=float)
        out = []
        for k in range(self.n_joints):
            shifted = theta.astype(complex)
            shifted[..., k] += 1j * STEP
            out.append(np.imag(f(shifted)) / STEP)
        return np.stack(out, axis=-1)

    def gravity_terms(self, theta):
        """Return G(θ) = ∇U, shape (..., n)."""
        return self._complex_step(self.potential, theta)

    def inverse_dynamics(self, theta, theta_dot, theta_ddot):
        """Return τ = M θ̈ + V + G + F, shape (..., n)."""
        theta = np.asarray(theta, dtype=float)
        qd = np.asarray(theta_dot, dtype=float)
        qdd = np.asarray(theta_ddot, dtype=float)
        m = self.mass_matrix(theta)
        dm = self._complex_step(self.mass_matrix, theta)             # (..., i, j, k)
        v = (np.einsum('...ijk,...j,...k->...i', dm, qd, qd)
             - 0.5 * np.einsum('...jki,...j,...k->...i', dm, qd, qd))
        friction = self.viscous * qd + self.coulomb * np.tanh(qd / self.coulomb_velocity)
        return (np.einsum('...ij,...j->...i', m, qdd) + v + self.gravity_terms(theta)
                + friction)

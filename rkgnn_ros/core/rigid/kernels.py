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
Compiled rigid-body dynamics of a tree of revolute joints, linear in its inertial parameters.

The arrays of a :class:`Tree` (built by :mod:`.structure` from a URDF) describe body i:
its parent body (``parent[i] < i``, -1 for the root), the fixed pose of its joint frame in
the parent body's frame at θ = 0 (``rot[i]`` child-to-parent rotation, ``pos[i]`` origin,
m), its unit joint axis in its own frame, and the column of the joint vector that drives
it (``col[i]``), so θ, θ̇, θ̈ and τ stay in the data's joint order.

Per body ten inertial parameters, in the body's joint frame:
``[m, m cx, m cy, m cz, Ixx, Iyy, Izz, Ixy, Ixz, Iyz]`` (kg, kg m, kg m²; the inertia about
the frame's origin, not the centre of mass), :data:`N_INERTIAL` per body; per joint four
more: rotor (armature) inertia, viscous and Coulomb friction and a torque offset,
``τ_f = Ia θ̈ + fv θ̇ + fc tanh(θ̇ / v_c) + c`` (kg m², N m s/rad, N m, N m). The full
parameter vector is the bodies' ten each, then the joints' four each.

Spatial vectors follow Featherstone (motion [ω; v], force [n; f], each body's quantities in
its own frame, gravity as an acceleration of the root). The recursive Newton-Euler
algorithm gives the inverse dynamics (:func:`inverse_dynamics`) and, with unit parameter
vectors, the joint-torque regressor Y with τ = Y π (:func:`regressor`); the composite
rigid-body algorithm gives M(θ) (:func:`mass_matrix`), and :func:`accelerations` the
forward dynamics θ̈ = M⁻¹ (τ − V − G − F) by Cholesky. Everything is numba-compiled and
allocation-free in the loops, so a closed-loop rollout can call it at every stage.
"""

import math
from typing import NamedTuple

from numba import njit
import numpy as np

__all__ = ['N_INERTIAL', 'N_JOINT', 'Tree', 'accelerations', 'bias_forces', 'cholesky_solve',
           'gravity_pass', 'gravity_regressor', 'inverse_dynamics', 'mass_matrix', 'regressor',
           'regressor_rows']

#: Inertial parameters per body.
N_INERTIAL = 10

#: Joint parameters per joint (armature, viscous, Coulomb, offset).
N_JOINT = 4


class Tree(NamedTuple):
    """
    The kinematic tree the kernels take (numba-friendly arrays, bodies in parent order).

    Attributes
    ----------
    parent : ndarray of int64, shape (B,)
        Parent body of each body (-1: the root).
    col : ndarray of int64, shape (B,)
        Column of the joint vector that drives each body.
    rot : ndarray, shape (B, 3, 3)
        Rotation of the body's joint frame in its parent's frame at θ = 0 (child to parent).
    pos : ndarray, shape (B, 3)
        Origin of the body's joint frame in its parent's frame (m).
    axis : ndarray, shape (B, 3)
        Unit joint axis in the body's own frame.
    gravity : ndarray, shape (3,)
        Gravitational acceleration in the root frame (m/s²), e.g. (0, 0, -9.81).
    coulomb_velocity : float
        v_c of the Coulomb term's tanh (rad/s).

    """

    parent: np.ndarray
    col: np.ndarray
    rot: np.ndarray
    pos: np.ndarray
    axis: np.ndarray
    gravity: np.ndarray
    coulomb_velocity: float


@njit(cache=True, nogil=True, inline='always')
def _cross(a, b, out):
    x = a[1] * b[2] - a[2] * b[1]
    y = a[2] * b[0] - a[0] * b[2]
    z = a[0] * b[1] - a[1] * b[0]
    out[0], out[1], out[2] = x, y, z


@njit(cache=True, nogil=True)
def _poses(tree_rot, axis, col, q, rot):
    """Write each body's rotation child-to-parent at θ = ``q`` into ``rot`` (B, 3, 3)."""
    for i in range(col.shape[0]):
        angle = q[col[i]]
        c, s = math.cos(angle), math.sin(angle)
        v = 1.0 - c
        x, y, z = axis[i, 0], axis[i, 1], axis[i, 2]
        rj00, rj01, rj02 = c + x * x * v, x * y * v - z * s, x * z * v + y * s
        rj10, rj11, rj12 = y * x * v + z * s, c + y * y * v, y * z * v - x * s
        rj20, rj21, rj22 = z * x * v - y * s, z * y * v + x * s, c + z * z * v
        for r in range(3):
            a0, a1, a2 = tree_rot[i, r, 0], tree_rot[i, r, 1], tree_rot[i, r, 2]
            rot[i, r, 0] = a0 * rj00 + a1 * rj10 + a2 * rj20
            rot[i, r, 1] = a0 * rj01 + a1 * rj11 + a2 * rj21
            rot[i, r, 2] = a0 * rj02 + a1 * rj12 + a2 * rj22


@njit(cache=True, nogil=True)
def _motion(parent, col, rot, pos, axis, gravity, qd, qdd, w, v, wd, al, tmp):
    """
    Forward pass: each body's ω, v, ω̇ and linear spatial acceleration, in its own frame.

    The root accelerates at −g (gravity enters as that acceleration). ``tmp`` (2, 3).
    """
    for i in range(parent.shape[0]):
        p = parent[i]
        j = col[i]
        r = rot[i]
        # the parent's motion (zero for the root, −g for its acceleration)
        for k in range(3):
            if p >= 0:
                tmp[0, k] = al[p, k]
            else:
                tmp[0, k] = -gravity[k]
        if p >= 0:
            # v_p − pos × ω_p and al_p − pos × ω̇_p, then rotated into the child: Rᵀ (...)
            _cross(pos[i], w[p], tmp[1])
            for k in range(3):
                tmp[1, k] = v[p, k] - tmp[1, k]
            for k in range(3):
                v[i, k] = r[0, k] * tmp[1, 0] + r[1, k] * tmp[1, 1] + r[2, k] * tmp[1, 2]
            _cross(pos[i], wd[p], tmp[1])
            for k in range(3):
                tmp[0, k] -= tmp[1, k]
            for k in range(3):
                w[i, k] = r[0, k] * w[p, 0] + r[1, k] * w[p, 1] + r[2, k] * w[p, 2]
                wd[i, k] = r[0, k] * wd[p, 0] + r[1, k] * wd[p, 1] + r[2, k] * wd[p, 2]
        else:
            for k in range(3):
                v[i, k] = 0.0
                w[i, k] = 0.0
                wd[i, k] = 0.0
        for k in range(3):
            al[i, k] = r[0, k] * tmp[0, 0] + r[1, k] * tmp[0, 1] + r[2, k] * tmp[0, 2]
        # the joint's own rate: ω += a q̇, ω̇ += a q̈ + ω × a q̇, al += v × a q̇
        rate = qd[j]
        for k in range(3):
            tmp[1, k] = axis[i, k] * rate
        _cross(w[i], tmp[1], tmp[0])
        for k in range(3):
            wd[i, k] += tmp[0, k] + axis[i, k] * qdd[j]
        _cross(v[i], tmp[1], tmp[0])
        for k in range(3):
            al[i, k] += tmp[0, k]
            w[i, k] += tmp[1, k]


@njit(cache=True, nogil=True)
def _wrench(pi, o, w, v, wd, al, n, f, tmp):
    """
    Write the wrench I a + v ×* I v of body parameters ``pi[o:o + 10]`` into ``n``, ``f``.

    ``w``, ``v``, ``wd``, ``al``: the body's ω, v, ω̇ and linear acceleration (3,);
    ``tmp`` (4, 3).
    """
    m = pi[o]
    hx, hy, hz = pi[o + 1], pi[o + 2], pi[o + 3]
    ixx, iyy, izz = pi[o + 4], pi[o + 5], pi[o + 6]
    ixy, ixz, iyz = pi[o + 7], pi[o + 8], pi[o + 9]
    h = tmp[0]
    h[0], h[1], h[2] = hx, hy, hz
    # L = Ī ω + h × v ; P = m v − h × ω
    lw0 = ixx * w[0] + ixy * w[1] + ixz * w[2]
    lw1 = ixy * w[0] + iyy * w[1] + iyz * w[2]
    lw2 = ixz * w[0] + iyz * w[1] + izz * w[2]
    _cross(h, v, tmp[1])
    lx, ly, lz = lw0 + tmp[1, 0], lw1 + tmp[1, 1], lw2 + tmp[1, 2]
    _cross(h, w, tmp[1])
    px, py, pz = m * v[0] - tmp[1, 0], m * v[1] - tmp[1, 1], m * v[2] - tmp[1, 2]
    # I a: [Ī ω̇ + h × al ; m al − h × ω̇]
    _cross(h, al, tmp[1])
    n[0] = ixx * wd[0] + ixy * wd[1] + ixz * wd[2] + tmp[1, 0]
    n[1] = ixy * wd[0] + iyy * wd[1] + iyz * wd[2] + tmp[1, 1]
    n[2] = ixz * wd[0] + iyz * wd[1] + izz * wd[2] + tmp[1, 2]
    _cross(h, wd, tmp[1])
    f[0] = m * al[0] - tmp[1, 0]
    f[1] = m * al[1] - tmp[1, 1]
    f[2] = m * al[2] - tmp[1, 2]
    # v ×* [L; P] = [ω × L + v × P ; ω × P]
    tmp[2, 0], tmp[2, 1], tmp[2, 2] = lx, ly, lz
    tmp[3, 0], tmp[3, 1], tmp[3, 2] = px, py, pz
    _cross(w, tmp[2], tmp[1])
    for k in range(3):
        n[k] += tmp[1, k]
    _cross(v, tmp[3], tmp[1])
    for k in range(3):
        n[k] += tmp[1, k]
    _cross(w, tmp[3], tmp[1])
    for k in range(3):
        f[k] += tmp[1, k]


@njit(cache=True, nogil=True, inline='always')
def _to_parent(r, p, n, f, tmp):
    """Express the wrench (n, f) of a body in its parent's frame, in place."""
    for k in range(3):
        tmp[0, k] = r[k, 0] * f[0] + r[k, 1] * f[1] + r[k, 2] * f[2]
        tmp[1, k] = r[k, 0] * n[0] + r[k, 1] * n[1] + r[k, 2] * n[2]
    _cross(p, tmp[0], tmp[2])
    for k in range(3):
        f[k] = tmp[0, k]
        n[k] = tmp[1, k] + tmp[2, k]


@njit(cache=True, nogil=True, inline='always')
def _add_to_parent(i, parent, rot, pos, fn, ff, tmp):
    """Add body i's wrench (fn[i], ff[i]), in its parent's frame, to the parent's (if any)."""
    p = parent[i]
    if p >= 0:
        _to_parent(rot[i], pos[i], fn[i], ff[i], tmp)
        for k in range(3):
            fn[p, k] += fn[i, k]
            ff[p, k] += ff[i, k]


@njit(cache=True, nogil=True)
def _joint_terms(pi, nb, j, qd, qdd, vc):
    """Return the joint's own torque Ia θ̈ + fv θ̇ + fc tanh(θ̇ / v_c) + c."""
    o = N_INERTIAL * nb + N_JOINT * j
    return pi[o] * qdd + pi[o + 1] * qd + pi[o + 2] * math.tanh(qd / vc) + pi[o + 3]


@njit(cache=True, nogil=True)
def _work(nb):
    return (np.empty((nb, 3, 3)), np.empty((nb, 3)), np.empty((nb, 3)), np.empty((nb, 3)),
            np.empty((nb, 3)), np.empty((nb, 3)), np.empty((nb, 3)), np.empty((4, 3)))


@njit(cache=True, nogil=True)
def _rnea(parent, col, trot, pos, axis, gravity, vc, pi, q, qd, qdd, with_joint, rot, w, v,
          wd, al, fn, ff, tmp, tau):
    """τ = RNEA(θ, θ̇, θ̈) with parameters ``pi`` into ``tau``; joint terms if ``with_joint``."""
    nb = parent.shape[0]
    _poses(trot, axis, col, q, rot)
    _motion(parent, col, rot, pos, axis, gravity, qd, qdd, w, v, wd, al, tmp)
    for i in range(nb):
        _wrench(pi, N_INERTIAL * i, w[i], v[i], wd[i], al[i], fn[i], ff[i], tmp)
    for i in range(nb - 1, -1, -1):
        j = col[i]
        tau[j] = axis[i, 0] * fn[i, 0] + axis[i, 1] * fn[i, 1] + axis[i, 2] * fn[i, 2]
        if with_joint:
            tau[j] += _joint_terms(pi, nb, j, qd[j], qdd[j], vc)
        _add_to_parent(i, parent, rot, pos, fn, ff, tmp)


@njit(cache=True, nogil=True)
def inverse_dynamics(parent, col, trot, pos, axis, gravity, vc, pi, q, qd, qdd):
    """
    Return τ = M θ̈ + V + G + F of parameters ``pi`` at K states, shape (K, n).

    ``q``, ``qd``, ``qdd`` (K, n): joint positions (rad), rates (rad/s), accelerations
    (rad/s²) in the data's joint order.
    """
    nb = parent.shape[0]
    rot, w, v, wd, al, fn, ff, tmp = _work(nb)
    out = np.empty(q.shape)
    for k in range(q.shape[0]):
        _rnea(parent, col, trot, pos, axis, gravity, vc, pi, q[k], qd[k], qdd[k], True, rot,
              w, v, wd, al, fn, ff, tmp, out[k])
    return out


@njit(cache=True, nogil=True)
def _regressor_one(parent, col, trot, pos, axis, gravity, vc, q, qd, qdd, rot, w, v, wd, al,
                   unit, n, f, tmp, out):
    """Write Y(θ, θ̇, θ̈) (n, 10 B + 4 n) into ``out`` (zeroed by the caller)."""
    nb = parent.shape[0]
    _poses(trot, axis, col, q, rot)
    _motion(parent, col, rot, pos, axis, gravity, qd, qdd, w, v, wd, al, tmp)
    for i in range(nb):
        for c in range(N_INERTIAL):
            unit[:] = 0.0
            unit[c] = 1.0
            _wrench(unit, 0, w[i], v[i], wd[i], al[i], n, f, tmp)
            b = i
            while b >= 0:
                out[col[b], N_INERTIAL * i + c] = (axis[b, 0] * n[0] + axis[b, 1] * n[1]
                                                   + axis[b, 2] * n[2])
                if parent[b] >= 0:
                    _to_parent(rot[b], pos[b], n, f, tmp)
                b = parent[b]
    for j in range(q.shape[0]):
        o = N_INERTIAL * nb + N_JOINT * j
        out[j, o] = qdd[j]
        out[j, o + 1] = qd[j]
        out[j, o + 2] = math.tanh(qd[j] / vc)
        out[j, o + 3] = 1.0


@njit(cache=True, nogil=True)
def regressor(parent, col, trot, pos, axis, gravity, vc, q, qd, qdd):
    """
    Return the regressor Y at K states, shape (K, n, 10 B + 4 n): τ_k = Y_k π.

    Columns: each body's ten inertial parameters, then each joint's four (module docstring).
    """
    nb = parent.shape[0]
    n_joints = q.shape[1]
    rot, w, v, wd, al, fn, ff, tmp = _work(nb)
    unit = np.zeros(N_INERTIAL)
    out = np.zeros((q.shape[0], n_joints, N_INERTIAL * nb + N_JOINT * n_joints))
    for k in range(q.shape[0]):
        _regressor_one(parent, col, trot, pos, axis, gravity, vc, q[k], qd[k], qdd[k], rot, w,
                       v, wd, al, unit, fn[0], ff[0], tmp, out[k])
    return out


@njit(cache=True, nogil=True)
def regressor_rows(parent, col, trot, pos, axis, gravity, vc, q, qd, qdd, columns):
    """
    Return Y's ``columns`` (C,) at K states stacked joint-major, shape (K n, C).

    Row k n + j is joint j of state k; the form a least-squares fit takes, without the
    full (K, n, P) array.
    """
    nb = parent.shape[0]
    n_joints = q.shape[1]
    rot, w, v, wd, al, fn, ff, tmp = _work(nb)
    unit = np.zeros(N_INERTIAL)
    full = np.zeros((n_joints, N_INERTIAL * nb + N_JOINT * n_joints))
    out = np.empty((q.shape[0] * n_joints, columns.shape[0]))
    for k in range(q.shape[0]):
        full[:] = 0.0
        _regressor_one(parent, col, trot, pos, axis, gravity, vc, q[k], qd[k], qdd[k], rot, w,
                       v, wd, al, unit, fn[0], ff[0], tmp, full)
        for j in range(n_joints):
            for c in range(columns.shape[0]):
                out[k * n_joints + j, c] = full[j, columns[c]]
    return out


@njit(cache=True, nogil=True)
def gravity_regressor(parent, col, trot, pos, axis, gravity, vc, q):
    """
    Return G's regressor at K configurations, shape (K, n, 10 B + 4 n): G_k = Y_g,k π.

    Only the mass and first-moment columns are non-zero.
    """
    zeros = np.zeros(q.shape)
    return regressor(parent, col, trot, pos, axis, gravity, vc, q, zeros, zeros)


@njit(cache=True, nogil=True)
def _composite(pi, o, r, p, out, ob):
    """Add body parameters ``pi[o:o+10]``, moved to the parent frame by (r, p), to ``out``."""
    m = pi[o]
    h0, h1, h2 = pi[o + 1], pi[o + 2], pi[o + 3]
    i00, i11, i22 = pi[o + 4], pi[o + 5], pi[o + 6]
    i01, i02, i12 = pi[o + 7], pi[o + 8], pi[o + 9]
    # R Ī (row by row), then R Ī Rᵀ's upper triangle
    a00 = r[0, 0] * i00 + r[0, 1] * i01 + r[0, 2] * i02
    a01 = r[0, 0] * i01 + r[0, 1] * i11 + r[0, 2] * i12
    a02 = r[0, 0] * i02 + r[0, 1] * i12 + r[0, 2] * i22
    a10 = r[1, 0] * i00 + r[1, 1] * i01 + r[1, 2] * i02
    a11 = r[1, 0] * i01 + r[1, 1] * i11 + r[1, 2] * i12
    a12 = r[1, 0] * i02 + r[1, 1] * i12 + r[1, 2] * i22
    a20 = r[2, 0] * i00 + r[2, 1] * i01 + r[2, 2] * i02
    a21 = r[2, 0] * i01 + r[2, 1] * i11 + r[2, 2] * i12
    a22 = r[2, 0] * i02 + r[2, 1] * i12 + r[2, 2] * i22
    b00 = a00 * r[0, 0] + a01 * r[0, 1] + a02 * r[0, 2]
    b11 = a10 * r[1, 0] + a11 * r[1, 1] + a12 * r[1, 2]
    b22 = a20 * r[2, 0] + a21 * r[2, 1] + a22 * r[2, 2]
    b01 = a00 * r[1, 0] + a01 * r[1, 1] + a02 * r[1, 2]
    b02 = a00 * r[2, 0] + a01 * r[2, 1] + a02 * r[2, 2]
    b12 = a10 * r[2, 0] + a11 * r[2, 1] + a12 * r[2, 2]
    rh0 = r[0, 0] * h0 + r[0, 1] * h1 + r[0, 2] * h2
    rh1 = r[1, 0] * h0 + r[1, 1] * h1 + r[1, 2] * h2
    rh2 = r[2, 0] * h0 + r[2, 1] * h1 + r[2, 2] * h2
    p0, p1, p2 = p[0], p[1], p[2]
    diag = m * (p0 * p0 + p1 * p1 + p2 * p2) + 2.0 * (p0 * rh0 + p1 * rh1 + p2 * rh2)
    out[ob] += m
    out[ob + 1] += rh0 + m * p0
    out[ob + 2] += rh1 + m * p1
    out[ob + 3] += rh2 + m * p2
    # Ī' = R Ī Rᵀ + m (|p|² 1 − p pᵀ) + 2 (p · R h) 1 − (R h) pᵀ − p (R h)ᵀ
    out[ob + 4] += b00 - m * p0 * p0 - 2.0 * rh0 * p0 + diag
    out[ob + 5] += b11 - m * p1 * p1 - 2.0 * rh1 * p1 + diag
    out[ob + 6] += b22 - m * p2 * p2 - 2.0 * rh2 * p2 + diag
    out[ob + 7] += b01 - m * p0 * p1 - rh0 * p1 - p0 * rh1
    out[ob + 8] += b02 - m * p0 * p2 - rh0 * p2 - p0 * rh2
    out[ob + 9] += b12 - m * p1 * p2 - rh1 * p2 - p1 * rh2


@njit(cache=True, nogil=True)
def _crba(parent, col, rot, pos, axis, pi, comp, fn, ff, tmp, mass):
    """Write M(θ) (joint terms' armature included) into ``mass``; ``rot`` at θ already."""
    nb = parent.shape[0]
    nj = mass.shape[0]
    mass[:, :] = 0.0
    for k in range(comp.shape[0]):
        comp[k] = pi[k]
    for i in range(nb - 1, -1, -1):
        p = parent[i]
        if p >= 0:
            _composite(comp, N_INERTIAL * i, rot[i], pos[i], comp, N_INERTIAL * p)
    for i in range(nb):
        o = N_INERTIAL * i
        a = axis[i]
        # F = I_c [a; 0] = [Ī a ; −h × a]
        n = fn[0]
        f = ff[0]
        n[0] = comp[o + 4] * a[0] + comp[o + 7] * a[1] + comp[o + 8] * a[2]
        n[1] = comp[o + 7] * a[0] + comp[o + 5] * a[1] + comp[o + 9] * a[2]
        n[2] = comp[o + 8] * a[0] + comp[o + 9] * a[1] + comp[o + 6] * a[2]
        tmp[3, 0], tmp[3, 1], tmp[3, 2] = comp[o + 1], comp[o + 2], comp[o + 3]
        _cross(tmp[3], a, f)
        for k in range(3):
            f[k] = -f[k]
        ci = col[i]
        rotor = pi[N_INERTIAL * nb + N_JOINT * ci]
        mass[ci, ci] = a[0] * n[0] + a[1] * n[1] + a[2] * n[2] + rotor
        b = i
        while parent[b] >= 0:
            _to_parent(rot[b], pos[b], n, f, tmp)
            b = parent[b]
            cb = col[b]
            value = axis[b, 0] * n[0] + axis[b, 1] * n[1] + axis[b, 2] * n[2]
            mass[ci, cb] = value
            mass[cb, ci] = value
    return nj


@njit(cache=True, nogil=True)
def mass_matrix(parent, col, trot, pos, axis, pi, q):
    """Return M(θ) at K configurations, shape (K, n, n) (rotor inertia included)."""
    nb = parent.shape[0]
    rot, w, v, wd, al, fn, ff, tmp = _work(nb)
    comp = np.empty(N_INERTIAL * nb)
    out = np.zeros((q.shape[0], q.shape[1], q.shape[1]))
    for k in range(q.shape[0]):
        _poses(trot, axis, col, q[k], rot)
        _crba(parent, col, rot, pos, axis, pi, comp, fn, ff, tmp, out[k])
    return out


@njit(cache=True, nogil=True)
def bias_forces(parent, col, trot, pos, axis, gravity, vc, pi, q, qd):
    """Return V + G + F (θ̈ = 0) at K states, shape (K, n)."""
    return inverse_dynamics(parent, col, trot, pos, axis, gravity, vc, pi, q, qd,
                            np.zeros(q.shape))


@njit(cache=True, nogil=True)
def cholesky_solve(mass, rhs):
    """Solve M a = rhs in place (``rhs`` becomes a); return False if M is not positive."""
    n = mass.shape[0]
    for j in range(n):
        s = mass[j, j]
        for k in range(j):
            s -= mass[j, k] * mass[j, k]
        if not s > 0.0:
            return False
        mass[j, j] = math.sqrt(s)
        for i in range(j + 1, n):
            s = mass[i, j]
            for k in range(j):
                s -= mass[i, k] * mass[j, k]
            mass[i, j] = s / mass[j, j]
    for i in range(n):
        s = rhs[i]
        for k in range(i):
            s -= mass[i, k] * rhs[k]
        rhs[i] = s / mass[i, i]
    for i in range(n - 1, -1, -1):
        s = rhs[i]
        for k in range(i + 1, n):
            s -= mass[k, i] * rhs[k]
        rhs[i] = s / mass[i, i]
    return True


@njit(cache=True, nogil=True)
def accelerations(parent, col, trot, pos, axis, gravity, vc, pi, q, qd, tau):
    """Return θ̈ = M⁻¹ (τ − V − G − F) at K states, shape (K, n); NaN where M is not positive."""
    nb = parent.shape[0]
    n_joints = q.shape[1]
    rot, w, v, wd, al, fn, ff, tmp = _work(nb)
    comp = np.empty(N_INERTIAL * nb)
    zeros = np.zeros(n_joints)
    bias = np.empty(n_joints)
    mass = np.zeros((n_joints, n_joints))
    out = np.empty(q.shape)
    for k in range(q.shape[0]):
        _rnea(parent, col, trot, pos, axis, gravity, vc, pi, q[k], qd[k], zeros, True, rot,
              w, v, wd, al, fn, ff, tmp, bias)
        _crba(parent, col, rot, pos, axis, pi, comp, fn, ff, tmp, mass)
        for j in range(n_joints):
            out[k, j] = tau[k, j] - bias[j]
        if not cholesky_solve(mass, out[k]):
            out[k, :] = np.nan
    return out


@njit(cache=True, nogil=True)
def gravity_pass(parent, col, rot, pos, axis, gravity, pi, al, fn, ff, tmp, tau):
    """
    Write G(θ) of parameters ``pi`` (inertial part) into ``tau``; ``rot`` at θ already.

    A Newton-Euler pass at rest: each body accelerates at −g in its frame, so its wrench is
    (h × a, m a).
    """
    nb = parent.shape[0]
    for i in range(nb):
        p = parent[i]
        r = rot[i]
        for k in range(3):
            tmp[0, k] = al[p, k] if p >= 0 else -gravity[k]
        for k in range(3):
            al[i, k] = r[0, k] * tmp[0, 0] + r[1, k] * tmp[0, 1] + r[2, k] * tmp[0, 2]
        o = N_INERTIAL * i
        m = pi[o]
        tmp[1, 0], tmp[1, 1], tmp[1, 2] = pi[o + 1], pi[o + 2], pi[o + 3]
        _cross(tmp[1], al[i], fn[i])
        for k in range(3):
            ff[i, k] = m * al[i, k]
    for i in range(nb - 1, -1, -1):
        tau[col[i]] = axis[i, 0] * fn[i, 0] + axis[i, 1] * fn[i, 1] + axis[i, 2] * fn[i, 2]
        _add_to_parent(i, parent, rot, pos, fn, ff, tmp)

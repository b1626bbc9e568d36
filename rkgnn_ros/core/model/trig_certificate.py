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
A proof that M(θ) of the trigonometric basis stays above a floor on a box of joint angles.

A fitted M can be positive definite along the data and not elsewhere. For a trigonometric
M the minimum of λ_min over a whole box can be bounded from below by finitely many
evaluations (:func:`certify_inertia`: adaptive cells, a first-order vertex bound and a
bound of the second derivatives), so "positive definite on the whole joint range" is
something a fit can establish, not only sample.
"""

from dataclasses import dataclass
import itertools

import numpy as np

from .trig import evaluate_features, TrigBasis
from .trig_dynamics import unpack_mass

__all__ = ['certify_inertia', 'InertiaCertificate']


@dataclass(frozen=True)
class InertiaCertificate:
    """
    A lower bound of λ_min(M(θ)) over a box of joint angles, and what was seen there.

    Attributes
    ----------
    lower_bound : float
        Rigorous: λ_min(M(θ)) >= lower_bound for every θ in the box (up to rounding).
    smallest_seen : float
        The smallest λ_min(M) at the cell centres evaluated (an upper bound of the minimum).
    worst_theta : ndarray, shape (n,)
        Where ``smallest_seen`` was found.
    floor : float
        The level asked for.
    cells : int
        Cells evaluated.
    violations : ndarray, shape (K, n)
        Cell centres with λ_min(M) < floor (K may be 0), worst first.

    """

    lower_bound: float
    smallest_seen: float
    worst_theta: np.ndarray
    floor: float
    cells: int
    violations: np.ndarray

    @property
    def certified(self) -> bool:
        """Whether λ_min(M) >= floor holds on the whole box."""
        return self.lower_bound >= self.floor


def _spectral_norms(a) -> np.ndarray:
    """Return the spectral norm of symmetric matrices, shape (...) from (..., n, n)."""
    ev = np.linalg.eigvalsh(a)
    return np.maximum(np.abs(ev[..., 0]), np.abs(ev[..., -1]))


def certify_inertia(basis: TrigBasis, mass_coefficients, floor: float, scale=None,
                    lower=None, upper=None, max_cells: int = 200_000,
                    chunk: int = 2048) -> InertiaCertificate:
    """
    Bound λ_min(S M(θ) S) from below over the joint range by adaptive cells.

    S = diag(``scale``) (a congruence: S M S is positive definite exactly where M is; with
    S = diag(M̄)^(-1/2) the bound no longer suffers from the spread of the joints' inertias).
    For a cell with centre c and half-widths r, every θ in it satisfies

        λ_min(S M(θ) S) >= min over the cell's vertices v of λ_min(S (M(c) + ∇M(c)·v) S)
                           - ½ Σ_jk H_jk r_j r_k:

    λ_min of an affine matrix function is concave, so its minimum over the box is at a
    vertex, and H_jk >= sup ‖S ∂_j ∂_k M S‖ bounds the Taylor remainder (Weyl). H is the
    smaller of two bounds: Σ_f ‖S W_f S‖ ω_fj ω_fk from the coefficients (ω_fk the
    frequency of feature f in joint k), and Bernstein's inequality for trigonometric
    polynomials of degree n_k in joint k, ‖∂_j ∂_k T‖ <= n_j n_k sup ‖T‖, with
    T = S (M - M_const) S and sup ‖T‖ <= (max of ‖T‖ on a grid of m_k points per joint) /
    (1 - Σ_k π n_k / m_k). Cells whose bound is below ``floor`` while their centre is above
    it are halved along their most uncertain joint, until every cell is decided or
    ``max_cells`` were evaluated. Joints M does not depend on (θ1 for any serial chain) are
    not gridded. The cells needed grow like (1 / r)^d over d = n - 1 gridded joints, r the
    cell size the margin λ_min - floor allows: a few thousand for 3 joints, about 10^5 for
    a planar 4-joint arm, far beyond any budget for 6.

    Parameters
    ----------
    basis : TrigBasis
        The basis of M.
    mass_coefficients : array_like, shape (P_M,)
        M's coefficients (the ``mass`` slice of :class:`.trig_dynamics.Layout`).
    floor : float
        The level to certify for λ_min(S M S).
    scale : array_like, shape (n,), optional
        The diagonal of S; ones by default.
    lower, upper : array_like, shape (n,), optional
        Joint limits; default the torus [-π, π] for every joint.
    max_cells : int
        Budget of cell evaluations.
    chunk : int
        Cells evaluated per batch.

    Returns
    -------
    InertiaCertificate
        Bounds in the scaled metric, λ_min(S M S).

    """
    n = basis.n_joints
    s = np.ones(n) if scale is None else np.asarray(scale, dtype=float)
    w = unpack_mass(basis, np.asarray(mass_coefficients, dtype=float)) * np.outer(s, s)
    used = np.flatnonzero(np.any(w != 0.0, axis=(1, 2)))
    freq, kinds, w = basis.frequencies[used], basis.kinds[used], w[used]
    omega = np.abs(freq).astype(float)                              # (F, n)
    degree = omega.max(axis=0) if used.size else np.zeros(n)
    dims = np.flatnonzero(degree > 0)
    d = dims.size
    lo = np.full(n, -np.pi) if lower is None else np.asarray(lower, dtype=float)
    hi = np.full(n, np.pi) if upper is None else np.asarray(upper, dtype=float)
    mid = 0.5 * (lo + hi)

    def matrices(theta):
        phi, grad = evaluate_features(freq, kinds, theta, gradient=True)
        return (np.einsum('tf,fij->tij', phi, w),
                np.einsum('tfk,fij->tkij', grad[:, :, dims], w))       # (T, d, n, n)

    def grid(points):
        axes = [lo[k] + (np.arange(points[i]) + 0.5) * (hi[k] - lo[k]) / points[i]
                for i, k in enumerate(dims)]
        mesh = np.stack(np.meshgrid(*axes, indexing='ij'), axis=-1).reshape(-1, d)
        theta = np.tile(mid, (mesh.shape[0], 1))
        theta[:, dims] = mesh
        return theta

    hess = np.einsum('f,fj,fk->jk', _spectral_norms(w), omega, omega) if used.size else \
        np.zeros((n, n))
    if d:
        # Bernstein: m_k = 4π d n_k points per joint make Σ π n_k / m_k = 1/4
        points = np.ceil(4.0 * np.pi * d * degree[dims]).astype(int)
        if np.prod(points.astype(float)) <= max_cells / 4:
            constant = np.flatnonzero(~np.any(freq, axis=1))
            varying = w.copy()
            varying[constant] = 0.0
            sup = 0.0
            theta = grid(points)
            for start in range(0, theta.shape[0], chunk):
                phi = evaluate_features(freq, kinds, theta[start:start + chunk])
                t = np.einsum('tf,fij->tij', phi, varying)
                sup = max(sup, float(_spectral_norms(t).max()))
            sup /= 1.0 - float(np.sum(np.pi * degree[dims] / points))
            hess = np.minimum(hess, sup * np.outer(degree, degree))
    per_dim = np.full(d, max(2, min(16, int((max_cells / 64.0) ** (1.0 / d))))) if d else []
    centres = grid(per_dim) if d else mid[None].copy()
    half = np.zeros_like(centres)
    if d:
        half[:, dims] = 0.5 * (hi[dims] - lo[dims]) / per_dim
    signs = np.array(list(itertools.product((-1.0, 1.0), repeat=d))).reshape(-1, d)
    bound, seen, worst, evaluated = np.inf, np.inf, mid.copy(), 0
    bad_theta, bad_value = [], []
    while centres.shape[0]:
        last = evaluated + centres.shape[0] > max_cells
        keep_c, keep_h = [], []
        for start in range(0, centres.shape[0], chunk):
            c, r = centres[start:start + chunk], half[start:start + chunk]
            m, dm = matrices(c)
            lam = np.linalg.eigvalsh(m)[:, 0]
            # the linear part at every vertex: M(c) + Σ_k ±r_k ∂_k M(c)
            offsets = signs[None] * r[:, None, dims]                       # (T, V, d)
            vert = m[:, None] + np.einsum('tvk,tkij->tvij', offsets, dm)
            linear = np.linalg.eigvalsh(vert)[..., 0].min(axis=1)
            lb = linear - 0.5 * np.einsum('tj,jk,tk->t', r, hess, r)
            evaluated += c.shape[0]
            k = int(np.argmin(lam))
            if lam[k] < seen:
                seen, worst = float(lam[k]), c[k].copy()
            low = lam < floor
            bad_theta.append(c[low])
            bad_value.append(lam[low])
            split = (lb < floor) & ~low & (not last)
            bound = min(bound, float(lb[~split].min(initial=np.inf)))
            if np.any(split):
                # halve along the joint with the largest first- plus second-order spread
                rs = r[split]
                spread = (_spectral_norms(dm[split]) * rs[:, dims]
                          + rs[:, dims] * (rs @ hess)[:, dims])
                axis = dims[np.argmax(spread, axis=1)]
                rows = np.arange(axis.size)
                rs[rows, axis] *= 0.5
                for sign in (-1.0, 1.0):
                    cs = c[split].copy()
                    cs[rows, axis] += sign * rs[rows, axis]
                    keep_c.append(cs)
                    keep_h.append(rs)
        centres = np.vstack(keep_c) if keep_c else np.zeros((0, n))
        half = np.vstack(keep_h) if keep_h else np.zeros((0, n))
    bad_theta = np.vstack(bad_theta)
    bad_value = np.concatenate(bad_value)
    order = np.argsort(bad_value)
    return InertiaCertificate(lower_bound=float(bound), smallest_seen=float(seen),
                              worst_theta=worst, floor=float(floor), cells=int(evaluated),
                              violations=bad_theta[order])

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
Least squares over physically consistent parameters, with the robot description as prior.

The problem every rigid-body fit here reduces to (rows already weighted):

    minimise  ‖A π + B k − y‖²  +  λ ‖(φ − φ₀) / s‖²  +  λ ‖(ψ − ψ₀) / s_ψ‖²

over the bodies' log-Cholesky coordinates φ (π's inertial part, :mod:`.consistency`), the
joint parameters ψ (rotor inertia, viscous and Coulomb friction >= 0, an offset: π's joint
part) and free linear unknowns k (a servo's gains and gravity weights in the closed-loop
cases, one linear equality fixing their scale in case 3). Only the base parameters
P π (:class:`.structure.BaseParameters`) change A π, so the data term is reduced once to
the triangular factor R of [A_B  B] (A_B: A's independent columns): ‖R [P π; k] − Qᵀ y‖²
plus a constant (:func:`triangular_rows`). The prior term pulls only where the data do
not: φ₀ are the URDF's bodies (moved just inside where not strictly realizable), s is 1
for the logarithms and :data:`LENGTH_SCALE` for the lengths; λ is :data:`PRIOR_WEIGHT`
times the number of rows, so a direction counts as determined by data once moving it by one
unit of φ changes the weighted torque by about 1 % RMS. Bounded trust-region least squares
(scipy's ``trf``) with the exact Jacobian solves it, from the prior.
"""

import math
from typing import NamedTuple, Optional

import numpy as np

from . import consistency
from .kernels import N_INERTIAL, N_JOINT

__all__ = ['ConsistentFit', 'PRIOR_WEIGHT', 'fit_consistent', 'triangular_rows']

#: λ per weighted row (module docstring).
PRIOR_WEIGHT = 1e-6

#: Length (m) by which the prior divides the log-Cholesky coordinates that are lengths.
LENGTH_SCALE = 0.1

#: Scale (in their own units) of the joint parameters' pull towards their prior.
JOINT_SCALE = np.array([10.0, 100.0, 100.0, 100.0])
#: Rows of [A | y] factorised per call by :func:`triangular_rows`.
QR_BLOCK_ROWS = 2000


def triangular_rows(a: np.ndarray, y: np.ndarray):
    """
    Return (R, c, rest) with ‖a x − y‖² = ‖R x − c‖² + rest for every x.

    R (P, P) is upper triangular (zero rows where ``a`` has fewer rows than columns), c (P,)
    and rest >= 0: the triangular factor of Householder QR of [a | y], taken
    :data:`QR_BLOCK_ROWS` rows at a time on the factor so far (Q is never formed). numpy's
    QR holds the GIL: a block is a call of milliseconds, so the node's other threads never
    wait for a whole factorisation of a long window.
    """
    a = np.asarray(a, dtype=float)
    stacked = np.hstack([a, np.asarray(y, dtype=float).reshape(-1, 1)])
    n_par = a.shape[1]
    factor = np.zeros((0, n_par + 1))
    for start in range(0, stacked.shape[0], QR_BLOCK_ROWS):
        factor = np.linalg.qr(np.vstack([factor, stacked[start:start + QR_BLOCK_ROWS]]),
                              mode='r')
    full = np.zeros((n_par + 1, n_par + 1))
    full[:factor.shape[0]] = factor[:n_par + 1]
    return full[:n_par, :n_par], full[:n_par, n_par], float(full[n_par, n_par] ** 2)


class ConsistentFit(NamedTuple):
    """The result of :func:`fit_consistent`."""

    #: full parameter vector π (10 B + 4 n), every body realizable
    parameters: np.ndarray
    #: the free linear unknowns k (E,)
    extra: np.ndarray
    #: RMS of the weighted data residual per row
    rms_residual: float
    #: rows the fit used
    rows: int
    #: solver iterations (function evaluations)
    evaluations: int


def _scale(n_bodies: int) -> np.ndarray:
    one = np.ones(10)
    one[4:] = LENGTH_SCALE
    return np.tile(one, n_bodies)


class PriorOptions(NamedTuple):
    """The prior and solver options of :func:`fit_consistent` (see there)."""

    prior_weight: float = PRIOR_WEIGHT
    extra_ridge: float = 0.0
    max_evaluations: int = 200


def fit_consistent(structure, a: np.ndarray, y: np.ndarray, b: Optional[np.ndarray] = None,
                   normalise: Optional[np.ndarray] = None, prior=None, **options) -> ConsistentFit:
    """
    Return the consistent parameters fitted to weighted rows (module docstring).

    Parameters
    ----------
    structure : RigidStructure
        Its base parameters reduce ``a`` and its :attr:`prior` is the default prior.
    a : ndarray, shape (R, P)
        The regressor's rows for the full parameter vector (weighted).
    y : ndarray, shape (R,)
        Targets (weighted): the torque in case 1, the servo's torque in case 2, zeros in
        case 3.
    b : ndarray, shape (R, E), optional
        Columns of free linear unknowns k (weighted).
    normalise : ndarray, shape (E,), optional
        With it, ``normalise @ k == 1`` (case 3's scale).
    prior : ndarray, shape (P,), optional
        Parameters the fit is pulled towards where the data do not decide.
    prior_weight : float
        λ per row.
    extra_ridge : float
        A ridge on k (per row, relative to the mean squared column of ``b``).
    max_evaluations : int
        Most residual evaluations of the solver.

    Raises
    ------
    ValueError
        On shapes that do not match or non-finite rows.

    """
    prior_weight, extra_ridge, max_evaluations = PriorOptions(**options)
    from scipy.optimize import least_squares
    a = np.asarray(a, dtype=float)
    y = np.asarray(y, dtype=float).reshape(-1)
    n_rows, n_par = a.shape
    nb = structure.n_joints
    if n_par != structure.n_parameters or y.size != n_rows:
        raise ValueError(f'rows {a.shape} and targets {y.shape} do not fit '
                         f'{structure.n_parameters} parameters')
    b = np.zeros((n_rows, 0)) if b is None else np.asarray(b, dtype=float)
    if b.ndim != 2 or b.shape[0] != n_rows:
        raise ValueError(f'extra columns {b.shape} do not fit {n_rows} rows')
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(y)) and np.all(np.isfinite(b))):
        raise ValueError('the rows of the fit are not finite')
    if n_rows == 0:
        raise ValueError('no rows to fit')
    base = structure.base
    n_extra = b.shape[1]
    # k = k0 + N z: the equality normalise · k = 1 eliminated
    if normalise is not None:
        normalise = np.asarray(normalise, dtype=float).reshape(-1)
        k0 = normalise / float(normalise @ normalise)
        _, _, vt = np.linalg.svd(normalise[None, :])
        null = vt[1:].T
    else:
        k0, null = np.zeros(n_extra), np.eye(n_extra)
    n_z = null.shape[1]
    # the data term through R of [A_B  B N] (targets moved by B k0)
    design = np.hstack([a[:, base.independent], b @ null])
    target = y - b @ k0
    r_mat, c_vec, constant = triangular_rows(design, target)
    if extra_ridge > 0.0 and n_z:
        col = np.sqrt(np.mean((b @ null) ** 2, axis=0))
        ridge = math.sqrt(extra_ridge * n_rows) * np.maximum(col, 1e-12)
    else:
        ridge = np.zeros(n_z)
    prior = structure.prior if prior is None else np.asarray(prior, dtype=float)
    phi0 = consistency.coordinates(prior[:N_INERTIAL * nb].reshape(nb, 10)).reshape(-1)
    psi0 = np.maximum(prior[N_INERTIAL * nb:], 0.0)
    psi0[N_JOINT - 1::N_JOINT] = prior[N_INERTIAL * nb + N_JOINT - 1::N_JOINT]
    lam = math.sqrt(max(prior_weight, 0.0) * n_rows)
    s_phi = lam / _scale(nb)
    s_psi = lam / np.tile(JOINT_SCALE, nb)
    n_phi, n_psi = phi0.size, psi0.size
    projection_b = base.projection            # (r, P)
    r_b = r_mat[:, :base.rank]
    r_k = r_mat[:, base.rank:]

    def unpack(x):
        return x[:n_phi], x[n_phi:n_phi + n_psi], x[n_phi + n_psi:]

    def full(phi, psi):
        inertial = consistency.parameters(phi.reshape(nb, 10)).reshape(-1)
        return np.concatenate([inertial, psi])

    def residual(x):
        phi, psi, z = unpack(x)
        pi = full(phi, psi)
        data = r_b @ (projection_b @ pi) + r_k @ z - c_vec
        return np.concatenate([data, s_phi * (phi - phi0), s_psi * (psi - psi0), ridge * z])

    def jacobian(x):
        phi, psi, z = unpack(x)
        _, dpi = consistency.parameters(phi.reshape(nb, 10), jacobian=True)
        # d(P π)/dφ: P's inertial columns body by body times each body's Jacobian
        rp = r_b @ projection_b
        j_phi = np.concatenate([rp[:, 10 * i:10 * (i + 1)] @ dpi[i] for i in range(nb)], 1)
        j_psi = rp[:, N_INERTIAL * nb:]
        top = np.hstack([j_phi, j_psi, r_k])
        prior_rows = np.zeros((n_phi + n_psi + n_z, n_phi + n_psi + n_z))
        prior_rows[np.arange(n_phi), np.arange(n_phi)] = s_phi
        prior_rows[n_phi + np.arange(n_psi), n_phi + np.arange(n_psi)] = s_psi
        prior_rows[n_phi + n_psi + np.arange(n_z), n_phi + n_psi + np.arange(n_z)] = ridge
        return np.vstack([top, prior_rows])

    lower = np.full(n_phi + n_psi + n_z, -np.inf)
    upper = np.full(n_phi + n_psi + n_z, np.inf)
    for j in range(nb):
        lower[n_phi + N_JOINT * j:n_phi + N_JOINT * j + 3] = 0.0   # Ia, fv, fc >= 0
    z0 = np.zeros(n_z)
    if n_z:
        # the linear unknowns' least-squares start with π at the prior
        rhs = c_vec - r_b @ (projection_b @ full(phi0, psi0))
        z0, *_ = np.linalg.lstsq(np.vstack([r_k, np.diag(ridge)]),
                                 np.concatenate([rhs, np.zeros(n_z)]), rcond=None)
    x0 = np.concatenate([phi0, np.clip(psi0, lower[n_phi:n_phi + n_psi], None), z0])
    settings = {'jac': jacobian, 'bounds': (lower, upper), 'method': 'trf', 'x_scale': 'jac',
                'max_nfev': int(max_evaluations), 'xtol': 1e-10, 'ftol': 1e-10, 'gtol': 1e-10}
    # a trial step far out overflows the log-Cholesky exponentials: the solver rejects a
    # non-finite residual and shrinks its region, so the overflow is no fault to report
    with np.errstate(over='ignore', invalid='ignore'):
        try:
            result = least_squares(residual, x0, **settings)
        except np.linalg.LinAlgError:
            # LAPACK's SVD of the trust-region step can fail to converge on an
            # ill-conditioned Jacobian (seen once online on noisy data): the iterative step
            # needs no SVD
            result = least_squares(residual, x0, tr_solver='lsmr', **settings)
    phi, psi, z = unpack(result.x)
    data = r_b @ (projection_b @ full(phi, psi)) + r_k @ z - c_vec
    rms = math.sqrt(max(float(data @ data) + constant, 0.0) / n_rows)
    return ConsistentFit(full(phi, psi), k0 + null @ z, rms, n_rows, int(result.nfev))

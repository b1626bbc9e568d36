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
The chain and its physically consistent parameters refined together.

Variable projection scores a chain by its best parameters, consistent or not. Where the
data leave part of a chain weakly fixed (a light wrist's lines, for one), a wrong chain can
explain the torque as well as the right one, but only with parameters no body has; the
consistent fit of that chain then leaves several times the residual. :func:`refine_jointly`
moves the chain's numbers x and the bodies' log-Cholesky coordinates φ (and the joint
terms ψ) at once:

    minimise  ‖W (Y(x) π(φ, ψ) − τ)‖² / ‖W τ‖²  +  the priors of :mod:`..rigid.solve`
              +  λ Σ (L / LENGTH_SCALE)²

(the priors on φ and ψ of :mod:`..rigid.solve`, far weaker, :data:`JOINT_PRIOR_WEIGHT`;
λ the pull towards a compact arm of :func:`~.chain_search.refine`), by scipy's bounded
trust region with the exact Jacobian in φ and ψ and forward differences of the rows'
torques in x (one inverse dynamics per number, :meth:`~.chain_rows.ChainRows.torques`).
"""

import math
from typing import NamedTuple

import numpy as np

from .chain_rows import ChainRows
from .chain_search import ChainCoding, LENGTH_SCALE, LENGTH_UNIT
from ..rigid import consistency
from ..rigid.kernels import N_INERTIAL, N_JOINT
from ..rigid.solve import JOINT_SCALE, LENGTH_SCALE as BODY_LENGTH

__all__ = ['JOINT_PRIOR_WEIGHT', 'JointRefinement', 'refine_jointly']


class JointRefinement(NamedTuple):
    """What :func:`refine_jointly` found."""

    x: np.ndarray               # the chain's numbers
    parameters: np.ndarray      # full parameters (P,), every body realizable
    cost: float                 # ‖W (Y π − τ)‖² / ‖W τ‖² on the rows
    evaluations: int
    extra: np.ndarray = np.zeros(0)   # the coefficients of the rows' extra columns


#: λ per row of the pull towards the prior parameters: far weaker than a robot
#: description's (:data:`~..rigid.solve.PRIOR_WEIGHT`), as a learned chain's prior is only
#: a guess (bodies as balls at their joints).
JOINT_PRIOR_WEIGHT = 1e-9


class JointOptions(NamedTuple):
    """The solver options of :func:`refine_jointly`: iterations, difference step, prior weight."""

    max_iterations: int = 60
    step: float = 1e-6
    prior_weight: float = JOINT_PRIOR_WEIGHT
    extra0: object = None       # a start of the rows' extra coefficients (zeros)


def refine_jointly(rows: ChainRows, weights, coding: ChainCoding, x0, parameters0, prior,
                   length_prior: float = 0.0, **options) -> JointRefinement:
    """
    Return the chain and consistent parameters refined together (module docstring).

    ``x0``: the chain's numbers; ``parameters0`` (P,): a start (made realizable);
    ``prior`` (P,): what the parameters are pulled towards where the rows do not decide;
    ``length_prior``: λ. The rows' extra columns (case 3's gains), if any, are fitted
    along, free.
    """
    max_iterations, step, prior_weight, extra0 = JointOptions(**options)
    from scipy.optimize import least_squares
    n = coding.n
    nx, nphi, npsi = coding.size, N_INERTIAL * n, N_JOINT * n
    extra = np.zeros((rows.n_rows * n, 0)) if rows.extra is None else rows.extra
    ne = extra.shape[1]
    w = np.tile(np.asarray(weights, dtype=float), rows.n_rows)
    target = (rows.tau * np.asarray(weights, dtype=float)).reshape(-1)
    norm = max(float(np.linalg.norm(target)), 1e-300)
    lam = math.sqrt(prior_weight * target.size) / norm
    body_scale = np.ones(N_INERTIAL)
    body_scale[4:] = BODY_LENGTH
    s_phi = lam / np.tile(body_scale, n)
    s_psi = lam / np.tile(JOINT_SCALE, n)
    prior = np.asarray(prior, dtype=float)
    phi0 = consistency.coordinates(prior[:nphi].reshape(n, N_INERTIAL)).reshape(-1)
    psi0 = prior[nphi:].copy()
    pull = math.sqrt(max(length_prior, 0.0)) * LENGTH_UNIT / LENGTH_SCALE
    lengths = coding.lengths
    count = [0]

    def unpack(z):
        return z[:nx], z[nx:nx + nphi], z[nx + nphi:nx + nphi + npsi], z[nx + nphi + npsi:]

    def full(phi, psi):
        inertial = consistency.parameters(phi.reshape(n, N_INERTIAL)).reshape(-1)
        return np.concatenate([inertial, psi])

    def residual(z):
        x, phi, psi, k = unpack(z)
        count[0] += 1
        data = ((rows.torques(coding.tree(x), full(phi, psi)) + extra @ k) * w - target) / norm
        return np.concatenate([data, s_phi * (phi - phi0), s_psi * (psi - psi0),
                               pull * x[lengths]])

    def jacobian(z):
        x, phi, psi, _ = unpack(z)
        inertial, d_inertial = consistency.parameters(phi.reshape(n, N_INERTIAL),
                                                      jacobian=True)
        pi = np.concatenate([inertial.reshape(-1), psi])
        tree = coding.tree(x)
        here = rows.torques(tree, pi)
        j_x = np.empty((target.size, nx))
        for k in range(nx):
            moved = x.copy()
            moved[k] += step
            j_x[:, k] = (rows.torques(coding.tree(moved), pi) - here) / step
        a = rows.design(tree)
        j_phi = np.concatenate([a[:, N_INERTIAL * i:N_INERTIAL * (i + 1)] @ d_inertial[i]
                                for i in range(n)], axis=1)
        top = np.hstack([j_x, j_phi, a[:, nphi:], extra]) * (w / norm)[:, None]
        size = nx + nphi + npsi + ne
        bottom = np.zeros((nphi + npsi + lengths.size, size))
        bottom[np.arange(nphi), nx + np.arange(nphi)] = s_phi
        bottom[nphi + np.arange(npsi), nx + nphi + np.arange(npsi)] = s_psi
        bottom[nphi + npsi + np.arange(lengths.size), lengths] = pull
        return np.vstack([top, bottom])

    lower = np.full(nx + nphi + npsi + ne, -np.inf)
    upper = np.full(nx + nphi + npsi + ne, np.inf)
    lower[:nx], upper[:nx] = coding.bounds()
    for j in range(n):      # rotor inertia, viscous and Coulomb friction >= 0
        lower[nx + nphi + N_JOINT * j:nx + nphi + N_JOINT * j + 3] = 0.0
    start = np.asarray(parameters0, dtype=float)
    z0 = np.concatenate([np.clip(x0, lower[:nx], upper[:nx]),
                         consistency.coordinates(start[:nphi].reshape(n, N_INERTIAL)).reshape(-1),
                         np.clip(start[nphi:], lower[nx + nphi:nx + nphi + npsi], None),
                         np.zeros(ne) if extra0 is None else np.asarray(extra0, dtype=float)])
    # the solver refuses a trial step that overflows: no warning for it in the log
    with np.errstate(over='ignore', invalid='ignore'):
        result = least_squares(residual, z0, jac=jacobian, bounds=(lower, upper),
                               method='trf', x_scale='jac', max_nfev=int(max_iterations),
                               xtol=1e-10, ftol=1e-10, gtol=1e-10)
    x, phi, psi, k = unpack(result.x)
    pi = full(phi, psi)
    data = (rows.torques(coding.tree(x), pi) + extra @ k) * w - target
    return JointRefinement(coding.wrap(x), pi, float(data @ data) / norm ** 2, count[0], k)

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
Equation-error warm start: the network's output weights by linear least squares.

With the RBF centres and widths fixed, the inverse dynamics of the network

    M(θ) θ̈ + V(θ, θ̇) + G(θ) + F(θ̇) = τ

is linear in every output weight when M is parametrised directly (``inertia='penalty'``):
each weight multiplies a known regressor (φ_k(θ) θ̈_j for M, φ_k(θ) θ̇_j θ̇_k for B, ...).
Given θ̈ estimated from the measured θ̇ (Savitzky-Golay derivative), one least-squares solve
gives weights that already explain the data; the evolutionary search then refines them on
the rollout (output) error, which is what long-horizon prediction needs. In case 3 the
torque network's weights join the unknowns and the system is homogeneous (the gauge
freedom of that case): the solution is the smallest right singular vector, scaled so that
M's diagonal matches the inertia scale on average.

This is the classical two-stage route of system identification (equation error, then
output error); the paper starts its evolution from random weights instead.
"""

from typing import Optional, Sequence

import numpy as np
from scipy.optimize import lsq_linear

from ..model.network import BatchedNetwork, features
from ..model.scales import Scales
from ..model.spec import NetworkSpec

# Genome blocks solved here; everything else (centres, widths) is kept from the start genome.
LINEAR_BLOCKS = ('theta_weights', 'theta_bias', 'friction', 'pd_linear')


def estimate_acceleration(theta_dot, dt, window=7, polyorder=3):
    """
    θ̈ from sampled θ̇ by a Savitzky-Golay derivative (exact for polynomials up to order 3).

    Parameters
    ----------
    theta_dot : ndarray, shape (N, n)
        Velocities.
    dt : float
        Sampling interval.
    window : int
        Odd window length in samples (shrunk for short data).
    polyorder : int
        Order of the local polynomial.

    Returns
    -------
    ndarray, shape (N, n)

    """
    n_samples = theta_dot.shape[0]
    window = min(window, n_samples if n_samples % 2 else n_samples - 1)
    if window <= polyorder:
        return np.gradient(theta_dot, dt, axis=0)
    from scipy.signal import savgol_filter  # at first use: scipy.signal imports in 0.8 s
    return savgol_filter(theta_dot, window, polyorder, deriv=1, delta=dt, axis=0,
                         mode='interp')


def _design(spec: NetworkSpec, scales: Scales, params, theta, theta_dot, theta_ddot,
            err, derr):
    """
    Regressors of the linear genome elements, shape (N*n, L), and their genome indices.

    Row ``t * n + i`` is joint i at sample t of M θ̈ + V + G + F - τ_network.
    """
    n = spec.n_joints
    n_samples = theta.shape[0]
    blocks = {b.name: b for b in spec.blocks()}
    out_scale = spec.output_scales(scales)
    sl = spec.output_slices()
    n_out = spec.n_outputs
    # φ of the θ features at every sample, (N, F); the bias is a feature with φ = 1
    phi = features(spec, params, theta)
    # r[t, i, o]: how output o (in physical units) enters row i at sample t
    r = np.zeros((n_samples, n, n_out))
    idx = sl['inertia'].start
    for i in range(n):
        for j in range(i, n):
            r[:, i, idx] += theta_ddot[:, j]
            if j != i:
                r[:, j, idx] += theta_ddot[:, i]
            idx += 1
    pairs = [(j, k) for j in range(n) for k in range(j + 1, n)]
    base = sl['coriolis'].start
    for i in range(n):
        for p, (j, k) in enumerate(pairs):
            r[:, i, base + i * len(pairs) + p] = theta_dot[:, j] * theta_dot[:, k]
    base = sl['centrifugal'].start
    for i in range(n):
        for j in range(n):
            r[:, i, base + i * n + j] = theta_dot[:, j] ** 2
    base = sl['gravity'].start
    for i in range(n):
        r[:, i, base + i] = 1.0
    r = r * out_scale[None, None, :]
    columns, index = [], []
    b = blocks['theta_weights']
    # weight (o, f) -> regressor r[:, :, o] * φ_f
    cols = r[:, :, :, None] * phi[:, None, None, :]  # (N, n, n_out, F)
    columns.append(cols.reshape(n_samples * n, -1))
    index.append(np.arange(b.start, b.stop))
    if 'theta_bias' in blocks:
        b = blocks['theta_bias']
        columns.append(r.reshape(n_samples * n, n_out))
        index.append(np.arange(b.start, b.stop))
    if 'friction' in blocks:
        b = blocks['friction']
        fr = np.zeros((n_samples, n, 2, n))
        for i in range(n):
            fr[:, i, 0, i] = 0.1 * scales.torque[i] / scales.velocity[i] * theta_dot[:, i]
            coulomb = np.tanh(theta_dot[:, i] / spec.coulomb_velocity)
            fr[:, i, 1, i] = 0.1 * scales.torque[i] * coulomb
        columns.append(fr.reshape(n_samples * n, 2 * n))
        index.append(np.arange(b.start, b.stop))
    if 'pd_linear' in blocks:
        b = blocks['pd_linear']
        lin = np.zeros((n_samples, n, 2, n))
        for i in range(n):
            lin[:, i, 0, i] = -scales.torque[i] / scales.error[i] * err[:, i]
            lin[:, i, 1, i] = -scales.torque[i] / scales.error_rate[i] * derr[:, i]
        columns.append(lin.reshape(n_samples * n, 2 * n))
        index.append(np.arange(b.start, b.stop))
    for name, e, centres, inv_width2 in (('p', err, params.p_centres, params.p_inv_width2),
                                         ('d', derr, params.d_centres, params.d_inv_width2)):
        if f'{name}_net' not in blocks:
            continue
        b = blocks[f'{name}_net']
        kt = spec.torque_units
        # weights are the third slab of the (3, n, Kt) block
        phi_e = np.exp(-np.square(e[:, :, None] - centres[0][None])
                       * inv_width2[0][None])  # (N, n, Kt)
        cols = np.zeros((n_samples, n, n, kt))
        for i in range(n):
            cols[:, i, i, :] = -scales.torque[i] * phi_e[:, i, :]
        columns.append(cols.reshape(n_samples * n, n * kt))
        index.append(b.start + 2 * n * kt + np.arange(n * kt))
    return np.hstack(columns), np.concatenate(index)


def least_squares_genome(spec: NetworkSpec, datasets: Sequence, scales: Scales,
                         genome: Optional[np.ndarray] = None, kp=None, kd=None,
                         ridge=1e-8, window=7) -> np.ndarray:
    """
    Return ``genome`` with its linear elements set by equation-error least squares.

    Parameters
    ----------
    spec : NetworkSpec
        Must use ``inertia='penalty'`` (M linear in the weights).
    datasets : list of Dataset
        Training segments.
    scales : Scales
        The scales the genome is decoded with.
    genome : ndarray, shape (N,), optional
        Start genome (centres and widths are kept); ``spec.initial_genome()`` by default.
    kp, kd : array_like, shape (n,), optional
        Known gains (case 'pd_gains').
    ridge : float
        Tikhonov weight relative to the mean squared column norm (keeps unused units at 0).
    window : int
        Savitzky-Golay window for θ̈.

    Returns
    -------
    ndarray, shape (N,)

    """
    if spec.velocity != 'learned':
        raise ValueError("the least-squares warm start needs velocity='learned'")
    if spec.inertia != 'penalty':
        raise ValueError("the least-squares warm start needs inertia='penalty' "
                         '(M = L Lᵀ is not linear in the weights)')
    g = np.array(spec.initial_genome() if genome is None else genome, dtype=float)
    params = spec.decode(g[None], scales)
    rows, targets = [], []
    for d in datasets:
        acc = estimate_acceleration(d.theta_dot, d.dt, window)
        if spec.case in ('pd_gains', 'unknown'):
            err = d.theta_d - d.theta
            derr = d.theta_d_dot - d.theta_dot
        else:
            err = derr = np.zeros_like(d.theta)
        a, index = _design(spec, scales, params, d.theta, d.theta_dot, acc, err, derr)
        if spec.case == 'torque':
            tau = d.tau
        elif spec.case == 'pd_gains':
            tau = err * np.asarray(kp, dtype=float) + derr * np.asarray(kd, dtype=float)
        else:
            tau = np.zeros_like(d.theta)
        # weight each joint's equations by its torque scale, so all joints count alike
        w = np.tile(1.0 / scales.torque, d.n_samples)
        rows.append(a * w[:, None])
        targets.append(tau.reshape(-1) * w)
    a = np.vstack(rows)
    b = np.concatenate(targets)
    prior = g[index].copy()
    col_norm = np.sqrt(np.mean(np.square(a), axis=0)) + 1e-300
    a_n = a / col_norm
    lam = ridge * a_n.shape[0]
    if spec.case == 'unknown':
        # homogeneous: smallest right singular vector of [A; sqrt(lam) I]
        _, _, vt = np.linalg.svd(np.vstack([a_n, np.sqrt(lam) * np.eye(a_n.shape[1])]),
                                 full_matrices=False)
        sol = vt[-1] / col_norm
    else:
        # ridge towards the start genome (M = diagonal inertia scale), not towards zero;
        # friction coefficients bounded below by 0 (they dissipate)
        lower = np.full(index.size, -np.inf)
        fric = next((blk for blk in spec.blocks() if blk.name == 'friction'), None)
        if fric is not None:
            lower[(index >= fric.start) & (index < fric.stop)] = 0.0
        big = np.vstack([a_n, np.sqrt(lam) * np.eye(a_n.shape[1])])
        rhs = np.concatenate([b, np.sqrt(lam) * prior * col_norm])
        res = lsq_linear(big, rhs, bounds=(lower * col_norm, np.inf), method='bvls'
                         if index.size <= 400 else 'trf', lsmr_tol='auto')
        sol = res.x / col_norm
    g[index] = sol
    if spec.case == 'unknown':
        g = _fix_gauge(spec, scales, g, datasets)
    return g


def _fix_gauge(spec, scales, g, datasets):
    """Scale the linear elements so that mean diag(M)/inertia scale = 1 (case 3 gauge)."""
    theta = np.vstack([d.theta for d in datasets])
    step = max(1, theta.shape[0] // 200)
    net = BatchedNetwork(spec, spec.decode(g[None], scales), scales)
    diag = np.array([np.diagonal(net.mass_matrix(th[None])[0]) for th in theta[::step]])
    level = float(np.mean(diag / scales.inertia))
    if not np.isfinite(level) or level == 0.0:
        return g
    index = np.concatenate([np.arange(b.start, b.stop) for b in spec.blocks()
                            if b.name in LINEAR_BLOCKS])
    for name in ('p_net', 'd_net'):
        b = next((blk for blk in spec.blocks() if blk.name == name), None)
        if b is not None:
            nkt = spec.n_joints * spec.torque_units
            index = np.concatenate([index, b.start + 2 * nkt + np.arange(nkt)])
    g = g.copy()
    g[index] /= level
    return g

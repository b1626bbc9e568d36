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
Compiled N_f and its rollouts (numba): the same arithmetic as the numpy reference.

The kernels take named records (:mod:`.params`): the decoded population
(:class:`.params.NetworkParams`), what the structure fixes (:class:`.params.NetworkConstants`)
and the measured segments with their stage inputs (:class:`Segments`). One call evaluates a
whole population in parallel over individuals (``prange``) and releases the GIL (``nogil``),
so the ROS executor keeps running while the identifier's worker thread evaluates a
generation. A diverged rollout stops early and costs +inf.

N_f is written out inline in the stage loop (its helpers are ``inline='always'`` and take
the arrays they compute on): a call per evaluation, or a record member read per use, would
cost more reference counting than the arithmetic, so the records are read once per sampling
interval (:func:`_advance`). The θ features come from the basis registry's dispatch on kind
codes, so adding a basis changes no kernel here; every kernel compiles in two versions, for
networks of the default basis alone (inlined) and for the others (``c.inlined``, passed on
as a compile-time constant). The integration step is the package's one Runge-Kutta-Gill
stage update (:func:`..integration.rkg.gill_stage`).

Compiled functions are cached on disk (``cache=True``); the first call compiles (seconds).
numba's cache notices changes of this file only, so :func:`ensure_current` (run at import)
recompiles when a file whose code is inlined here (the bases, the registry, the RKG update)
changed since the cache was written.
"""

import math
from typing import NamedTuple
import zlib

from numba import literally, njit, prange
import numpy as np

from . import linalg
from . import params as params_module
from .basis import registry
from .linalg import det, solve
from .params import individual
from ..integration import rkg
from ..integration.rkg import gill_node, gill_stage
from ..servo_law import compiled_pd_torque


class Segments(NamedTuple):
    """
    Measured segments and the inputs of a rollout over them.

    Attributes
    ----------
    x_meas : ndarray, shape (N_total, 2n)
        Measured states of all segments, stacked.
    seg_start : ndarray of int64, shape (S + 1,)
        Row where each segment starts; the last entry is N_total.
    u_flat : ndarray, shape (N_total - S, substeps, 3, m)
        Input at the stage times of every interval (see :mod:`..integration.inputs`).
    h : float
        RKG step.
    substeps : int
        RKG steps per sampling interval.
    shooting : int
        0, or restart from the measured state every ``shooting`` samples.
    bound_center, bound_scale : ndarray, shape (2n,)
        A rollout has diverged when a state leaves ``center ± scale``.

    """

    x_meas: np.ndarray
    seg_start: np.ndarray
    u_flat: np.ndarray
    h: float
    substeps: int
    shooting: int
    bound_center: np.ndarray
    bound_scale: np.ndarray


class Buffers(NamedTuple):
    """Work arrays of one model's evaluations (allocated once per rollout)."""

    phi: np.ndarray         # (F,) features
    work: np.ndarray        # the bases' work table
    out: np.ndarray         # (n_out,) θ outputs
    mat: np.ndarray         # (n, n) M
    lmat: np.ndarray        # (n, n) L (Cholesky mode)
    scratch: np.ndarray     # (n, n) minors
    rhs: np.ndarray         # (n,)
    acc: np.ndarray         # (n,) θ̈
    xs: np.ndarray          # (2n,) stage state
    k: np.ndarray           # (2n,) rate
    q: np.ndarray           # (2n,) Gill's accumulator
    dout: np.ndarray        # (n, n(n+1)/2) ∂(inertia outputs)/∂θ
    dl: np.ndarray          # (n, n) Christoffel work
    dmat: np.ndarray        # (n, n, n) ∂M/∂θ (penalty mode)
    vvec: np.ndarray        # (n,) V


def _dependencies_fingerprint() -> int:
    """Return a checksum of the files whose compiled code is linked into these kernels."""
    crc = registry.source_fingerprint()
    for module in (rkg, params_module, linalg):
        with open(module.__file__, 'rb') as f:
            crc = zlib.crc32(f.read(), crc)
    return int(crc)


_FINGERPRINT = _dependencies_fingerprint()


@njit(cache=True)
def _compiled_fingerprint():
    """Return the fingerprint this file's cached kernels were compiled with."""
    return _FINGERPRINT


@njit(cache=True, nogil=True)
def buffers(c, p):
    """Allocate the work arrays of one model ``p`` (a row of a population record)."""
    n = c.eps.shape[0]
    n_feat = c.codes.shape[0]
    return Buffers(np.empty(n_feat), np.zeros((c.work_rows, c.work_cols)),
                   np.empty(p.weights.shape[0]), np.empty((n, n)), np.empty((n, n)),
                   np.empty((n, n)), np.empty(n),
                   np.empty(n), np.empty(2 * n), np.empty(2 * n), np.empty(2 * n),
                   np.empty((n, n * (n + 1) // 2)), np.empty((n, n)), np.empty((n, n, n)),
                   np.empty(n))


@njit(cache=True, nogil=True, error_model='numpy', inline='always')
def _theta_outputs(x, n, bases, kinds, codes, feats, weights, bias, work, phi, out, inlined):
    """Fill ``phi`` and ``out`` with the features and the θ outputs at x (θ = x[:n])."""
    registry.prepare(x, n, bases, work, inlined)
    registry.features(x, n, kinds, codes, feats, work, phi, inlined)
    n_feat = codes.shape[0]
    for o in range(out.shape[0]):
        acc = 0.0
        for kk in range(n_feat):
            acc += weights[o, kk] * phi[kk]
        out[o] = acc + bias[o]


@njit(cache=True, nogil=True, error_model='numpy', inline='always')
def _mass(out, n, chol, eps, mat, lmat):
    idx = 0
    if chol:
        for i in range(n):
            for j in range(n):
                lmat[i, j] = 0.0
        for i in range(n):
            for j in range(i + 1):
                lmat[i, j] = out[idx]
                idx += 1
        for i in range(n):
            for j in range(n):
                acc = 0.0
                for k in range(min(i, j) + 1):
                    acc += lmat[i, k] * lmat[j, k]
                mat[i, j] = acc
            mat[i, i] += eps[i]
    else:
        for i in range(n):
            for j in range(i, n):
                mat[i, j] = out[idx]
                mat[j, i] = out[idx]
                idx += 1


@njit(cache=True, nogil=True, error_model='numpy')
def _min_minor(x, n, c, p, b, inlined):
    """Return the smallest leading principal minor of the normalised M at x."""
    literally(inlined)
    out, mat, scratch, inv_sqrt_ms = b.out, b.mat, b.scratch, c.inv_sqrt_ms
    _theta_outputs(x, n, c.bases, c.kinds, c.codes, p.features, p.weights, p.bias, b.work,
                   b.phi, out, inlined)
    _mass(out, n, c.chol, c.eps, mat, b.lmat)
    worst = np.inf
    for k in range(1, n + 1):
        for i in range(n):
            for j in range(n):
                scratch[i, j] = mat[i, j] * inv_sqrt_ms[i] * inv_sqrt_ms[j]
        d = det(scratch, k)
        if d < worst:
            worst = d
    return worst


@njit(cache=True, nogil=True, error_model='numpy', inline='always')
def _christoffel(xs, n, chol, bases, starts, codes, feats, weights, work, phi, lmat, dout, dl,
                 dmat, vvec, y, z, inlined):
    """
    Fill vvec with V = Ṁθ̇ - ½ ∂(θ̇ᵀMθ̇)/∂θ from the inertia outputs (phi, lmat set).

    With w_k = (∂M/∂θ_k) θ̇, V_a = Σ_k θ̇_k w_k[a] - ½ Σ_j θ̇_j w_a[j]. For M = L Lᵀ + εI,
    ∂M/∂θ_k = (∂L/∂θ_k) Lᵀ + L (∂L/∂θ_k)ᵀ, so w_k = (∂L/∂θ_k) y + L (∂L/∂θ_k)ᵀ θ̇ with
    y = Lᵀθ̇: triangular products, no n x n x n tensor. dl holds w (row k = w_k), y and z
    are work vectors; dmat is used only without ``chol`` (M's outputs are M itself).
    """
    n_in = n * (n + 1) // 2
    # dout[k, o] = ∂out_o/∂θ_k = Σ_f weights[o, f] ∂φ_f/∂θ_k
    for kk in range(n):
        for o in range(n_in):
            dout[kk, o] = 0.0
    registry.output_gradients(xs, n, bases, starts, codes, feats, work, phi, weights, n_in,
                              dout, inlined)
    if chol:
        # outputs fill L row by row: L[i, m] = out[i (i + 1) / 2 + m], m <= i
        for m in range(n):
            acc = 0.0
            for j in range(m, n):
                acc += lmat[j, m] * xs[n + j]
            y[m] = acc
        for kk in range(n):
            for m in range(n):
                acc = 0.0
                for j in range(m, n):
                    acc += dout[kk, j * (j + 1) // 2 + m] * xs[n + j]
                z[m] = acc
            for a in range(n):
                base = a * (a + 1) // 2
                acc = 0.0
                for m in range(a + 1):
                    acc += dout[kk, base + m] * y[m] + lmat[a, m] * z[m]
                dl[kk, a] = acc
    else:
        for kk in range(n):
            idx = 0
            for i in range(n):
                for j in range(i, n):
                    dmat[kk, i, j] = dout[kk, idx]
                    dmat[kk, j, i] = dout[kk, idx]
                    idx += 1
            for a in range(n):
                acc = 0.0
                for j in range(n):
                    acc += dmat[kk, a, j] * xs[n + j]
                dl[kk, a] = acc
    for a in range(n):
        v = 0.0
        for kk in range(n):
            v += xs[n + kk] * dl[kk, a] - 0.5 * xs[n + kk] * dl[a, kk]
        vvec[a] = v


@njit(cache=True, nogil=True, error_model='numpy', inline='always')
def _learned_velocity(xs, n, out, vvec):
    """Fill vvec with the paper's V = B(θ)[θ̇θ̇] + C(θ)[θ̇²] from the learned RBF outputs."""
    n_pairs = n * (n - 1) // 2
    off_b = n * (n + 1) // 2
    off_c = off_b + n * n_pairs
    for a in range(n):
        v = 0.0
        p = 0
        for j in range(n):
            for jj in range(j + 1, n):
                v += out[off_b + a * n_pairs + p] * xs[n + j] * xs[n + jj]
                p += 1
        for j in range(n):
            v += out[off_c + a * n + j] * xs[n + j] * xs[n + j]
        vvec[a] = v


@njit(cache=True, nogil=True, error_model='numpy')
def _advance(x, u_flat, row, h, substeps, c, p, b, inlined):
    """
    Advance x in place over one sampling interval: ``substeps`` RKG steps of N_f.

    N_f is written out in the stage loop, on the records' members bound to local names
    once per interval (numba counts a reference each time a loop reads an array out of a
    record). The input of stage ``stage`` of substep ``s`` is
    ``u_flat[row, s, gill_node(stage)]`` (the stage times t, t + h/2, t + h/2, t + h).
    ``inlined`` (``c.inlined`` as a constant) compiles one version for networks of the
    default basis alone, one for the others (:mod:`.basis.registry`).
    """
    literally(inlined)
    n2 = x.shape[0]
    n = n2 // 2
    case_id, chol, christ, vc = c.case_id, c.chol, c.christ, c.coulomb_velocity
    bases, starts, kinds, codes, eps = c.bases, c.starts, c.kinds, c.codes, c.eps
    kp_known, kd_known = c.kp_known, c.kd_known
    feats, weights, bias, viscous, coulomb = p.features, p.weights, p.bias, p.viscous, p.coulomb
    pc, piw, pw, dc, diw, dw = (p.p_centres, p.p_inv_width2, p.p_weights, p.d_centres,
                                p.d_inv_width2, p.d_weights)
    kp, kd = p.kp, p.kd
    phi, work, out, mat, lmat = b.phi, b.work, b.out, b.mat, b.lmat
    rhs, acc, xs, k, q = b.rhs, b.acc, b.xs, b.k, b.q
    dout, dl, dmat, vvec = b.dout, b.dl, b.dmat, b.vvec
    # G follows the inertia outputs, and the learned B and C outputs when present
    off_g = n * (n + 1) // 2 if christ else n * (n + 1) // 2 + n * n * (n - 1) // 2 + n * n
    n_pu = pc.shape[1]
    n_du = dc.shape[1]
    for s in range(substeps):
        for j in range(n2):
            xs[j] = x[j]
        for stage in range(4):
            ui = gill_node(stage)
            # ---- k = N_f(xs, u): θ outputs, M, V, then θ̈ = M⁻¹ (τ - V - G - F)
            _theta_outputs(xs, n, bases, kinds, codes, feats, weights, bias, work, phi, out,
                           inlined)
            _mass(out, n, chol, eps, mat, lmat)
            if christ:
                # rhs and acc are free until the solve below: the work vectors y, z
                _christoffel(xs, n, chol, bases, starts, codes, feats, weights, work, phi, lmat,
                             dout, dl, dmat, vvec, rhs, acc, inlined)
            else:
                _learned_velocity(xs, n, out, vvec)
            for a in range(n):
                qd = xs[n + a]
                if case_id == 0:
                    tau = u_flat[row, s, ui, a]
                else:
                    err = u_flat[row, s, ui, a] - xs[a]
                    derr = u_flat[row, s, ui, n + a] - qd
                    if case_id == 1:
                        tau = compiled_pd_torque(kp_known[a], kd_known[a], err, derr)
                    else:
                        tau = compiled_pd_torque(kp[a], kd[a], err, derr)
                        for kk in range(n_pu):
                            diff = err - pc[a, kk]
                            tau += pw[a, kk] * math.exp(-diff * diff * piw[a, kk])
                        for kk in range(n_du):
                            diff = derr - dc[a, kk]
                            tau += dw[a, kk] * math.exp(-diff * diff * diw[a, kk])
                f = viscous[a] * qd + coulomb[a] * math.tanh(qd / vc)
                rhs[a] = tau - vvec[a] - out[off_g + a] - f
                k[a] = qd
            solve(mat, rhs, acc)
            for a in range(n):
                k[n + a] = acc[a]
            # ---- the package's Runge-Kutta-Gill stage update
            gill_stage(stage, h, x, xs, k, q)


@njit(cache=True, nogil=True, error_model='numpy')
def _individual_cost(seg, c, p, penalty_weight, n_predicted, inlined):
    """Return the cost J of one model ``p`` on the segments ``seg`` (see fitness.py)."""
    literally(inlined)
    x_meas = seg.x_meas
    n2 = x_meas.shape[1]
    n = n2 // 2
    b = buffers(c, p)
    x = np.empty(n2)
    total = 0.0
    worst = np.inf
    u_row = 0
    for segment in range(seg.seg_start.shape[0] - 1):
        start = seg.seg_start[segment]
        n_samples = seg.seg_start[segment + 1] - start
        for j in range(n2):
            x[j] = x_meas[start, j]
        if not c.chol:
            worst = min(worst, _min_minor(x, n, c, p, b, inlined))
        for i in range(n_samples - 1):
            if seg.shooting > 0 and i > 0 and i % seg.shooting == 0:
                for j in range(n2):
                    x[j] = x_meas[start + i, j]
            _advance(x, seg.u_flat, u_row + i, seg.h, seg.substeps, c, p, b, inlined)
            e_pos = 0.0
            e_vel = 0.0
            for j in range(n2):
                xj = x[j]
                if not (abs(xj - seg.bound_center[j]) <= seg.bound_scale[j]):  # also NaN
                    return np.inf
                diff = xj - x_meas[start + i + 1, j]
                if j < n:
                    e_pos += diff * diff
                else:
                    e_vel += diff * diff
            total += math.sqrt(e_pos) + math.sqrt(e_vel)
            if not c.chol:
                worst = min(worst, _min_minor(x, n, c, p, b, inlined))
        u_row += n_samples - 1
    cost = total / n_predicted
    if not c.chol and worst < 0.0:
        cost += penalty_weight * (-worst)
    if not math.isfinite(cost):
        return np.inf
    return cost


@njit(cache=True, nogil=True, error_model='numpy')
def rollout(x0, u_flat, h, substeps, c, p, bound_center, bound_scale):
    """
    Predicted states of one model ``p`` (a population record's row) from x0.

    Returns
    -------
    ndarray, shape (u_flat.shape[0] + 1, 2n)
        States at the sample times; rows after a divergence are NaN.

    """
    n2 = x0.shape[0]
    n_int = u_flat.shape[0]
    states = np.full((n_int + 1, n2), np.nan)
    b = buffers(c, p)
    x = x0.copy()
    for j in range(n2):
        states[0, j] = x[j]
    for i in range(n_int):
        if c.inlined:
            _advance(x, u_flat, i, h, substeps, c, p, b, True)
        else:
            _advance(x, u_flat, i, h, substeps, c, p, b, False)
        for j in range(n2):
            if not (abs(x[j] - bound_center[j]) <= bound_scale[j]):
                return states
        for j in range(n2):
            states[i + 1, j] = x[j]
    return states


@njit(cache=True, nogil=True, parallel=True, error_model='numpy')
def population_cost(seg, c, params, penalty_weight, n_predicted):
    """
    Costs of a population (:class:`..fitting.fitness.FitnessProblem` builds the records).

    Returns
    -------
    ndarray, shape (P,)

    """
    pop = params.weights.shape[0]
    costs = np.empty(pop)
    for p in prange(pop):
        # private copies: views would share their parent's reference count between threads
        own = Segments(seg.x_meas.copy(), seg.seg_start, seg.u_flat, seg.h, seg.substeps,
                       seg.shooting, seg.bound_center, seg.bound_scale)
        if c.inlined:
            costs[p] = _individual_cost(own, c, individual(params, p), penalty_weight,
                                        n_predicted, True)
        else:
            costs[p] = _individual_cost(own, c, individual(params, p), penalty_weight,
                                        n_predicted, False)
    return costs


@njit(cache=True, nogil=True, parallel=True, error_model='numpy')
def population_rollouts(seg, c, params):
    """
    Predicted states of a population over all segments, with multiple shooting.

    Row k of the result predicts ``seg.x_meas[k]``; the first row of each segment is the
    measurement itself. Rows after a divergence (within the same shooting window) are NaN.

    Returns
    -------
    ndarray, shape (P, seg.x_meas.shape[0], 2n)

    """
    pop = params.weights.shape[0]
    x_meas = seg.x_meas
    n_rows, n2 = x_meas.shape
    result = np.full((pop, n_rows, n2), np.nan)
    for p in prange(pop):
        own = individual(params, p)
        b = buffers(c, own)
        x = np.empty(n2)
        u_row = 0
        for segment in range(seg.seg_start.shape[0] - 1):
            start = seg.seg_start[segment]
            n_samples = seg.seg_start[segment + 1] - start
            alive = True
            for j in range(n2):
                x[j] = x_meas[start, j]
                result[p, start, j] = x[j]
            for i in range(n_samples - 1):
                if seg.shooting > 0 and i > 0 and i % seg.shooting == 0:
                    alive = True
                    for j in range(n2):
                        x[j] = x_meas[start + i, j]
                if alive:
                    if c.inlined:
                        _advance(x, seg.u_flat, u_row + i, seg.h, seg.substeps, c, own, b, True)
                    else:
                        _advance(x, seg.u_flat, u_row + i, seg.h, seg.substeps, c, own, b,
                                 False)
                    for j in range(n2):
                        if not (abs(x[j] - seg.bound_center[j]) <= seg.bound_scale[j]):
                            alive = False
                    if alive:
                        for j in range(n2):
                            result[p, start + i + 1, j] = x[j]
            u_row += n_samples - 1
    return result


@njit(cache=True, nogil=True, error_model='numpy')
def _inverse_dynamics_terms(x, acc, c, p, out_mv, out_diag, inlined):
    """M θ̈ + V + G of one model ``p`` at every sample into ``out_mv`` (S, n), diag M too."""
    literally(inlined)
    samples, n = out_mv.shape
    n_in = n * (n + 1) // 2
    n_pairs = n * (n - 1) // 2
    g0 = n_in if c.christ else n_in + n * n_pairs + n * n
    b = buffers(c, p)
    out, mat, vvec = b.out, b.mat, b.vvec
    for s in range(samples):
        xs = x[s]
        _theta_outputs(xs, n, c.bases, c.kinds, c.codes, p.features, p.weights, p.bias,
                       b.work, b.phi, out, inlined)
        _mass(out, n, c.chol, c.eps, mat, b.lmat)
        if c.christ:
            _christoffel(xs, n, c.chol, c.bases, c.starts, c.codes, p.features, p.weights,
                         b.work, b.phi, b.lmat, b.dout, b.dl, b.dmat, vvec, b.rhs, b.acc,
                         inlined)
        else:
            _learned_velocity(xs, n, out, vvec)
        for i in range(n):
            acc_i = vvec[i] + out[g0 + i]
            for j in range(n):
                acc_i += mat[i, j] * acc[s, j]
            out_mv[s, i] = acc_i
            out_diag[s, i] = mat[i, i]


@njit(cache=True, nogil=True, parallel=True, error_model='numpy')
def inverse_dynamics_terms(x, acc, c, params, out_mv, out_diag):
    """
    M θ̈ + V + G per (model, sample) into ``out_mv`` (P, S, n); diag M into ``out_diag``.

    ``x`` (S, 2n) are states and ``acc`` (S, n) accelerations: the equation error's
    left-hand side without friction, for a whole population in parallel.
    """
    # each model's work runs in a function of its own, as in population_cost: with the
    # inlined helpers writing into a record of buffers directly in the prange body, numba
    # 0.68's parallel lowering computed garbage
    for p in prange(out_mv.shape[0]):
        if c.inlined:
            _inverse_dynamics_terms(x, acc, c, individual(params, p), out_mv[p], out_diag[p],
                                    True)
        else:
            _inverse_dynamics_terms(x, acc, c, individual(params, p), out_mv[p], out_diag[p],
                                    False)


_KERNELS = (_compiled_fingerprint, buffers, _min_minor, _advance, _individual_cost, rollout,
            population_cost, population_rollouts, _inverse_dynamics_terms,
            inverse_dynamics_terms)


def ensure_current() -> bool:
    """
    Recompile the kernels if a file inlined into them changed since numba cached them.

    numba's disk cache is keyed on this file only; a changed basis, registry or RKG update
    would otherwise run stale compiled code. Returns whether the cache was stale.
    """
    if _compiled_fingerprint() == _FINGERPRINT:
        return False
    for kernel in registry.COMPILED + _KERNELS:
        kernel.recompile()
    return True


ensure_current()

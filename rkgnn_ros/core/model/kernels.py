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
Compiled fitness kernel (numba): the same arithmetic as the numpy reference in fitness.py.

One call evaluates a whole population in parallel over individuals (``prange``) and
releases the GIL (``nogil``), so the ROS executor keeps running while the identifier's
worker thread evaluates a generation. A diverged rollout stops early and costs +inf.
Compiled functions are cached on disk (``cache=True``); the first call compiles (seconds).
"""

import math

from numba import njit, prange
import numpy as np

from ..integration.rkg import ALPHA, BETA, D, E, G, GAMMA


@njit(cache=True, nogil=True, error_model='numpy', inline='always')
def _solve(a, b, out):
    """Solve a @ out = b by Gaussian elimination with partial pivoting (a, b overwritten)."""
    n = b.shape[0]
    for k in range(n):
        piv = k
        big = abs(a[k, k])
        for r in range(k + 1, n):
            if abs(a[r, k]) > big:
                big = abs(a[r, k])
                piv = r
        if big == 0.0:
            for r in range(n):
                out[r] = np.nan
            return
        if piv != k:
            for c in range(n):
                tmp = a[k, c]
                a[k, c] = a[piv, c]
                a[piv, c] = tmp
            tmp = b[k]
            b[k] = b[piv]
            b[piv] = tmp
        for r in range(k + 1, n):
            f = a[r, k] / a[k, k]
            if f != 0.0:
                for c in range(k, n):
                    a[r, c] -= f * a[k, c]
                b[r] -= f * b[k]
    for r in range(n - 1, -1, -1):
        acc = b[r]
        for c in range(r + 1, n):
            acc -= a[r, c] * out[c]
        out[r] = acc / a[r, r]


@njit(cache=True, nogil=True, error_model='numpy')
def _det(a, k):
    """Return the determinant of the leading k x k block of a (a is overwritten)."""
    det = 1.0
    for j in range(k):
        piv = j
        big = abs(a[j, j])
        for r in range(j + 1, k):
            if abs(a[r, j]) > big:
                big = abs(a[r, j])
                piv = r
        if big == 0.0:
            return 0.0
        if piv != j:
            det = -det
            for c in range(k):
                tmp = a[j, c]
                a[j, c] = a[piv, c]
                a[piv, c] = tmp
        det *= a[j, j]
        for r in range(j + 1, k):
            f = a[r, j] / a[j, j]
            for c in range(j, k):
                a[r, c] -= f * a[j, c]
    return det


@njit(cache=True, nogil=True, error_model='numpy')
def _theta_outputs(x, centres, inv_w2, weights, bias, phi, out):
    # x holds [θ, θ̇]; only θ (the first centres.shape[1] entries) is used
    n_units = centres.shape[0]
    n = centres.shape[1]
    for k in range(n_units):
        d2 = 0.0
        for j in range(n):
            diff = x[j] - centres[k, j]
            d2 += diff * diff
        phi[k] = math.exp(-d2 * inv_w2[k])
    for o in range(out.shape[0]):
        acc = 0.0
        for k in range(n_units):
            acc += weights[o, k] * phi[k]
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
def _min_minor(x, n, chol, eps, inv_sqrt_ms, centres, inv_w2, weights, bias, phi, out,
               mat, lmat, work):
    _theta_outputs(x, centres, inv_w2, weights, bias, phi, out)
    _mass(out, n, chol, eps, mat, lmat)
    worst = np.inf
    for k in range(1, n + 1):
        for i in range(n):
            for j in range(n):
                work[i, j] = mat[i, j] * inv_sqrt_ms[i] * inv_sqrt_ms[j]
        d = _det(work, k)
        if d < worst:
            worst = d
    return worst


@njit(cache=True, nogil=True, error_model='numpy', inline='always')
def _christoffel(xs, n, chol, centres, inv_w2, weights, phi, lmat, dout, dl, dmat, vvec, y, z):
    """
    Fill vvec with V = Ṁθ̇ - ½ ∂(θ̇ᵀMθ̇)/∂θ from the RBF inertia outputs (phi, lmat set).

    With w_k = (∂M/∂θ_k) θ̇, V_a = Σ_k θ̇_k w_k[a] - ½ Σ_j θ̇_j w_a[j]. For M = L Lᵀ + εI,
    ∂M/∂θ_k = (∂L/∂θ_k) Lᵀ + L (∂L/∂θ_k)ᵀ, so w_k = (∂L/∂θ_k) y + L (∂L/∂θ_k)ᵀ θ̇ with
    y = Lᵀθ̇: triangular products, no n x n x n tensor. dl holds w (row k = w_k), y and z
    are work vectors; dmat is used only without ``chol`` (M's outputs are M itself).
    """
    n_in = n * (n + 1) // 2
    n_units = centres.shape[0]
    # dout[k, o] = ∂out_o/∂θ_k: Σ_u weights[o, u] phi_u (-2 / w_u²)(θ_k - c_uk)
    for kk in range(n):
        for o in range(n_in):
            dout[kk, o] = 0.0
        for u in range(n_units):
            g = -2.0 * phi[u] * inv_w2[u] * (xs[kk] - centres[u, kk])
            for o in range(n_in):
                dout[kk, o] += weights[o, u] * g
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
def _advance(x, u_flat, row, h, substeps, case_id, chol, christ, kp_known, kd_known, eps,
             vc, centres, inv_w2, weights, bias, viscous, coulomb, pc, piw, pw, dc, diw, dw,
             kp, kd, phi, out, mat, lmat, rhs, acc, xs, k, q, dout, dl, dmat, vvec):
    """
    Advance x in place over one sampling interval: ``substeps`` RKG steps of N_f.

    N_f is written out inline in the stage loop: a call per evaluation with ~25 array
    arguments costs more reference counting than the arithmetic itself (one call per sample
    is cheap beside 4 x substeps evaluations). u = u_flat[row, substep, stage].
    With ``christ``, V comes from the Christoffel symbols of M (work arrays dout, dl, dmat,
    vvec); otherwise from the learned B and C outputs.
    """
    n2 = x.shape[0]
    n = n2 // 2
    n_out = weights.shape[0]
    n_units = centres.shape[0]
    # G follows the inertia outputs, and the learned B and C outputs when present
    off_g = n * (n + 1) // 2 if christ else n * (n + 1) // 2 + n * n * (n - 1) // 2 + n * n
    n_pu = pc.shape[1]
    n_du = dc.shape[1]
    for s in range(substeps):
        for j in range(n2):
            xs[j] = x[j]
        for stage in range(4):
            ui = 0 if stage == 0 else (2 if stage == 3 else 1)  # t, t+h/2, t+h/2, t+h
            # ---- k = N_f(xs, u): θ-RBF outputs
            for kk in range(n_units):
                d2 = 0.0
                for j in range(n):
                    diff = xs[j] - centres[kk, j]
                    d2 += diff * diff
                phi[kk] = math.exp(-d2 * inv_w2[kk])
            for o in range(n_out):
                val = 0.0
                for kk in range(n_units):
                    val += weights[o, kk] * phi[kk]
                out[o] = val + bias[o]
            _mass(out, n, chol, eps, mat, lmat)
            if christ:
                # rhs and acc are free until the solve below: the work vectors y, z
                _christoffel(xs, n, chol, centres, inv_w2, weights, phi, lmat, dout, dl, dmat,
                             vvec, rhs, acc)
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
                        tau = kp_known[a] * err + kd_known[a] * derr
                    else:
                        tau = kp[a] * err + kd[a] * derr
                        for kk in range(n_pu):
                            diff = err - pc[a, kk]
                            tau += pw[a, kk] * math.exp(-diff * diff * piw[a, kk])
                        for kk in range(n_du):
                            diff = derr - dc[a, kk]
                            tau += dw[a, kk] * math.exp(-diff * diff * diw[a, kk])
                v = vvec[a]
                f = viscous[a] * qd + coulomb[a] * math.tanh(qd / vc)
                rhs[a] = tau - v - out[off_g + a] - f
                k[a] = qd
            _solve(mat, rhs, acc)
            for a in range(n):
                k[n + a] = acc[a]
            # ---- Runge-Kutta-Gill update, Gill's form (see rkg.py)
            if stage == 0:
                for j in range(n2):
                    k[j] *= h
                    xs[j] = x[j] + 0.5 * k[j]
                    q[j] = k[j]
            elif stage == 1:
                for j in range(n2):
                    k[j] *= h
                    xs[j] = xs[j] + ALPHA * (k[j] - q[j])
                    q[j] = BETA * q[j] + E * k[j]
            elif stage == 2:
                for j in range(n2):
                    k[j] *= h
                    xs[j] = xs[j] + D * (k[j] - q[j])
                    q[j] = GAMMA * q[j] + G * k[j]
            else:
                for j in range(n2):
                    x[j] = xs[j] + h * k[j] / 6.0 - q[j] / 3.0


@njit(cache=True, nogil=True, error_model='numpy')
def _individual_cost(x_meas, seg_start, u_flat, h, substeps, shooting, case_id, chol, christ,
                     kp_known, kd_known, eps, inv_sqrt_ms, vc,
                     centres, inv_w2, weights, bias, viscous, coulomb,
                     pc, piw, pw, dc, diw, dw, kp, kd,
                     penalty_weight, bound_center, bound_scale, n_predicted):
    n2 = x_meas.shape[1]
    n = n2 // 2
    phi = np.empty(centres.shape[0])
    out = np.empty(weights.shape[0])
    mat = np.empty((n, n))
    lmat = np.empty((n, n))
    work = np.empty((n, n))
    rhs = np.empty(n)
    acc = np.empty(n)
    x = np.empty(n2)
    xs = np.empty(n2)
    k = np.empty(n2)
    q = np.empty(n2)
    dout = np.empty((n, n * (n + 1) // 2))
    dl = np.empty((n, n))
    dmat = np.empty((n, n, n))
    vvec = np.empty(n)
    total = 0.0
    worst = np.inf
    u_row = 0
    for seg in range(seg_start.shape[0] - 1):
        start = seg_start[seg]
        n_samples = seg_start[seg + 1] - start
        for j in range(n2):
            x[j] = x_meas[start, j]
        if not chol:
            worst = min(worst, _min_minor(x, n, chol, eps, inv_sqrt_ms, centres, inv_w2,
                                          weights, bias, phi, out, mat, lmat, work))
        for i in range(n_samples - 1):
            if shooting > 0 and i > 0 and i % shooting == 0:
                for j in range(n2):
                    x[j] = x_meas[start + i, j]
            _advance(x, u_flat, u_row + i, h, substeps, case_id, chol, christ, kp_known,
                     kd_known, eps, vc, centres, inv_w2, weights, bias, viscous, coulomb, pc, piw,
                     pw, dc, diw, dw, kp, kd, phi, out, mat, lmat, rhs, acc, xs, k, q, dout, dl,
                     dmat, vvec)
            e_pos = 0.0
            e_vel = 0.0
            for j in range(n2):
                xj = x[j]
                if not (abs(xj - bound_center[j]) <= bound_scale[j]):  # also catches NaN
                    return np.inf
                diff = xj - x_meas[start + i + 1, j]
                if j < n:
                    e_pos += diff * diff
                else:
                    e_vel += diff * diff
            total += math.sqrt(e_pos) + math.sqrt(e_vel)
            if not chol:
                worst = min(worst, _min_minor(x, n, chol, eps, inv_sqrt_ms, centres, inv_w2,
                                              weights, bias, phi, out, mat, lmat, work))
        u_row += n_samples - 1
    cost = total / n_predicted
    if not chol and worst < 0.0:
        cost += penalty_weight * (-worst)
    if not math.isfinite(cost):
        return np.inf
    return cost


@njit(cache=True, nogil=True, error_model='numpy')
def rollout(x0, u_flat, h, substeps, case_id, chol, christ, kp_known, kd_known, eps, vc,
            centres, inv_w2, weights, bias, viscous, coulomb, pc, piw, pw, dc, diw, dw, kp, kd,
            bound_center, bound_scale):
    """
    Predicted states of one model from x0 over ``u_flat.shape[0]`` sampling intervals.

    Returns
    -------
    ndarray, shape (u_flat.shape[0] + 1, 2n)
        States at the sample times; rows after a divergence are NaN.

    """
    n2 = x0.shape[0]
    n = n2 // 2
    n_int = u_flat.shape[0]
    states = np.full((n_int + 1, n2), np.nan)
    phi = np.empty(centres.shape[0])
    out = np.empty(weights.shape[0])
    mat = np.empty((n, n))
    lmat = np.empty((n, n))
    rhs = np.empty(n)
    acc = np.empty(n)
    x = x0.copy()
    xs = np.empty(n2)
    k = np.empty(n2)
    q = np.empty(n2)
    dout = np.empty((n, n * (n + 1) // 2))
    dl = np.empty((n, n))
    dmat = np.empty((n, n, n))
    vvec = np.empty(n)
    for j in range(n2):
        states[0, j] = x[j]
    for i in range(n_int):
        _advance(x, u_flat, i, h, substeps, case_id, chol, christ, kp_known, kd_known, eps,
                 vc, centres, inv_w2, weights, bias, viscous, coulomb, pc, piw, pw, dc, diw, dw,
                 kp, kd, phi, out, mat, lmat, rhs, acc, xs, k, q, dout, dl, dmat, vvec)
        for j in range(n2):
            if not (abs(x[j] - bound_center[j]) <= bound_scale[j]):
                return states
        for j in range(n2):
            states[i + 1, j] = x[j]
    return states


@njit(cache=True, nogil=True, parallel=True, error_model='numpy')
def population_cost(x_meas, seg_start, u_flat, h, substeps, shooting, case_id, chol, christ,
                    kp_known, kd_known, eps, inv_sqrt_ms, vc,
                    centres, inv_w2, weights, bias, viscous, coulomb,
                    pc, piw, pw, dc, diw, dw, kp, kd,
                    penalty_weight, bound_center, bound_scale, n_predicted):
    """
    Costs of a population (see FitnessProblem.kernel_args for the arguments).

    Returns
    -------
    ndarray, shape (P,)

    """
    pop = centres.shape[0]
    costs = np.empty(pop)
    for p in prange(pop):
        # private copies: views would share their parent's reference count between threads
        costs[p] = _individual_cost(
            x_meas.copy(), seg_start, u_flat, h, substeps, shooting, case_id, chol, christ,
            kp_known, kd_known, eps, inv_sqrt_ms, vc,
            centres[p].copy(), inv_w2[p].copy(), weights[p].copy(), bias[p].copy(),
            viscous[p].copy(), coulomb[p].copy(), pc[p].copy(), piw[p].copy(), pw[p].copy(),
            dc[p].copy(), diw[p].copy(), dw[p].copy(), kp[p].copy(), kd[p].copy(),
            penalty_weight, bound_center, bound_scale, n_predicted)
    return costs


@njit(cache=True, nogil=True, parallel=True, error_model='numpy')
def population_rollouts(x_meas, seg_start, u_flat, h, substeps, shooting, case_id, chol,
                        christ, kp_known, kd_known, eps, vc,
                        centres, inv_w2, weights, bias, viscous, coulomb,
                        pc, piw, pw, dc, diw, dw, kp, kd, bound_center, bound_scale):
    """
    Predicted states of a population over all segments, with multiple shooting.

    Row k of the result predicts ``x_meas[k]``; the first row of each segment is the
    measurement itself. Rows after a divergence (within the same shooting window) are NaN.

    Returns
    -------
    ndarray, shape (P, x_meas.shape[0], 2n)

    """
    pop = centres.shape[0]
    n_rows, n2 = x_meas.shape
    n = n2 // 2
    result = np.full((pop, n_rows, n2), np.nan)
    for p in prange(pop):
        cen = centres[p].copy()
        iw2 = inv_w2[p].copy()
        wts = weights[p].copy()
        bia = bias[p].copy()
        vis = viscous[p].copy()
        cou = coulomb[p].copy()
        pc_ = pc[p].copy()
        piw_ = piw[p].copy()
        pw_ = pw[p].copy()
        dc_ = dc[p].copy()
        diw_ = diw[p].copy()
        dw_ = dw[p].copy()
        kp_ = kp[p].copy()
        kd_ = kd[p].copy()
        phi = np.empty(cen.shape[0])
        out = np.empty(wts.shape[0])
        mat = np.empty((n, n))
        lmat = np.empty((n, n))
        rhs = np.empty(n)
        acc = np.empty(n)
        x = np.empty(n2)
        xs = np.empty(n2)
        k = np.empty(n2)
        q = np.empty(n2)
        dout = np.empty((n, n * (n + 1) // 2))
        dl = np.empty((n, n))
        dmat = np.empty((n, n, n))
        vvec = np.empty(n)
        u_row = 0
        for seg in range(seg_start.shape[0] - 1):
            start = seg_start[seg]
            n_samples = seg_start[seg + 1] - start
            alive = True
            for j in range(n2):
                x[j] = x_meas[start, j]
                result[p, start, j] = x[j]
            for i in range(n_samples - 1):
                if shooting > 0 and i > 0 and i % shooting == 0:
                    alive = True
                    for j in range(n2):
                        x[j] = x_meas[start + i, j]
                if alive:
                    _advance(x, u_flat, u_row + i, h, substeps, case_id, chol, christ,
                             kp_known, kd_known, eps, vc, cen, iw2, wts, bia, vis, cou, pc_,
                             piw_, pw_, dc_, diw_, dw_, kp_, kd_, phi, out, mat, lmat, rhs, acc,
                             xs, k, q, dout, dl, dmat, vvec)
                    for j in range(n2):
                        if not (abs(x[j] - bound_center[j]) <= bound_scale[j]):
                            alive = False
                    if alive:
                        for j in range(n2):
                            result[p, start + i + 1, j] = x[j]
            u_row += n_samples - 1
    return result

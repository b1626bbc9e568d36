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

from .rkg import ALPHA, BETA, D, E, G, GAMMA


@njit(cache=True, nogil=True)
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


@njit(cache=True, nogil=True)
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


@njit(cache=True, nogil=True)
def _theta_outputs(theta, centres, inv_w2, weights, bias, phi, out):
    n_units = centres.shape[0]
    n = theta.shape[0]
    for k in range(n_units):
        d2 = 0.0
        for j in range(n):
            diff = theta[j] - centres[k, j]
            d2 += diff * diff
        phi[k] = math.exp(-d2 * inv_w2[k])
    for o in range(out.shape[0]):
        acc = 0.0
        for k in range(n_units):
            acc += weights[o, k] * phi[k]
        out[o] = acc + bias[o]


@njit(cache=True, nogil=True)
def _mass(out, n, chol, eps, mat):
    idx = 0
    if chol:
        lmat = np.zeros((n, n))
        for i in range(n):
            for j in range(i + 1):
                lmat[i, j] = out[idx]
                idx += 1
        for i in range(n):
            for j in range(n):
                acc = 0.0
                for k in range(n):
                    acc += lmat[i, k] * lmat[j, k]
                mat[i, j] = acc
            mat[i, i] += eps[i]
    else:
        for i in range(n):
            for j in range(i, n):
                mat[i, j] = out[idx]
                mat[j, i] = out[idx]
                idx += 1


@njit(cache=True, nogil=True)
def _rhs(x, u, dx, n, case_id, chol, kp_known, kd_known, eps, vc,
         centres, inv_w2, weights, bias, viscous, coulomb,
         pc, piw, pw, dc, diw, dw, kp, kd, phi, out, mat, rhs, acc):
    """Evaluate dx = N_f(x, u) for one individual (work arrays phi, out, mat, rhs, acc)."""
    theta = x[:n]
    _theta_outputs(theta, centres, inv_w2, weights, bias, phi, out)
    _mass(out, n, chol, eps, mat)
    n_pairs = n * (n - 1) // 2
    off_b = n * (n + 1) // 2
    off_c = off_b + n * n_pairs
    off_g = off_c + n * n
    for i in range(n):
        qd = x[n + i]
        # torque
        if case_id == 0:
            tau = u[i]
        else:
            err = u[i] - x[i]
            derr = u[n + i] - qd
            if case_id == 1:
                tau = kp_known[i] * err + kd_known[i] * derr
            else:
                tau = kp[i] * err + kd[i] * derr
                for k in range(pc.shape[1]):
                    diff = err - pc[i, k]
                    tau += pw[i, k] * math.exp(-diff * diff * piw[i, k])
                for k in range(dc.shape[1]):
                    diff = derr - dc[i, k]
                    tau += dw[i, k] * math.exp(-diff * diff * diw[i, k])
        v = 0.0
        p = 0
        for j in range(n):
            for k in range(j + 1, n):
                v += out[off_b + i * n_pairs + p] * x[n + j] * x[n + k]
                p += 1
        for j in range(n):
            v += out[off_c + i * n + j] * x[n + j] * x[n + j]
        f = viscous[i] * qd + coulomb[i] * math.tanh(qd / vc)
        rhs[i] = tau - v - out[off_g + i] - f
        dx[i] = qd
    _solve(mat, rhs, acc)
    for i in range(n):
        dx[n + i] = acc[i]


@njit(cache=True, nogil=True)
def _min_minor(theta, n, chol, eps, inv_sqrt_ms, centres, inv_w2, weights, bias, phi, out,
               mat):
    _theta_outputs(theta, centres, inv_w2, weights, bias, phi, out)
    _mass(out, n, chol, eps, mat)
    worst = np.inf
    work = np.empty((n, n))
    for k in range(1, n + 1):
        for i in range(n):
            for j in range(n):
                work[i, j] = mat[i, j] * inv_sqrt_ms[i] * inv_sqrt_ms[j]
        d = _det(work, k)
        if d < worst:
            worst = d
    return worst


@njit(cache=True, nogil=True)
def _individual_cost(x_meas, seg_start, u_flat, h, substeps, shooting, case_id, chol,
                     kp_known, kd_known, eps, inv_sqrt_ms, vc,
                     centres, inv_w2, weights, bias, viscous, coulomb,
                     pc, piw, pw, dc, diw, dw, kp, kd,
                     penalty_weight, bound_center, bound_scale, n_predicted):
    n2 = x_meas.shape[1]
    n = n2 // 2
    n_out = weights.shape[0]
    phi = np.empty(centres.shape[0])
    out = np.empty(n_out)
    mat = np.empty((n, n))
    rhs = np.empty(n)
    acc = np.empty(n)
    x = np.empty(n2)
    xs = np.empty(n2)
    k = np.empty(n2)
    q = np.empty(n2)
    total = 0.0
    worst = np.inf
    u_row = 0
    for seg in range(seg_start.shape[0] - 1):
        start = seg_start[seg]
        n_samples = seg_start[seg + 1] - start
        for j in range(n2):
            x[j] = x_meas[start, j]
        if not chol:
            m = _min_minor(x[:n], n, chol, eps, inv_sqrt_ms, centres, inv_w2, weights, bias,
                           phi, out, mat)
            worst = min(worst, m)
        for i in range(n_samples - 1):
            if shooting > 0 and i > 0 and i % shooting == 0:
                for j in range(n2):
                    x[j] = x_meas[start + i, j]
            for s in range(substeps):
                u0 = u_flat[u_row + i, s, 0]
                uh = u_flat[u_row + i, s, 1]
                u1 = u_flat[u_row + i, s, 2]
                # Runge-Kutta-Gill, Gill's form (see rkg.py)
                _rhs(x, u0, k, n, case_id, chol, kp_known, kd_known, eps, vc, centres, inv_w2,
                     weights, bias, viscous, coulomb, pc, piw, pw, dc, diw, dw, kp, kd,
                     phi, out, mat, rhs, acc)
                for j in range(n2):
                    k[j] *= h
                    xs[j] = x[j] + 0.5 * k[j]
                    q[j] = k[j]
                _rhs(xs, uh, k, n, case_id, chol, kp_known, kd_known, eps, vc, centres,
                     inv_w2, weights, bias, viscous, coulomb, pc, piw, pw, dc, diw, dw, kp, kd,
                     phi, out, mat, rhs, acc)
                for j in range(n2):
                    k[j] *= h
                    xs[j] = xs[j] + ALPHA * (k[j] - q[j])
                    q[j] = BETA * q[j] + E * k[j]
                _rhs(xs, uh, k, n, case_id, chol, kp_known, kd_known, eps, vc, centres,
                     inv_w2, weights, bias, viscous, coulomb, pc, piw, pw, dc, diw, dw, kp, kd,
                     phi, out, mat, rhs, acc)
                for j in range(n2):
                    k[j] *= h
                    xs[j] = xs[j] + D * (k[j] - q[j])
                    q[j] = GAMMA * q[j] + G * k[j]
                _rhs(xs, u1, k, n, case_id, chol, kp_known, kd_known, eps, vc, centres,
                     inv_w2, weights, bias, viscous, coulomb, pc, piw, pw, dc, diw, dw, kp, kd,
                     phi, out, mat, rhs, acc)
                for j in range(n2):
                    x[j] = xs[j] + h * k[j] / 6.0 - q[j] / 3.0
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
                m = _min_minor(x[:n], n, chol, eps, inv_sqrt_ms, centres, inv_w2, weights,
                               bias, phi, out, mat)
                worst = min(worst, m)
        u_row += n_samples - 1
    cost = total / n_predicted
    if not chol and worst < 0.0:
        cost += penalty_weight * (-worst)
    if not math.isfinite(cost):
        return np.inf
    return cost


@njit(cache=True, nogil=True, parallel=True)
def population_cost(x_meas, seg_start, u_flat, h, substeps, shooting, case_id, chol,
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
        costs[p] = _individual_cost(
            x_meas, seg_start, u_flat, h, substeps, shooting, case_id, chol,
            kp_known, kd_known, eps, inv_sqrt_ms, vc,
            centres[p], inv_w2[p], weights[p], bias[p], viscous[p], coulomb[p],
            pc[p], piw[p], pw[p], dc[p], diw[p], dw[p], kp[p], kd[p],
            penalty_weight, bound_center, bound_scale, n_predicted)
    return costs

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
Small dense linear algebra for the compiled kernels: a solve and a determinant, in place.

Gaussian elimination with partial pivoting, written out for the kernels' inner loops: one
n x n solve per N_f evaluation (n about 3), on caller-owned buffers, nothing allocated. A
singular matrix gives NaN (the rollout then costs +inf) or a zero determinant, never an
exception.
"""

from numba import njit
import numpy as np


@njit(cache=True, nogil=True, error_model='numpy', inline='always')
def _pivot(a, k, n):
    """Return the row r in k..n-1 with the largest |a[r, k]| (the first of equals), and it."""
    piv = k
    big = abs(a[k, k])
    for r in range(k + 1, n):
        if abs(a[r, k]) > big:
            big = abs(a[r, k])
            piv = r
    return piv, big


@njit(cache=True, nogil=True, error_model='numpy', inline='always')
def solve(a, b, out):
    """Solve a @ out = b by Gaussian elimination with partial pivoting (a, b overwritten)."""
    n = b.shape[0]
    for k in range(n):
        piv, big = _pivot(a, k, n)
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
def det(a, k):
    """Return the determinant of the leading k x k block of a (a is overwritten)."""
    det = 1.0
    for j in range(k):
        piv, big = _pivot(a, j, k)
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

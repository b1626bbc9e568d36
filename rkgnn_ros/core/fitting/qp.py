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
A convex quadratic programme with few linear constraints, solved through its dual.

The closed-form fits (:mod:`.linear`) add a handful of inequality constraints (friction
non-negative, cuts that keep M positive definite) and at most one equality (case 3's gain
normalisation) to a least-squares problem with many coefficients; its dual is then a small
non-negative least squares, solved exactly.
"""

import numpy as np
from scipy.linalg import cho_solve, solve_triangular
from scipy.optimize import nnls

__all__ = ['solve_qp']


def solve_qp(chol, b, rows=None, rhs=None, equalities=0):
    """
    Minimise ½ zᵀHz - bᵀz subject to ``rows @ z >= rhs`` (the last ``equalities`` rows: ==).

    ``chol`` is the Cholesky factor of H (scipy ``cho_factor``). The constraints are few
    next to the coefficients, so the dual is solved: with Q = rows H⁻¹ rowsᵀ = UᵀU it is
    the non-negative least squares min ‖U y - U⁻ᵀ r‖ (an equality's multiplier is free:
    written as the difference of two non-negative ones), and z = H⁻¹ (b + rowsᵀ y).
    """
    z = cho_solve(chol, b)
    if rows is None or rows.shape[0] == 0:
        return z
    r = rhs - rows @ z
    if equalities == 0 and np.all(r <= 0.0):
        return z                                                    # nothing is active
    hinv_at = cho_solve(chol, rows.T)                               # (P, m)
    q = rows @ hinv_at
    q = 0.5 * (q + q.T) + 1e-12 * np.trace(q) / q.shape[0] * np.eye(q.shape[0])
    upper = np.linalg.cholesky(q).T                                 # q = Uᵀ U
    target = solve_triangular(upper, r, trans='T')
    if equalities:
        upper = np.hstack([upper, -upper[:, -equalities:]])
    y, _ = nnls(upper, target, maxiter=50 * upper.shape[1])
    if equalities:
        y = y[:rows.shape[0]] - np.concatenate([np.zeros(rows.shape[0] - equalities),
                                                y[rows.shape[0]:]])
    return z + hinv_at @ y

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
A fixed polynomial basis: the monomials of degree 1 and 2 in the normalised joint angles.

``φ_f(θ) = Π_j z_j^e_fj`` with ``z = (θ - θ̄) / spread`` (the :class:`..scales.Scales` of
the data) and the exponents ``e_f`` (the integer code table, one row per feature) running
over every monomial of total degree 1 or 2: n + n(n+1)/2 features, no genome parameters.
Decoded per feature: ``data[f] = [θ̄ (n), 1/spread (n)]``.

It is the smallest global basis, and the worked example of a plug-in without genome
parameters (as a trigonometric basis would be): this file and one line in the registry.
Beside the RBF units (``NetworkSpec.basis = 'poly+rbf'``) it gives M and G a smooth trend
over the whole range and the units local corrections.
"""

from itertools import combinations_with_replacement

from numba import njit
import numpy as np

from .base import Basis

#: Code of this basis in the compiled dispatch (:mod:`.registry`).
KIND = 1

#: Highest total degree.
DEGREE = 2


@njit(cache=True, nogil=True)
def prepare(x, n, work):
    """Precompute nothing (every monomial is a short product)."""


@njit(cache=True, nogil=True)
def value(x, n, codes, data, f, work):
    """Return φ_f = Π_j z_j^e_fj at the state ``x`` (θ = x[:n])."""
    acc = 1.0
    for j in range(n):
        e = codes[f, j]
        if e > 0:
            acc *= ((x[j] - data[f, j]) * data[f, n + j]) ** e
    return acc


@njit(cache=True, nogil=True)
def gradient(x, n, codes, data, f, k, phi_f, work):
    """Return ∂φ_f/∂θ_k = e_k z_k^(e_k - 1) / spread_k Π_(j≠k) z_j^e_j."""
    e = codes[f, k]
    if e == 0:
        return 0.0
    acc = e * ((x[k] - data[f, k]) * data[f, n + k]) ** (e - 1) * data[f, n + k]
    for j in range(n):
        if j != k and codes[f, j] > 0:
            acc *= ((x[j] - data[f, j]) * data[f, n + j]) ** codes[f, j]
    return acc


class Polynomial(Basis):
    """Monomials of degree 1 to :data:`DEGREE` in the normalised angles; nothing to fit."""

    name = 'poly'
    kind = KIND

    def codes(self, spec) -> np.ndarray:
        """Return the exponents, one row per monomial, graded by degree, shape (F, n)."""
        n = spec.n_joints
        rows = []
        for degree in range(1, DEGREE + 1):
            for joints in combinations_with_replacement(range(n), degree):
                row = np.zeros(n, dtype=np.int64)
                for j in joints:
                    row[j] += 1
                rows.append(row)
        return np.array(rows, dtype=np.int64).reshape(-1, n)

    def size(self, spec) -> int:
        """Return n + n(n+1)/2 (degree 2)."""
        return self.codes(spec).shape[0]

    def data_width(self, spec) -> int:
        """Return 2n: the centre and the inverse spread of θ."""
        return 2 * spec.n_joints

    def decode(self, spec, blocks, scales) -> np.ndarray:
        """Return ``[θ̄, 1/spread]`` for every feature, shape (P, F, 2n)."""
        pop = next(iter(blocks.values())).shape[0]
        row = np.concatenate([scales.theta_center, 1.0 / scales.theta_spread])
        return np.broadcast_to(row, (pop, self.size(spec), row.size)).copy()

    def features(self, theta, codes, data) -> np.ndarray:
        """Return φ, shape (S, F)."""
        n = theta.shape[-1]
        z = (theta[:, None, :] - data[..., :n]) * data[..., n:]
        return np.prod(z ** codes, axis=-1)

    def gradients(self, theta, codes, data, phi) -> np.ndarray:
        """Return ∂φ/∂θ, shape (S, F, n)."""
        n = theta.shape[-1]
        z = (theta[:, None, :] - data[..., :n]) * data[..., n:]          # (S, F, n)
        out = np.zeros(z.shape)
        for k in range(n):
            e = codes[:, k]
            lowered = codes.copy()
            lowered[:, k] = np.maximum(e - 1, 0)
            out[..., k] = e * np.prod(z ** lowered, axis=-1) * data[..., n + k]
        return out

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
The paper's basis: shape-adaptive Gaussian RBF units over θ (eqs. 7-8).

``φ_k(θ) = exp(-|θ - c_k|² / s_k²)``, with the centre c_k (n) and the width s_k of every
unit in the genome (blocks ``theta_centres`` (K, n) and ``theta_widths`` (K,), K =
``NetworkSpec.theta_units``), normalised by the spread of the data: c = θ̄ + spread ∘ g_c
and 1/s² = exp(-2 g_s) / |spread|². Decoded per unit: ``data[k] = [c_k (n), 1/s_k²]``.
The units are local: they learn the dynamics where the arm went.
"""

import math

from numba import njit
import numpy as np

from .base import Basis

#: Code of this basis in the compiled dispatch (:mod:`.registry`).
KIND = 0
#: Width genes are read within ±this: e^50 spreads is flat, e^-50 a point; beyond it
#: exp(-2 g) overflows and a unit at its centre would give inf · 0.
LOG_WIDTH_LIMIT = 50.0


@njit(cache=True, nogil=True, inline='always')
def prepare(x, n, work):
    """Precompute nothing: every unit needs its own distance."""


@njit(cache=True, nogil=True, inline='always')
def squared_distance(x, n, data, f):
    """Return |θ - c_f|² (rad²), θ = x[:n] and c_f = data[f, :n]."""
    d2 = 0.0
    for j in range(n):
        diff = x[j] - data[f, j]
        d2 += diff * diff
    return d2


@njit(cache=True, nogil=True, inline='always')
def value(x, n, codes, data, f, work):
    """Return φ_f at the state ``x`` (θ = x[:n]); ``data[f] = [c (n), 1/s²]``."""
    return math.exp(-squared_distance(x, n, data, f) * data[f, n])


@njit(cache=True, nogil=True, inline='always')
def gradient(x, n, codes, data, f, k, phi_f, work):
    """Return ∂φ_f/∂θ_k = -2 φ_f (θ_k - c_k) / s²."""
    return -2.0 * phi_f * data[f, n] * (x[k] - data[f, k])


class GaussianRBF(Basis):
    """Shape-adaptive Gaussian RBF units over θ: centres and widths are genome elements."""

    name = 'rbf'
    kind = KIND
    #: The names of the genome blocks of the centres and of the log-widths.
    centres, widths = 'theta_centres', 'theta_widths'

    def size(self, spec) -> int:
        """Return K, the units (``spec.theta_units``)."""
        return int(spec.theta_units)

    def blocks(self, spec):
        """Return the centres (K, n) and the log-widths (K,)."""
        k, n = int(spec.theta_units), spec.n_joints
        return [(self.centres, (k, n)), (self.widths, (k,))]

    def data_width(self, spec) -> int:
        """Return n + 1: the centre and 1/s²."""
        return spec.n_joints + 1

    def decode(self, spec, blocks, scales) -> np.ndarray:
        """Return ``[c (n), 1/s²]`` per unit, shape (P, K, n + 1)."""
        centres = scales.theta_center + scales.theta_spread * blocks[self.centres]
        width0 = float(np.linalg.norm(scales.theta_spread))
        log_width = np.clip(blocks[self.widths], -LOG_WIDTH_LIMIT, LOG_WIDTH_LIMIT)
        inv_width2 = np.exp(-2.0 * log_width) / width0 ** 2
        return np.concatenate([centres, inv_width2[..., None]], axis=-1)

    def initial(self, spec, rng=None):
        """
        Return centres spread over ±1.5 spreads of θ, and unit widths.

        The centres are random if ``rng`` is given, else on a fixed low-discrepancy pattern.
        """
        k, n = int(spec.theta_units), spec.n_joints
        if rng is not None:
            centres = rng.uniform(-1.5, 1.5, size=(k, n))
        else:
            golden = (np.sqrt(5.0) - 1.0) / 2.0
            steps = golden + 0.318 * np.arange(n)
            centres = 3.0 * ((np.arange(1, k + 1)[:, None] * steps) % 1.0) - 1.5
        return {self.centres: centres, self.widths: np.zeros(k)}

    def features(self, theta, codes, data) -> np.ndarray:
        """Return φ, shape (S, K)."""
        n = theta.shape[-1]
        d2 = np.sum(np.square(theta[:, None, :] - data[..., :n]), axis=-1)
        return np.exp(-d2 * data[..., n])

    def gradients(self, theta, codes, data, phi) -> np.ndarray:
        """Return ∂φ/∂θ, shape (S, K, n)."""
        n = theta.shape[-1]
        diff = theta[:, None, :] - data[..., :n]
        return phi[..., None] * (-2.0 * data[..., n][..., None] * diff)

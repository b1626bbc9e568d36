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
Inverse multiquadric units over θ: radial like the paper's, with tails that reach far.

``φ_k(θ) = 1 / sqrt(1 + |θ - c_k|² / s_k²)``, with the centre c_k (n) and the width s_k of
every unit in the genome (blocks ``imq_centres`` (K, n) and ``imq_widths`` (K,), K =
``NetworkSpec.theta_units``), normalised by the spread of the data as the Gaussian units
are: c = θ̄ + spread ∘ g_c and 1/s² = exp(-2 g_s) / |spread|². Decoded per unit:
``data[k] = [c_k (n), 1/s_k²]``. A Gaussian unit is e^-4 of its peak two widths out; this
one is 1/sqrt(5) there and falls as s/|θ - c|, so a unit fitted where the arm went still
says something a few widths away.

It is this package's worked example of adding a basis with genome parameters: this file
and its entries in :mod:`.registry` (``NetworkSpec.basis = 'imq'`` or a sum such as
'imq+rbf'); the genome, the decoding and the distance are the Gaussian units'
(:mod:`.rbf`).
"""

import math

from numba import njit
import numpy as np

from .rbf import GaussianRBF, prepare, squared_distance  # noqa: F401 - prepare is this basis's

#: Code of this basis in the compiled dispatch (:mod:`.registry`).
KIND = 4


@njit(cache=True, nogil=True)
def value(x, n, codes, data, f, work):
    """Return φ_f at the state ``x`` (θ = x[:n]); ``data[f] = [c (n), 1/s²]``."""
    return 1.0 / math.sqrt(1.0 + squared_distance(x, n, data, f) * data[f, n])


@njit(cache=True, nogil=True)
def gradient(x, n, codes, data, f, k, phi_f, work):
    """Return ∂φ_f/∂θ_k = -φ_f³ (θ_k - c_k) / s²."""
    return -phi_f * phi_f * phi_f * data[f, n] * (x[k] - data[f, k])


class InverseMultiquadric(GaussianRBF):
    """Inverse multiquadric units over θ: centres and widths are genome elements."""

    name = 'imq'
    kind = KIND
    centres, widths = 'imq_centres', 'imq_widths'

    def initial(self, spec, rng=None):
        """Return centres uniform over ±1.5 spreads of θ (a fixed seed without ``rng``)."""
        k, n = int(spec.theta_units), spec.n_joints
        rng = np.random.default_rng(0) if rng is None else rng
        return {self.centres: rng.uniform(-1.5, 1.5, size=(k, n)),
                self.widths: np.zeros(k)}

    def features(self, theta, codes, data) -> np.ndarray:
        """Return φ, shape (S, K)."""
        n = theta.shape[-1]
        d2 = np.sum(np.square(theta[:, None, :] - data[..., :n]), axis=-1)
        return 1.0 / np.sqrt(1.0 + d2 * data[..., n])

    def gradients(self, theta, codes, data, phi) -> np.ndarray:
        """Return ∂φ/∂θ, shape (S, K, n)."""
        n = theta.shape[-1]
        diff = theta[:, None, :] - data[..., :n]
        return (phi ** 3)[..., None] * (-data[..., n][..., None] * diff)

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
The trigonometric basis of a serial arm as a plug-in: the features of :mod:`..trig`.

Every feature is a Fourier mode of the joint angles, ``φ_f(θ) = cos(m_fᵀθ)`` or
``sin(m_fᵀθ)``, with the integer frequencies m_f (the code table, one row per feature) and
the kind (cos or sin: the decoded ``data[f] = [0 or 1]``) of the feature table of a
:class:`..trig.TrigBasis`. That table spans the arm's M(θ) and U(θ) exactly (the rigid-body
structure: :mod:`..trig`), so a network in this basis is a global model of the arm, right on
the whole torus and not only near the data, as the RBF units are. No genome parameters: the
weights of the features are the only ones fitted.

Two settings of the table are registered:

- 'trig': all joint axes parallel (a planar arm, every arm of the simulator): the runs of
  consecutive joints ``TrigBasis(n, planar=True)``: n(n + 1) features (12 for 3 joints, 42
  for 6; the constant is left to the network's bias).
- 'trig3d': a spatial serial chain, frequencies up to 2 in M and 1 in U, M_ij over the
  joints after min(i, j) (``TrigBasis(n, mass_degree=2)``); it grows like 5^(n-1) and 3^n
  (42 features for 3 joints, 178 for 4), so beyond 4 joints ``max_order=2`` prunes M's modes
  to pairs of joints (:data:`SPATIAL_MAX_ORDER`; 858 features for 6).

A sum with the RBF units ('trig+rbf') adds local corrections for what the rigid body misses.
"""

import math

from numba import njit
import numpy as np

from .base import Basis
from ..trig import TrigBasis

#: Code of the planar table in the compiled dispatch (:mod:`.registry`).
KIND = 2

#: Code of the spatial table; it shares this file's compiled functions.
KIND_SPATIAL = 3

#: Joints above which the spatial table keeps M's modes of at most two joints.
SPATIAL_FULL_JOINTS = 4

#: The ``max_order`` of the spatial table's M beyond :data:`SPATIAL_FULL_JOINTS` joints.
SPATIAL_MAX_ORDER = 2


@njit(cache=True, nogil=True)
def prepare(x, n, work):
    """Precompute nothing: every feature is one angle mᵀθ."""


@njit(cache=True, nogil=True)
def value(x, n, codes, data, f, work):
    """Return φ_f = cos(m_fᵀθ) (``data[f, 0] = 0``) or sin(m_fᵀθ) (1) at θ = x[:n]."""
    angle = 0.0
    for j in range(n):
        if codes[f, j] != 0:
            angle += codes[f, j] * x[j]
    if data[f, 0] > 0.5:
        return math.sin(angle)
    return math.cos(angle)


@njit(cache=True, nogil=True)
def gradient(x, n, codes, data, f, k, phi_f, work):
    """Return ∂φ_f/∂θ_k = m_fk cos(m_fᵀθ) for a sine, -m_fk sin(m_fᵀθ) for a cosine."""
    m = codes[f, k]
    if m == 0:
        return 0.0
    angle = 0.0
    for j in range(n):
        if codes[f, j] != 0:
            angle += codes[f, j] * x[j]
    if data[f, 0] > 0.5:
        return m * math.cos(angle)
    return -m * math.sin(angle)


class Trigonometric(Basis):
    """The features of an arm's :class:`..trig.TrigBasis`, all axes parallel ('trig')."""

    name = 'trig'
    kind = KIND

    def table(self, n_joints: int) -> TrigBasis:
        """Return the :class:`..trig.TrigBasis` whose feature table this basis evaluates."""
        return TrigBasis(n_joints, mass_degree=1, planar=True)

    def _rows(self, spec):
        """Return the frequencies (F, n) and kinds (F,) without the constant feature."""
        table = self.table(spec.n_joints)
        keep = np.any(table.frequencies != 0, axis=1)      # the network has its own bias
        return table.frequencies[keep], table.kinds[keep]

    def codes(self, spec) -> np.ndarray:
        """Return the frequencies m_f, shape (F, n)."""
        return self._rows(spec)[0].astype(np.int64)

    def size(self, spec) -> int:
        """Return F, the modes of the table without the constant."""
        return int(self._rows(spec)[1].size)

    def data_width(self, spec) -> int:
        """Return 1: the kind (0 cos, 1 sin)."""
        return 1

    def decode(self, spec, blocks, scales) -> np.ndarray:
        """Return the kinds, shape (P, F, 1)."""
        pop = next(iter(blocks.values())).shape[0] if blocks else 1
        kinds = self._rows(spec)[1].astype(float)[:, None]
        return np.broadcast_to(kinds, (pop,) + kinds.shape).copy()

    def features(self, theta, codes, data) -> np.ndarray:
        """Return φ, shape (S, F)."""
        angle = theta @ codes.T.astype(float)                    # (S, F)
        return np.where(data[..., 0] > 0.5, np.sin(angle), np.cos(angle))

    def gradients(self, theta, codes, data, phi) -> np.ndarray:
        """Return ∂φ/∂θ, shape (S, F, n)."""
        angle = theta @ codes.T.astype(float)
        slope = np.where(data[..., 0] > 0.5, np.cos(angle), -np.sin(angle))
        return slope[..., None] * codes.astype(float)


class SpatialTrigonometric(Trigonometric):
    """The features of a spatial serial chain's :class:`..trig.TrigBasis` ('trig3d')."""

    name = 'trig3d'
    kind = KIND_SPATIAL

    def table(self, n_joints: int) -> TrigBasis:
        """Return the spatial table, M's modes pruned to joint pairs beyond 4 joints."""
        order = None if n_joints <= SPATIAL_FULL_JOINTS else SPATIAL_MAX_ORDER
        return TrigBasis(n_joints, mass_degree=2, max_order=order)

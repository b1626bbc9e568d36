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
What a basis of the θ-dependent outputs is: the interface every basis plug-in implements.

Every θ-dependent output of N_f (the entries of M or of its Cholesky factor, the learned B
and C, G) is a linear combination of features φ_f(θ) plus a constant::

    out_o(θ) = Σ_f W[o, f] φ_f(θ) + bias_o

The weights W and the constants are genome elements that every basis shares; a basis
decides what the features are. It is a plug-in, as a feature library is in PySINDy
(``feature_library/base.py``): a :class:`Basis` object says how many features it has for a
network structure, which genome blocks of its own parameters it adds (the paper's RBF
centres and widths; none for a fixed basis), how it decodes them and where they start, and
evaluates its features and their gradients in numpy (the reference). Its module also
provides the compiled twins, three numba functions that the registry dispatches on the
basis's ``kind`` code::

    prepare(x, n, work)                              once per evaluation (e.g. cos θ_j)
    value(x, n, codes, data, f, work) -> float       φ_f
    gradient(x, n, codes, data, f, k, phi_f, work) -> float    ∂φ_f/∂θ_k

with ``x`` the state (θ in its first n entries), ``codes`` (F, n) the fixed integer table
of all features, ``data`` (F, D) the decoded real parameters of one model and ``work``
(kinds, W) a scratch table in which row ``kind`` is the basis's own. They index the tables
themselves and return scalars (no array views, nothing stored in the inner loops: the
kernels' speed depends on it). A sum of bases
(``NetworkSpec.basis = 'poly+rbf'``) concatenates their features.
"""

from typing import Dict, List, Tuple

import numpy as np


class Basis:
    """
    A family of features φ_f(θ) for the θ-dependent outputs (subclass it; one file each).

    Attributes
    ----------
    name : str
        What ``NetworkSpec.basis`` calls it.
    kind : int
        Its code in the compiled dispatch (unique, small: it indexes the work table).

    """

    name = ''
    kind = -1

    def size(self, spec) -> int:
        """Return the number of features F for the network structure ``spec``."""
        raise NotImplementedError

    def blocks(self, spec) -> List[Tuple[str, Tuple[int, ...]]]:
        """Return the genome blocks of the basis's own parameters, (name, shape) in order."""
        return []

    def codes(self, spec) -> np.ndarray:
        """Return the fixed integer table of the features, shape (F, n)."""
        return np.zeros((self.size(spec), spec.n_joints), dtype=np.int64)

    def data_width(self, spec) -> int:
        """Return D, the real parameters per feature in the decoded table."""
        return 0

    def work_width(self, spec) -> int:
        """Return the scratch values ``prepare`` writes per evaluation."""
        return 0

    def decode(self, spec, blocks: Dict[str, np.ndarray], scales) -> np.ndarray:
        """
        Map the basis's genome blocks to its decoded parameters.

        Parameters
        ----------
        spec : NetworkSpec
            Network structure.
        blocks : dict of ndarray
            Every genome block by name, each of shape (P,) + block shape.
        scales : Scales
            Physical scales of the data.

        Returns
        -------
        ndarray, shape (P, F, D)

        """
        pop = next(iter(blocks.values())).shape[0] if blocks else 1
        return np.zeros((pop, self.size(spec), self.data_width(spec)))

    def initial(self, spec, rng=None) -> Dict[str, np.ndarray]:
        """Return starting values of the basis's genome blocks, by name."""
        return {}

    def features(self, theta, codes, data) -> np.ndarray:
        """
        Evaluate the features in numpy (the reference the compiled twin is held to).

        Parameters
        ----------
        theta : ndarray, shape (S, n)
            Joint angles: one per model (S = P), or any number for one model (P = 1).
        codes : ndarray, shape (F, n)
            This basis's rows of the integer table.
        data : ndarray, shape (P, F, D)
            This basis's decoded parameters.

        Returns
        -------
        ndarray, shape (S, F)

        """
        raise NotImplementedError

    def gradients(self, theta, codes, data, phi) -> np.ndarray:
        """Return ∂φ_f/∂θ_k, shape (S, F, n), given the features ``phi`` (S, F)."""
        raise NotImplementedError

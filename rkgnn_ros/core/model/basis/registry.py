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
The registry of bases: names to basis objects, and the compiled dispatch on their kind code.

The compiled kernels never name a basis: they call :func:`prepare`, :func:`features` and
:func:`gradients` here with the integer table of the network's features (one kind code per
feature), and these call the basis module's numba functions. Adding a basis is its own
file and one entry in :data:`MODULES` plus one branch in each of the three dispatchers
below; the kernels, the fitness, the warm start and the nodes stay as they are.

numba links the dispatch into every compiled kernel that calls it, and its on-disk cache
only notices changes of the kernel's own file. :func:`source_fingerprint` is therefore a
checksum of this file and every basis module; the kernels compare it with the one they were
compiled with and recompile when it differs (:func:`..kernels.ensure_current`).
"""

import math
from typing import Tuple
import zlib

from numba import njit
import numpy as np

from . import base, poly, rbf
from .base import Basis

#: The basis modules, each with KIND, prepare, value, gradient and one Basis subclass.
MODULES = (rbf, poly)

#: Every registered basis by name (``NetworkSpec.basis`` joins names with '+').
BASES = {b.name: b for b in (rbf.GaussianRBF(), poly.Polynomial())}

if len({b.kind for b in BASES.values()}) != len(BASES):
    raise RuntimeError('two bases share a kind code')

#: Rows of the work table: one per kind code.
N_KINDS = max(b.kind for b in BASES.values()) + 1


def lookup(name: str) -> Tuple[Basis, ...]:
    """
    Return the bases of a ``NetworkSpec.basis`` value such as 'rbf' or 'poly+rbf'.

    Raises ValueError for an unknown or repeated name.
    """
    parts = [part.strip() for part in str(name).split('+')]
    unknown = [part for part in parts if part not in BASES]
    if unknown or not parts:
        raise ValueError(f'basis must be one of {sorted(BASES)} or a sum of them joined by '
                         f"'+', got {name!r}")
    if len(set(parts)) != len(parts):
        raise ValueError(f'basis {name!r} names a basis twice')
    return tuple(BASES[part] for part in parts)


def source_fingerprint() -> int:
    """Return a checksum of the source of this registry and of every basis module."""
    crc = 0
    for module in (base, *MODULES):
        with open(module.__file__, 'rb') as f:
            crc = zlib.crc32(f.read(), crc)
    with open(__file__, 'rb') as f:
        crc = zlib.crc32(f.read(), crc)
    return int(crc)


def work_shape(spec) -> Tuple[int, int]:
    """Return the shape of the work table for a network structure: (kinds, widest need)."""
    width = max([b.work_width(spec) for b in spec.bases] + [1])
    return N_KINDS, width


@njit(cache=True, nogil=True, inline='always')
def prepare(x, n, bases, work):
    """Let each basis in ``bases`` (kind codes) precompute what its features share at ``x``."""
    for b in range(bases.shape[0]):
        kind = bases[b]
        if kind == rbf.KIND:
            rbf.prepare(x, n, work)
        elif kind == poly.KIND:
            poly.prepare(x, n, work)


@njit(cache=True, nogil=True, inline='always')
def features(x, n, kinds, codes, data, work, phi):
    """
    Fill ``phi`` (F,) with every feature at the state ``x`` (θ = x[:n]).

    ``kinds`` (F,) and ``codes`` (F, n) are the network's feature table, ``data`` (F, D)
    one model's decoded basis parameters, ``work`` what :func:`prepare` wrote. A kind this
    dispatch does not know gives NaN (the rollout then costs +inf).
    """
    for f in range(kinds.shape[0]):
        kind = kinds[f]
        if kind == rbf.KIND:
            phi[f] = rbf.value(x, n, codes, data, f, work)
        elif kind == poly.KIND:
            phi[f] = poly.value(x, n, codes, data, f, work)
        else:
            phi[f] = math.nan


@njit(cache=True, nogil=True, inline='always')
def gradients(x, n, kinds, codes, data, work, phi, dphi):
    """Fill ``dphi`` (F, n) with ∂φ_f/∂θ_k, given the features ``phi`` at ``x``."""
    for f in range(kinds.shape[0]):
        kind = kinds[f]
        if kind == rbf.KIND:
            rbf.gradient(x, n, codes, data, f, phi[f], work, dphi)
        elif kind == poly.KIND:
            poly.gradient(x, n, codes, data, f, phi[f], work, dphi)
        else:
            for k in range(n):
                dphi[f, k] = math.nan


def table(spec):
    """
    Return the integer table of a network's features.

    Returns
    -------
    bases : ndarray of int64, shape (B,)
        The kind codes of the bases, in order.
    kinds : ndarray of int64, shape (F,)
        The kind code of every feature.
    codes : ndarray of int64, shape (F, n)
        Every basis's fixed codes, stacked.

    """
    bases = spec.bases
    kinds = np.concatenate([np.full(b.size(spec), b.kind, dtype=np.int64) for b in bases])
    codes = np.vstack([b.codes(spec) for b in bases]).astype(np.int64)
    return (np.array([b.kind for b in bases], dtype=np.int64), kinds,
            np.ascontiguousarray(codes.reshape(-1, spec.n_joints)))

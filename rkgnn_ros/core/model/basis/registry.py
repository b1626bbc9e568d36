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
:func:`output_gradients` here with the integer table of the network's features (the kind
code of each basis and of each feature), and these call the basis module's numba functions.
The kernels are compiled twice: for networks of the default basis alone (the paper's RBF
units), whose functions are inlined into the inner loops, and for any other basis or sum of
bases, reached through the small dispatch functions below, compiled apart (``_prepare``,
``_value``, ``_gradient``): code of other bases in the kernels' inner loops slows them
even in a branch never taken (README, numerical core). Adding a basis is its own file, one
entry in :data:`MODULES` and :data:`BASES`, and one branch in each of those three
functions; the kernels, the fitness, the warm start and the nodes stay as they are.

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

from . import base, imq, poly, rbf, trig
from .base import Basis

#: The basis modules, each with KIND, prepare, value, gradient and one Basis subclass.
MODULES = (rbf, poly, trig, imq)

#: Every registered basis by name (``NetworkSpec.basis`` joins names with '+').
BASES = {b.name: b for b in (rbf.GaussianRBF(), poly.Polynomial(), trig.Trigonometric(),
                             trig.SpatialTrigonometric(), imq.InverseMultiquadric())}

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
    """Return the shape of the work table for a network structure: (kind codes, widest)."""
    width = max([b.work_width(spec) for b in spec.bases] + [1])
    return N_KINDS, width


def inlined_only(spec) -> bool:
    """Return whether every basis of ``spec`` is the one compiled into the kernels."""
    return all(b.kind == rbf.KIND for b in spec.bases)


@njit(cache=True, nogil=True, inline='always')
def prepare(x, n, bases, work, inlined):
    """Let each basis in ``bases`` (kind codes) precompute what its features share at ``x``."""
    if inlined:
        rbf.prepare(x, n, work)
    else:
        for b in range(bases.shape[0]):
            _prepare(bases[b], x, n, work)


@njit(cache=True, nogil=True, inline='always')
def features(x, n, kinds, codes, data, work, phi, inlined):
    """
    Fill ``phi`` (F,) with every feature at the state ``x`` (θ = x[:n]).

    ``kinds`` (F,) and ``codes`` (F, n) are the network's feature table, ``data`` (F, D)
    one model's decoded basis parameters, ``work`` what :func:`prepare` wrote; ``inlined``
    (a compile-time constant) says the network has only the inlined basis. A kind this
    dispatch does not know gives NaN (the rollout then costs +inf).
    """
    if inlined:
        for f in range(kinds.shape[0]):
            phi[f] = rbf.value(x, n, codes, data, f, work)
    else:
        for f in range(kinds.shape[0]):
            phi[f] = _value(kinds[f], x, n, codes, data, f, work)


@njit(cache=True, nogil=True, inline='always')
def output_gradients(x, n, bases, starts, codes, data, work, phi, weights, rows, dout, inlined):
    """
    Add ∂out_o/∂θ_k = Σ_f weights[o, f] ∂φ_f/∂θ_k to ``dout[k, o]`` for the outputs o < rows.

    Basis ``b`` (kind ``bases[b]``) owns the features ``starts[b]`` to ``starts[b + 1]``.
    For every ``dout[k, o]`` the features are summed in order.
    """
    if inlined:
        for k in range(n):
            for f in range(codes.shape[0]):
                g = rbf.gradient(x, n, codes, data, f, k, phi[f], work)
                for o in range(rows):
                    dout[k, o] += weights[o, f] * g
    else:
        for b in range(bases.shape[0]):
            _output_gradients(bases[b], x, n, codes, data, starts[b], starts[b + 1], work,
                              phi, weights, rows, dout)


# ----- every basis, compiled apart and called (see the module docstring)

@njit(cache=True, nogil=True)
def _prepare(kind, x, n, work):
    if kind == rbf.KIND:
        rbf.prepare(x, n, work)
    elif kind == poly.KIND:
        poly.prepare(x, n, work)
    elif kind == trig.KIND or kind == trig.KIND_SPATIAL:
        trig.prepare(x, n, work)
    elif kind == imq.KIND:
        imq.prepare(x, n, work)


@njit(cache=True, nogil=True)
def _value(kind, x, n, codes, data, f, work):
    if kind == rbf.KIND:
        return rbf.value(x, n, codes, data, f, work)
    if kind == poly.KIND:
        return poly.value(x, n, codes, data, f, work)
    if kind == trig.KIND or kind == trig.KIND_SPATIAL:
        return trig.value(x, n, codes, data, f, work)
    if kind == imq.KIND:
        return imq.value(x, n, codes, data, f, work)
    return math.nan


@njit(cache=True, nogil=True)
def _gradient(kind, x, n, codes, data, f, k, phi_f, work):
    if kind == rbf.KIND:
        return rbf.gradient(x, n, codes, data, f, k, phi_f, work)
    if kind == poly.KIND:
        return poly.gradient(x, n, codes, data, f, k, phi_f, work)
    if kind == trig.KIND or kind == trig.KIND_SPATIAL:
        return trig.gradient(x, n, codes, data, f, k, phi_f, work)
    if kind == imq.KIND:
        return imq.gradient(x, n, codes, data, f, k, phi_f, work)
    return math.nan


@njit(cache=True, nogil=True)
def _output_gradients(kind, x, n, codes, data, f0, f1, work, phi, weights, rows, dout):
    for k in range(n):
        for f in range(f0, f1):
            g = _gradient(kind, x, n, codes, data, f, k, phi[f], work)
            for o in range(rows):
                dout[k, o] += weights[o, f] * g


#: The dispatch functions compiled apart, which :func:`..kernels.ensure_current` refreshes.
COMPILED = (_prepare, _value, _gradient, _output_gradients)


def table(spec):
    """
    Return the integer table of a network's features.

    Returns
    -------
    bases : ndarray of int64, shape (B,)
        The kind codes of the bases, in order.
    starts : ndarray of int64, shape (B + 1,)
        Where each basis's features start; the last entry is F.
    kinds : ndarray of int64, shape (F,)
        The kind code of every feature.
    codes : ndarray of int64, shape (F, n)
        Every basis's fixed codes, stacked.

    """
    bases = spec.bases
    sizes = [b.size(spec) for b in bases]
    kinds = np.concatenate([np.full(size, b.kind, dtype=np.int64)
                            for b, size in zip(bases, sizes)])
    codes = np.vstack([b.codes(spec) for b in bases]).astype(np.int64)
    return (np.array([b.kind for b in bases], dtype=np.int64),
            np.cumsum([0] + sizes).astype(np.int64), kinds,
            np.ascontiguousarray(codes.reshape(-1, spec.n_joints)))

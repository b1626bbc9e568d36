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
The trigonometric basis of a serial revolute arm: M(θ) and U(θ) in a finite feature set.

Why this basis
--------------
For any serial arm with revolute joints, link l's position is a sum of products of its
predecessors' rotations, whose entries are 1, cos θk or sin θk. So the potential U(θ) is a
trigonometric polynomial of degree at most 1 in each joint angle, and the inertia matrix
M(θ) = Σ_l J_lᵀ Λ_l J_l, a product of two such factors, of degree at most 2 in each.
Both are therefore linear in the coefficients of a finite set of features, and so are V
(Christoffel symbols of M) and G = ∇U: inverse dynamics is linear in a finite coefficient
set (:mod:`rkgnn_ros.core.fitting.linear`). The features are periodic, so a model holds on
the whole torus, not only near the data.

A feature here is a Fourier mode, cos(mᵀθ) or sin(mᵀθ), with an integer frequency per
joint, |m_k| <= degree. The products of 1, cos θk, sin θk (and cos 2θk, sin 2θk) over the
joints span exactly the same functions (product-to-sum: cos a cos b = ½ cos(a - b) +
½ cos(a + b), ...), with the same count, and every pruning below keeps the two spans
equal; modes are cheaper to evaluate (one angle per feature) and make the planar structure
one rule.

Pruning
-------
- Serial chain: M_ij depends only on the joints after min(i, j). Turning joint k moves the
  chain beyond it rigidly about joint k's axis, which leaves every inner product among the
  Jacobian columns of joints k, k+1, ... unchanged; M_ij is built from columns i and j of
  the links beyond max(i, j), so it is invariant under every joint k <= min(i, j). In
  particular M never depends on θ1.
- U has degree 1 per joint. Link l's share depends on joints <= l only, but the sum over
  the links reaches every joint, so U keeps all its modes (3^n - 1; the constant exerts no
  torque) unless gravity is parallel to the first axis (a vertical base joint:
  ``potential_skips_first``, U does not depend on θ1).
- ``planar``: all axes parallel (a planar arm). Angles about parallel axes add, so link l's
  absolute angle is φ_l = θ1 + ... + θl: M is a sum of cos and sin of φ_k - φ_l (a run of
  consecutive joints, frequency 1 on each) and U of cos and sin of φ_l (runs from joint 1).
  ``tied`` goes one step further: the kinetic energy of a planar chain is ½ φ̇ᵀ D φ̇ with
  D_kl = a_kl cos(φ_k - φ_l) + b_kl sin(φ_k - φ_l) (k ≠ l) and D_kk constant, so
  M = Sᵀ D S (S the lower-triangular ones, θ̇ = S⁻¹ φ̇) and M_ij = Σ_{k >= i, l >= j} D_kl:
  every entry shares the n² link-pair coefficients. Exact for any planar arm (links of any
  shape), and the coefficients drop from Σ_i (n - i + 1)(m_i (m_i + 1) + 1) to n².
- ``max_order`` keeps the modes of M with at most that many joints involved: couplings of
  far-apart joints through many intermediate ones are dropped. That is an approximation
  (a planar arm's M_11 holds cos(θ2 + ... + θn)), for where the full set is too large. U is
  never truncated: gravity reaches the base through every joint (a planar arm's U holds
  sin(θ1 + ... + θn) with the full weight of the last link).

Counts (coefficients of M + those of U, :func:`feature_counts`): E = n(n+1)/2 entries,
q = 2 degree + 1 values per joint::

    all modes:        E q^n + 3^n - 1
    serial chain:     Σ_i (n - i + 1) q^(n-i) + 3^n - 1      (entry (i, j), i <= j)
    planar chain:     Σ_i (n - i + 1) (m_i (m_i + 1) + 1) + 2n,  m_i = n - i
    planar, tied:     n² + 2n

Spatial (degree 2) serial chain, n = 2, 3, 4, 6, 7: 11 + 8, 86 + 26, 586 + 80,
22 461 + 728, 131 836 + 2186; degree 1 (parallel axes, full modes): 7 + 8, 34 + 26,
142 + 80, 2005 + 728, 7108 + 2186; planar: 7 + 4, 28 + 6, 80 + 8, 371 + 12, 672 + 14;
planar tied: 4 + 4, 9 + 6, 16 + 8, 36 + 12, 49 + 14. All modes of a chain grow like q^n:
one least-squares solve handles them up to 4 spatial joints. For 6-7 spatial joints,
``max_order=2`` (M) gives 1981 + 728 and 3836 + 2186, a polynomial growth in n; that many
coefficients need data from far more of the joint space than one 20 s run about one pose
(``bench/generalization.py``), and a structure that ties the entries (as ``tied`` does for
parallel axes) is what makes a 6-joint fit well posed.

Everything here is numpy, vectorised over leading batch axes of θ, and ROS-free.
"""

from dataclasses import dataclass, field
import itertools
from math import comb
from typing import Dict, Optional, Sequence, Tuple

import numpy as np

#: Kinds of feature: cos(mᵀθ) (the constant is the cosine of m = 0) and sin(mᵀθ).
KINDS = ('cos', 'sin')


def modes(n_joints: int, joints: Sequence[int], degree: int = 1,
          max_order: Optional[int] = None) -> Tuple[np.ndarray, np.ndarray]:
    """
    Return every Fourier mode over ``joints`` (frequency 0 on the other joints).

    Parameters
    ----------
    n_joints : int
        Number of joints n.
    joints : sequence of int
        The joints (0-based) the features may depend on.
    degree : {1, 2}
        Largest frequency per joint: 1 for (1, cos θ, sin θ), 2 for spatial M.
    max_order : int, optional
        At most this many joints with a non-zero frequency; None: no limit.

    Returns
    -------
    frequencies : ndarray of int8, shape (F, n)
        m, with its first non-zero entry positive (m and -m give the same features).
    kinds : ndarray of int8, shape (F,)
        0 for cos(mᵀθ), 1 for sin(mᵀθ); the constant (m = 0, cos) first.

    """
    if degree not in (1, 2):
        raise ValueError(f'degree must be 1 or 2, got {degree}')
    joints = sorted({int(k) for k in joints})
    if joints and (joints[0] < 0 or joints[-1] >= n_joints):
        raise ValueError(f'joints must lie in [0, {n_joints}), got {joints}')
    rows = [np.zeros(n_joints, dtype=np.int8)]
    kinds = [0]
    for combo in itertools.product(range(-degree, degree + 1), repeat=len(joints)):
        nonzero = [c for c in combo if c != 0]
        if not nonzero or nonzero[0] < 0:
            continue
        if max_order is not None and len(nonzero) > max_order:
            continue
        row = np.zeros(n_joints, dtype=np.int8)
        row[joints] = combo
        rows += [row, row]
        kinds += [0, 1]
    return np.array(rows, dtype=np.int8), np.array(kinds, dtype=np.int8)


def run_modes(n_joints: int, joints: Sequence[int],
              prefixes: bool = False) -> Tuple[np.ndarray, np.ndarray]:
    """
    Return the planar modes: cos and sin of θa + ... + θb over consecutive ``joints``.

    Parameters
    ----------
    n_joints : int
        Number of joints n.
    joints : sequence of int
        Consecutive joints (0-based) the runs lie in.
    prefixes : bool
        Only the runs that start at ``joints[0]`` (the absolute link angles), and no
        constant.

    Returns
    -------
    frequencies, kinds : as :func:`modes`.

    """
    joints = sorted({int(k) for k in joints})
    if joints and joints != list(range(joints[0], joints[-1] + 1)):
        raise ValueError(f'joints must be consecutive, got {joints}')
    rows, kinds = ([], []) if prefixes else ([np.zeros(n_joints, dtype=np.int8)], [0])
    for a in joints[:1] if prefixes else joints:
        for b in range(a, joints[-1] + 1):
            row = np.zeros(n_joints, dtype=np.int8)
            row[a:b + 1] = 1
            rows += [row, row]
            kinds += [0, 1]
    return (np.array(rows, dtype=np.int8).reshape(-1, n_joints),
            np.array(kinds, dtype=np.int8))


def feature_names(frequencies, kinds) -> Tuple[str, ...]:
    """Return readable names, e.g. ``'cos(θ2+θ3)'``, ``'sin(2θ3-θ4)'``, ``'1'``."""
    names = []
    for m, kind in zip(np.atleast_2d(frequencies), np.atleast_1d(kinds)):
        terms = []
        for k, c in enumerate(m):
            if c:
                sign = '-' if c < 0 else ('+' if terms else '')
                size = '' if abs(c) == 1 else str(abs(c))
                terms.append(f'{sign}{size}θ{k + 1}')
        names.append(f"{KINDS[kind]}({''.join(terms)})" if terms else '1')
    return tuple(names)


def evaluate_features(frequencies, kinds, theta, gradient: bool = False):
    """
    Return the features' values (and gradients) at a batch of configurations.

    Parameters
    ----------
    frequencies : array_like of int, shape (F, n)
        The features' frequency vectors m (:func:`modes`).
    kinds : array_like of int, shape (F,)
        0 for cos(mᵀθ), 1 for sin(mᵀθ).
    theta : array_like, shape (..., n)
        Joint angles.
    gradient : bool
        Also return the gradients.

    Returns
    -------
    values : ndarray, shape (..., F)
    gradients : ndarray, shape (..., F, n)
        Only with ``gradient``: ``gradients[..., f, k] = ∂φ_f / ∂θ_k``.

    """
    m = np.asarray(frequencies, dtype=float)
    theta = np.asarray(theta, dtype=float)
    if theta.shape[-1:] != m.shape[1:]:
        raise ValueError(f'theta must have shape (..., {m.shape[1]}), got {theta.shape}')
    angle = theta @ m.T                                             # (..., F)
    c, s = np.cos(angle), np.sin(angle)
    is_sin = np.asarray(kinds) == 1
    values = np.where(is_sin, s, c)
    if not gradient:
        return values
    slope = np.where(is_sin, c, -s)                                 # d value / d angle
    return values, slope[..., None] * m


def mass_support(i: int, j: int, n_joints: int) -> Tuple[int, ...]:
    """Return the joints (0-based) M_ij of a serial chain depends on: those after min(i, j)."""
    return tuple(range(min(i, j) + 1, n_joints))


@dataclass(frozen=True)
class TrigBasis:
    """
    Which features each entry of M and the potential U use, for an n-joint serial arm.

    All features live in one table (:attr:`frequencies`, :attr:`kinds`: the union),
    evaluated once per θ; :attr:`mass_index` and :attr:`potential_index` select each term's
    features from it.

    Parameters
    ----------
    n_joints : int
        Number of joints n.
    mass_degree : {1, 2}
        Largest frequency per joint in M: 2 for a general (spatial) arm, 1 where all axes
        are parallel.
    planar : bool
        All axes parallel: runs of consecutive joints only (module docstring).
    tied : bool
        With ``planar``: M = Sᵀ D S (module docstring), one coefficient per link pair
        instead of one per entry and feature.
    max_order : int, optional
        At most this many joints per mode of M; None: no limit.
    chain : bool
        Prune by the serial-chain structure (M_ij over the joints after min(i, j)); False
        gives every entry the modes of all joints (for counting and for tests).
    potential_skips_first : bool
        Gravity parallel to the first joint's axis: U does not depend on θ1.

    Attributes
    ----------
    frequencies : ndarray of int8, shape (F, n)
    kinds : ndarray of int8, shape (F,)
        The union of the features; the constant is feature 0.
    mass_entries : ndarray of int, shape (E, 2)
        The upper triangle (i <= j) of M, row by row.
    mass_index : tuple of E ndarrays of int
        Features of each entry (indices into the table).
    mass_tie : ndarray, shape (Σ_e |mass_index[e]|, C) or None
        ``tied``: the entries' feature coefficients are ``mass_tie @ c``, c the C = n²
        free ones (D_kk, then a_kl and b_kl per pair k > l).
    potential_index : ndarray of int
        Features of U (the constant left out: it exerts no torque).

    """

    n_joints: int
    mass_degree: int = 2
    planar: bool = False
    tied: bool = False
    max_order: Optional[int] = None
    chain: bool = True
    potential_skips_first: bool = False
    frequencies: np.ndarray = field(init=False, repr=False, compare=False)
    kinds: np.ndarray = field(init=False, repr=False, compare=False)
    mass_entries: np.ndarray = field(init=False, repr=False, compare=False)
    mass_index: Tuple[np.ndarray, ...] = field(init=False, repr=False, compare=False)
    mass_tie: Optional[np.ndarray] = field(init=False, repr=False, compare=False)
    potential_index: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        n = int(self.n_joints)
        if n != self.n_joints or n < 1:
            raise ValueError(f'n_joints must be a positive integer, got {self.n_joints}')
        if self.max_order is not None and int(self.max_order) < 1:
            raise ValueError(f'max_order must be >= 1 or None, got {self.max_order}')
        entries = np.array([(i, j) for i in range(n) for j in range(i, n)], dtype=int)
        per_entry = []
        for i, j in entries:
            joints = mass_support(i, j, n) if self.chain else range(n)
            if self.planar:
                per_entry.append(run_modes(n, joints))
            else:
                per_entry.append(modes(n, joints, self.mass_degree, self.max_order))
        first = 1 if self.potential_skips_first else 0
        if self.planar:
            potential = run_modes(n, range(first, n), prefixes=True)
        else:
            m, k = modes(n, range(first, n), 1)
            potential = (m[1:], k[1:])
        keys = np.vstack([np.column_stack([m, k]) for m, k in per_entry + [potential]])
        union = np.unique(keys, axis=0)                    # the constant sorts first
        lookup = {row.tobytes(): k for k, row in enumerate(union)}

        def index(m, k):
            rows = np.column_stack([m, k]).astype(union.dtype)
            return np.array([lookup[r.tobytes()] for r in rows], dtype=int)

        object.__setattr__(self, 'frequencies', union[:, :n].astype(np.int8))
        object.__setattr__(self, 'kinds', union[:, n].astype(np.int8))
        object.__setattr__(self, 'mass_entries', entries)
        object.__setattr__(self, 'mass_index', tuple(index(*mk) for mk in per_entry))
        object.__setattr__(self, 'potential_index', index(*potential))
        if self.tied and not (self.planar and self.chain):
            raise ValueError('tied needs planar (and chain)')
        object.__setattr__(self, 'mass_tie', self._tie() if self.tied else None)

    def _tie(self) -> np.ndarray:
        """Return the map from (D_kk, a_kl, b_kl) to the entries' feature coefficients."""
        n = self.n_joints
        pairs = [(k, j) for k in range(n) for j in range(k)]          # k > j
        names = {}
        for f, (freq, kind) in enumerate(zip(self.frequencies.tolist(), self.kinds.tolist())):
            names[(tuple(freq), kind)] = f
        rows = []
        for (i, j), ix in zip(self.mass_entries, self.mass_index):
            position = {int(f): r for r, f in enumerate(ix)}
            block = np.zeros((ix.size, n + 2 * len(pairs)))
            for k in range(max(i, j), n):                               # D_kk, constant
                block[position[0], k] += 1.0
            for p, (k, m) in enumerate(pairs):
                # ordered pairs (k, m) and (m, k) of M_ij = Σ_{a >= i, b >= j} D_ab
                count = int(k >= i and m >= j) + int(m >= i and k >= j)
                if count == 0:
                    continue
                run = np.zeros(n, dtype=int)
                run[m + 1:k + 1] = 1
                block[position[names[(tuple(run), 0)]], n + p] += count
                block[position[names[(tuple(run), 1)]], n + len(pairs) + p] += count
            rows.append(block)
        return np.vstack(rows)

    @property
    def n_features(self) -> int:
        """Size F of the feature table."""
        return self.kinds.size

    @property
    def n_entry_features(self) -> int:
        """Features of all the entries of M together (Σ_e |mass_index[e]|)."""
        return int(sum(ix.size for ix in self.mass_index))

    @property
    def n_mass_coefficients(self) -> int:
        """Free coefficients of M (n² when ``tied``, else one per entry and feature)."""
        return self.n_joints ** 2 if self.tied else self.n_entry_features

    @property
    def n_potential_coefficients(self) -> int:
        """Coefficients of U."""
        return int(self.potential_index.size)

    @property
    def constant(self) -> int:
        """Index of the constant feature in the table."""
        return 0

    def values(self, theta, gradient: bool = False):
        """Return :func:`evaluate_features` of the whole table at ``theta`` (..., n)."""
        return evaluate_features(self.frequencies, self.kinds, theta, gradient)

    def names(self) -> Tuple[str, ...]:
        """Return the names of the table's features (:func:`feature_names`)."""
        return feature_names(self.frequencies, self.kinds)

    def to_dict(self) -> Dict[str, object]:
        """Return the settings that rebuild this basis (for a model file)."""
        return {'n_joints': int(self.n_joints), 'mass_degree': int(self.mass_degree),
                'planar': bool(self.planar), 'tied': bool(self.tied),
                'max_order': None if self.max_order is None else int(self.max_order),
                'chain': bool(self.chain),
                'potential_skips_first': bool(self.potential_skips_first)}


def feature_counts(n_joints: int, mass_degree: int = 2, max_order: Optional[int] = None,
                   chain: bool = True, planar: bool = False,
                   tied: bool = False) -> Dict[str, int]:
    """
    Return how many coefficients M and U take for a basis setting, in closed form.

    An entry over m joints takes Σ_{k <= K} C(m, k) (2 degree)^k features (K = min(m,
    max_order)), or m (m + 1) + 1 when ``planar``; U takes 3^n - 1 (planar: 2n). No table
    is built, so any n is cheap.

    Returns
    -------
    dict
        ``mass``, ``potential`` and ``total`` coefficient counts.

    """
    n = int(n_joints)
    order = n if max_order is None else int(max_order)

    def count(m):
        if planar:
            return m * (m + 1) + 1
        return sum(comb(m, k) * (2 * mass_degree) ** k for k in range(min(m, order) + 1))

    if tied:
        mass = n * n
    else:
        mass = sum(count(n - 1 - min(i, j) if chain else n)
                   for i in range(n) for j in range(i, n))
    potential = 2 * n if planar else 3 ** n - 1
    return {'mass': mass, 'potential': potential, 'total': mass + potential}

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
The search for a chain: its numbers, local refinement, the symmetries, and what was found.

:class:`ChainCoding` writes a chain of n revolute joints as 4 n − 4 numbers with every
freedom that changes nothing removed: modified DH (:func:`~..rigid.chain.dh_of_lines`)
with the first axis as the base's z and the first common normal as its x, so the first
joint has no numbers; gravity's tilt β from -z and azimuth γ (its magnitude fixed); the
last joint's offset and d dropped (its frame slides and turns along its axis freely, the
body's parameters follow). Per joint i = 1 ... n − 1: α_i, a_i, then (but for the last)
offset_i, d_i. Angles are in units of π, lengths of :data:`LENGTH_UNIT`, lengths bounded by
:data:`MAX_LENGTH`. What stays free: γ when the first axis is vertical, and for parallel
neighbours the place of their common normal along them (d_i against d_{i-1}).

:func:`refine` is Levenberg-Marquardt's kind (scipy's bounded trust region, ``trf``) on
the variable-projection residual of :class:`~.chain_rows.ChainScore`. Two chains give
exactly the same dynamics when one is the other's mirror image (every axis turned: a
symmetry, nothing to fix); an axis turned alone nearly does when the body it drives is
nearly symmetric about it and light, and the search settles there. :func:`turn_axes`
tries each axis turned (the same line, reversed) from the best chain and keeps what
refines lower. :func:`multistart` draws starts, refines each, and stops once the best cost
was reached :data:`AGREE` times. :func:`determinacy` says how well the data fix each axis:
the Gauss-Newton covariance of the numbers, s² (JᵀJ)⁺ with s² the residual variance per
row, carried to each axis direction (degrees) and its line's place (m); infinite where a
direction the data leave free moves it.
"""

import math
import time
from typing import List, NamedTuple, Optional

import numpy as np

from .chain_rows import ChainScore
from ..rigid.chain import Chain, chain_tree, dh_of_lines, from_dh, lines
from ..rigid.kernels import Tree

__all__ = ['AGREE', 'ChainCoding', 'LENGTH_SCALE', 'LENGTH_UNIT', 'Local', 'MAX_LENGTH',
           'SEARCH_PRIOR', 'determinacy', 'multistart', 'refine', 'turn_axes']

#: Metres per unit of a length in the coding.
LENGTH_UNIT = 0.5

#: Largest |a| and |d| (m) a chain may have.
MAX_LENGTH = 2.0

#: Length (m) the pull towards a compact arm divides the lengths by (:func:`refine`).
LENGTH_SCALE = 0.25

#: The search's pull λ towards a compact arm (a share of the relative torque residual).
SEARCH_PRIOR = 1e-8

#: Starts that must reach the best cost (within :data:`AGREE_SHARE`) to stop the search.
AGREE = 2

#: Relative difference of two costs that count as the same minimum.
AGREE_SHARE = 0.02

#: A singular value of the residual's Jacobian below this share of the largest: a
#: direction the data leave free.
FREE_SHARE = 1e-10

#: A free direction moving an axis, a line or gravity by more than this (per unit of the
#: numbers) leaves it undetermined.
MOVED = 1e-3


class ChainCoding:
    """The numbers of a chain of ``n_joints`` revolute joints (module docstring)."""

    def __init__(self, n_joints: int, gravity: float = 9.81):
        if n_joints < 1:
            raise ValueError(f'a chain needs at least one joint, got {n_joints}')
        self.n = int(n_joints)
        self.gravity = float(gravity)
        angles, lengths = [0, 1], []
        k = 2
        for i in range(1, self.n):
            angles.append(k)
            lengths.append(k + 1)
            k += 2
            if i < self.n - 1:
                angles.append(k)
                lengths.append(k + 1)
                k += 2
        self.size = k
        self.angles = np.array(angles, dtype=int)
        self.lengths = np.array(lengths, dtype=int)

    def dh(self, x):
        """Return (alpha, a, offset, d) (n,) each and gravity (3,) of numbers ``x``."""
        x = np.asarray(x, dtype=float).reshape(-1)
        if x.size != self.size:
            raise ValueError(f'{self.size} numbers expected, got {x.size}')
        alpha, a, offset, d = (np.zeros(self.n) for _ in range(4))
        k = 2
        for i in range(1, self.n):
            alpha[i], a[i] = math.pi * x[k], LENGTH_UNIT * x[k + 1]
            k += 2
            if i < self.n - 1:
                offset[i], d[i] = math.pi * x[k], LENGTH_UNIT * x[k + 1]
                k += 2
        beta, gamma = math.pi * x[0], math.pi * x[1]
        gravity = self.gravity * np.array([-math.sin(beta) * math.cos(gamma),
                                           -math.sin(beta) * math.sin(gamma), -math.cos(beta)])
        return alpha, a, offset, d, gravity

    def chain(self, x) -> Chain:
        """Return the chain of numbers ``x``."""
        return from_dh(*self.dh(x))

    def tree(self, x) -> Tree:
        """Return the kernels' tree of numbers ``x``."""
        return chain_tree(self.chain(x))

    def bounds(self):
        """Return the (lower, upper) bounds of the numbers: the lengths' only."""
        lower = np.full(self.size, -np.inf)
        upper = np.full(self.size, np.inf)
        lower[self.lengths] = -MAX_LENGTH / LENGTH_UNIT
        upper[self.lengths] = MAX_LENGTH / LENGTH_UNIT
        return lower, upper

    def sample(self, rng: np.random.Generator, length_scale: float = 0.2) -> np.ndarray:
        """Return random numbers: angles uniform, lengths normal of ``length_scale`` (m)."""
        x = np.empty(self.size)
        x[self.angles] = rng.uniform(-1.0, 1.0, self.angles.size)
        x[self.lengths] = rng.normal(0.0, length_scale / LENGTH_UNIT, self.lengths.size)
        lower, upper = self.bounds()
        return np.clip(x, lower, upper)

    def wrap(self, x) -> np.ndarray:
        """Return ``x`` with every angle in [-1, 1) (units of π)."""
        x = np.array(x, dtype=float)
        x[self.angles] = (x[self.angles] + 1.0) % 2.0 - 1.0
        return x

    def numbers(self, chain: Chain) -> np.ndarray:
        """Return the numbers of any chain of n joints (gravity's magnitude aside)."""
        axes, points = lines(chain)
        return self.of_lines(axes, points, chain.gravity)

    def of_lines(self, axes, points, gravity) -> np.ndarray:
        """Return the numbers of the chain whose axes are these lines (and gravity)."""
        dh = dh_of_lines(axes, points, gravity)
        g = dh.gravity
        x = np.empty(self.size)
        x[0] = math.atan2(math.hypot(g[0], g[1]), -g[2]) / math.pi
        x[1] = math.atan2(-g[1], -g[0]) / math.pi
        k = 2
        for i in range(1, self.n):
            x[k], x[k + 1] = dh.alpha[i] / math.pi, dh.a[i] / LENGTH_UNIT
            k += 2
            if i < self.n - 1:
                x[k], x[k + 1] = dh.offset[i] / math.pi, dh.d[i] / LENGTH_UNIT
                k += 2
        return self.wrap(x)

    def turned(self, x, joint: int) -> np.ndarray:
        """Return the numbers of ``x``'s chain with the axis of ``joint`` reversed."""
        chain = self.chain(x)
        axes, points = lines(chain)
        axes[joint] = -axes[joint]
        return self.of_lines(axes, points, chain.gravity)


class Local(NamedTuple):
    """A refined chain: its numbers, cost and the residual evaluations it took."""

    x: np.ndarray
    cost: float
    evaluations: int


def refine(score: ChainScore, coding: ChainCoding, x0, max_iterations: int = 40,
           tolerance: float = 1e-8, prior: float = 0.0) -> Local:
    """
    Return the local minimum of ``score`` from ``x0`` (module docstring).

    ``prior`` λ adds λ Σ (L / :data:`LENGTH_SCALE`)² over the lengths L to the cost: a pull
    towards a compact arm where the data leave a length free. The cost returned is the
    data's alone.
    """
    from scipy.optimize import least_squares
    lower, upper = coding.bounds()
    x0 = np.clip(np.asarray(x0, dtype=float), lower, upper)
    start = score.evaluations
    pull = math.sqrt(max(prior, 0.0)) * LENGTH_UNIT / LENGTH_SCALE
    lengths = coding.lengths

    def residual(x):
        return np.concatenate([score.residual(coding.tree(x)), pull * x[lengths]])

    def jacobian(x):
        extra = np.zeros((lengths.size, x.size))
        extra[np.arange(lengths.size), lengths] = pull
        return np.vstack([score.jacobian(coding.tree, x)[1], extra])

    result = least_squares(residual, x0, jac=jacobian, bounds=(lower, upper), method='trf',
                           x_scale=1.0, max_nfev=int(max_iterations), xtol=tolerance,
                           ftol=tolerance, gtol=tolerance)
    x = coding.wrap(result.x)
    return Local(x, score.cost(coding.tree(x)), score.evaluations - start)


def turn_axes(score: ChainScore, coding: ChainCoding, best: Local,
              max_iterations: int = 40, prior: float = 0.0) -> Local:
    """Return the best of ``best`` and each single axis turned, refined (module docstring)."""
    improved = True
    evaluations = best.evaluations
    while improved:
        improved = False
        for joint in range(coding.n):
            other = refine(score, coding, coding.turned(best.x, joint), max_iterations,
                           prior=prior)
            evaluations += other.evaluations
            if other.cost < best.cost * (1.0 - AGREE_SHARE):
                best, improved = other, True
    return best._replace(evaluations=evaluations)


class SearchResult(NamedTuple):
    """What :func:`multistart` found."""

    best: Local
    #: every start's local minimum, in the order refined
    minima: List[Local]
    #: how many starts reached the best cost (within AGREE_SHARE)
    agreeing: int
    evaluations: int
    seconds: float
    message: str


def multistart(score: ChainScore, coding: ChainCoding, rng: np.random.Generator,
               max_starts: int = 40, time_budget: float = math.inf,
               agree: int = AGREE, max_iterations: int = 40,
               turn_below: float = 0.05) -> SearchResult:
    """
    Refine random starts until the best cost was reached ``agree`` times (module docstring).

    A start whose minimum is the best so far and leaves less than ``turn_below`` of the
    torque unexplained gets its axes turned (:func:`turn_axes`). Stops after ``max_starts``
    starts or once ``time_budget`` (s) is spent.
    """
    began = time.monotonic()
    minima: List[Local] = []
    best: Optional[Local] = None
    agreeing, evaluations = 0, 0
    message = f'{max_starts} starts'
    for _ in range(max_starts):
        if time.monotonic() - began > time_budget:
            message = f'time budget of {time_budget:.0f} s spent'
            break
        local = refine(score, coding, coding.sample(rng), max_iterations, prior=SEARCH_PRIOR)
        evaluations += local.evaluations
        if local.cost < turn_below and (best is None or local.cost < best.cost):
            local = turn_axes(score, coding, local, max_iterations, SEARCH_PRIOR)
            evaluations += local.evaluations
        minima.append(local)
        if best is not None and abs(local.cost - best.cost) <= AGREE_SHARE * best.cost:
            agreeing += 1
        elif best is None or local.cost < best.cost:
            best, agreeing = local, 1
        if agreeing >= agree:
            message = f'best reached {agreeing} times'
            break
    return SearchResult(best, minima, agreeing, evaluations, time.monotonic() - began,
                        message)


def determinacy(score: ChainScore, coding: ChainCoding, x, step: float = 1e-6) -> dict:
    """
    Return how well the rows fix the chain of ``x`` (module docstring).

    ``axis_deg`` (n,): standard deviation of each axis direction (deg); ``line_m`` (n,):
    of its line's place across the axis (m); ``gravity_tilt_deg``: of gravity's angle to the
    first axis; each infinite where a number the data leave free (a singular value below
    :data:`FREE_SHARE` of the largest) moves it. ``singular_values``: of the Jacobian of
    the relative residual; ``free_directions``: how many are free; ``residual_share``:
    ‖r‖², the unexplained share. The rows count as independent, which filtered rows are
    not quite: the deviations are lower bounds.
    """
    r, jac = score.jacobian(coding.tree, x)
    n_rows, n_numbers = jac.shape
    dof = max(n_rows - n_numbers - score.rows.columns.size, 1)
    variance = float(r @ r) / dof
    _, s, vt = np.linalg.svd(jac, full_matrices=False)
    kept = s > FREE_SHARE * s[0] if s.size else np.zeros(0, dtype=bool)
    covariance = variance * ((vt[kept].T / s[kept] ** 2) @ vt[kept])
    free = vt[~kept]
    axes0, points0 = lines(coding.chain(x))
    d_axes = np.empty((coding.n, 3, n_numbers))
    d_points = np.empty((coding.n, 3, n_numbers))
    d_tilt = np.zeros((1, n_numbers))
    d_tilt[0, 0] = math.pi         # gravity's angle to the first axis, β = π x[0]
    for k in range(n_numbers):
        moved = np.array(x, dtype=float)
        moved[k] += step
        axes, points = lines(coding.chain(moved))
        d_axes[:, :, k] = (axes - axes0) / step
        d_points[:, :, k] = (points - points0) / step

    def deviation(g):
        if free.size and np.max(np.abs(g @ free.T)) > MOVED:
            return math.inf
        return math.sqrt(max(float(np.trace(g @ covariance @ g.T)), 0.0))

    axis_sd = [math.degrees(deviation(d_axes[i])) for i in range(coding.n)]
    line_sd = [deviation((np.eye(3) - np.outer(axes0[i], axes0[i])) @ d_points[i])
               for i in range(coding.n)]
    return {'axis_deg': axis_sd, 'line_m': line_sd,
            'gravity_tilt_deg': math.degrees(deviation(d_tilt)),
            'singular_values': s.tolist(), 'free_directions': int(np.sum(~kept)),
            'residual_share': float(r @ r), 'rows': int(n_rows)}

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
The global network: the arm's closed-form fit on the trigonometric basis, then its rollouts.

A network whose θ-features are the trigonometric basis ('trig', 'trig3d'), with M's entries
as outputs (``inertia='penalty'``) and V from M's Christoffel symbols, is linear in its
weights, and so is the arm model of :mod:`..model.trig_dynamics`: the two are the same
model when the weights are a fixed linear image of the arm's coefficients (M's entries are
the features' coefficients, G = ∇U is again in the span of the Fourier modes). This module
builds that image (:class:`CoefficientMap`, exact to rounding), which gives the search two
things:

- a start that needs no search: :class:`~.linear.LinearDynamics` fits the coefficients in
  closed form (a second for 20 s of a 3-joint arm, its ridge and θ̈ window chosen on held-out
  samples, M certified positive on the joint range), and its genome is the same model;
- a refinement in the arm's own coefficients: Levenberg-Marquardt on the rollout
  residuals over the coefficients (21 for the paper's tied planar arm, against 123 genome
  elements) keeps every candidate a rigid body (M from one energy, G a gradient, friction
  dissipative), so the fit of the rollouts cannot trade the physics away for the training
  path. The equation-error fit sees θ̈ only through a smoother; the rollout sees the motion
  itself, and removes that bias (README: the held-out figures of both).

:func:`global_spec` is the structure, :func:`linear_fit` the closed-form fit for a case,
:func:`coefficient_map` the image, :class:`CoefficientProblem` a fitness problem over
coefficients (what :func:`~.refine.refine_lm` and CMA-ES take); the staged search within a
wall-time budget is :func:`.global_search.fit_global`.
"""

from dataclasses import replace
from typing import NamedTuple, Optional, Sequence

import numpy as np

from .fitness import FitnessProblem
from .linear import LinearDynamics
from ..data import Dataset
from ..differentiate import centred_derivative, CENTRED_MIN_SAMPLES
from ..model.scales import Scales
from ..model.spec import NetworkSpec
from ..model.trig import TrigBasis
from ..model.trig_dynamics import Layout, unpack_mass

__all__ = ['CoefficientMap', 'CoefficientProblem', 'closed_form_genome', 'coefficient_map',
           'global_spec', 'is_global', 'linear_fit', 'trig_table', 'variable_unit']

#: Bases whose features are a :class:`~..model.trig.TrigBasis` table (the first of a sum).
TRIG_BASES = ('trig', 'trig3d')

#: Random configurations on which the image of the coefficients is fitted (per feature).
_POINTS_PER_FEATURE = 4

#: Largest relative residual of that image: beyond it the basis does not span the arm.
MAP_TOLERANCE = 1e-8


def global_spec(n_joints: int, case: str, basis: str = 'trig') -> NetworkSpec:
    """
    Return the global network's structure for ``case``.

    The features of ``basis`` (a trigonometric basis, alone or first in a sum such as
    'trig+rbf'), M's upper triangle as outputs (linear in the weights; positive definite
    on the joint range as the closed-form fit certifies it, the paper's minor penalty
    beside), V from M's Christoffel symbols, a constant per output, viscous and Coulomb
    friction, and in case 3 a linear PD torque network (no RBF torque units: the servo's
    law is what the closed-form fit identifies).
    """
    spec = NetworkSpec(n_joints=int(n_joints), case=case, theta_units=3, torque_units=0,
                       inertia='penalty', bias=True, friction=True,
                       torque_linear=case == 'unknown', velocity='christoffel', basis=basis)
    if not is_global(spec):
        raise ValueError(f'basis {basis!r}: the global network needs a trigonometric basis '
                         f'first ({", ".join(TRIG_BASES)})')
    return spec


def is_global(spec: NetworkSpec) -> bool:
    """Return True if ``spec`` is linear in the weights of a trigonometric basis first."""
    return (spec.bases[0].name in TRIG_BASES and spec.inertia == 'penalty'
            and spec.velocity == 'christoffel' and spec.bias and spec.friction
            and (spec.case != 'unknown' or (spec.torque_linear and spec.torque_units == 0)))


def trig_table(spec: NetworkSpec) -> TrigBasis:
    """
    Return the :class:`~..model.trig.TrigBasis` the closed-form fit uses for ``spec``.

    The network basis's own table; for the planar 'trig' the tied one (M = Sᵀ D S: n²
    coefficients, one per link pair, instead of one per entry and feature).
    """
    basis = spec.bases[0]
    table = basis.table(spec.n_joints)
    return replace(table, tied=True) if basis.name == 'trig' else table


def linear_fit(datasets: Sequence[Dataset], case: str, table: TrigBasis, kp=None, kd=None,
               coulomb_velocity: float = 0.05,
               deadline: Optional[float] = None) -> LinearDynamics:
    """
    Fit the arm (case 3: the arm and its PD servo, mean Kp 1) on ``table`` in closed form.

    ``deadline``: see :meth:`.linear.LinearDynamics.fit`.

    Case 3's θ̇ is the centred derivative of θ: without torque, θ̈ comes from θ̇ alone and a
    differenced velocity's noise would reach it amplified; segments too short for it
    (fewer than :data:`~..differentiate.CENTRED_MIN_SAMPLES`) are left out. ValueError
    when no segment is left or the samples are too few to fit.
    """
    fit = LinearDynamics(table, coulomb_velocity)
    if case == 'unknown':
        smooth = [replace(seg, theta_dot=centred_derivative(seg.theta, seg.dt))
                  for seg in datasets if seg.n_samples >= CENTRED_MIN_SAMPLES]
        if not smooth:
            raise ValueError(f'no segment of at least {CENTRED_MIN_SAMPLES} samples to fit')
        return fit.fit(smooth, 'unknown', deadline=deadline)
    if not datasets:
        raise ValueError('no segment to fit')
    kp, kd = (kp, kd) if case == 'pd_gains' else (None, None)
    return fit.fit(list(datasets), case, kp, kd, deadline=deadline)


class CoefficientMap(NamedTuple):
    """
    The genome of the global network as an affine image of the arm's coefficients.

    ``genome = matrix @ coef + offset``; ``coef`` in the order of :class:`Layout`
    ([M | U | f_v | f_c] and, in case 3, Kp and Kd).
    """

    matrix: np.ndarray      # (N, C)
    offset: np.ndarray      # (N,)
    layout: Layout
    table: TrigBasis

    def genomes(self, coefficients) -> np.ndarray:
        """Return the genomes of coefficient rows, shape (P, N) for (P, C)."""
        return np.atleast_2d(coefficients) @ self.matrix.T + self.offset

    def genome(self, coefficients) -> np.ndarray:
        """Return the genome of one coefficient vector, shape (N,)."""
        return self.genomes(coefficients)[0]


def coefficient_map(spec: NetworkSpec, scales: Scales, table: TrigBasis,
                    layout: Layout, rng=0) -> CoefficientMap:
    """
    Return the :class:`CoefficientMap` of ``spec`` (a global network) for ``table``.

    The weights of the trigonometric features and the output constants are fitted to M's
    entries and G on random configurations of the torus (exact when the basis spans the
    table's M and U: checked, ValueError otherwise); friction and gains map one to one.
    The blocks of further bases in a sum keep their initial values with zero weights.
    """
    if not is_global(spec):
        raise ValueError('coefficient_map needs a global network (global_spec)')
    n = spec.n_joints
    basis = spec.bases[0]
    codes, data = basis.codes(spec), basis.decode(spec, {}, scales)[0]
    size = data.shape[0]
    rng = np.random.default_rng(rng)
    theta = rng.uniform(-np.pi, np.pi, (max(64, _POINTS_PER_FEATURE * (size + 1)), n))
    design = np.hstack([basis.features(theta, codes, data), np.ones((theta.shape[0], 1))])
    pinv = np.linalg.pinv(design)                                   # (F + 1, S)
    phi, grad = table.values(theta, gradient=True)                  # (S, Ft), (S, Ft, n)
    upper = np.triu_indices(n)                                      # row-major, = penalty

    columns = []
    for c in np.eye(layout.size):
        mass = np.einsum('sf,fij->sij', phi, unpack_mass(table, c[layout.mass]))
        pot = np.zeros(table.n_features)
        pot[table.potential_index] = c[layout.potential]
        targets = np.hstack([mass[:, upper[0], upper[1]],                     # (S, n_out)
                             np.einsum('sfk,f->sk', grad, pot)])
        weights = pinv @ targets                                        # (F + 1, n_out)
        scale = max(float(np.abs(targets).max()), 1e-300)
        if np.abs(design @ weights - targets).max() > MAP_TOLERANCE * scale:
            raise ValueError(f'the basis {spec.basis!r} does not span the arm model of its '
                             'table')
        columns.append(weights)

    out_scale = spec.output_scales(scales)
    blocks = {b.name: b for b in spec.blocks()}
    offset = spec.initial_genome()
    for name in ('theta_weights', 'theta_bias', 'friction', 'pd_linear'):
        if name in blocks:
            offset[blocks[name].start:blocks[name].stop] = 0.0
    matrix = np.zeros((spec.genome_size, layout.size))
    w_block, b_block = blocks['theta_weights'], blocks['theta_bias']
    for k, weights in enumerate(columns):
        w = np.zeros(w_block.shape)                                  # (n_out, F_all)
        w[:, :size] = weights[:size].T / out_scale[:, None]
        matrix[w_block.start:w_block.stop, k] = w.ravel()
        matrix[b_block.start:b_block.stop, k] = weights[size] / out_scale
    friction = blocks['friction'].start                             # (2, n): viscous, coulomb
    viscous_unit = 0.1 * scales.torque / scales.velocity
    coulomb_unit = 0.1 * scales.torque
    for j in range(n):
        matrix[friction + j, layout.viscous.start + j] = 1.0 / viscous_unit[j]
        matrix[friction + n + j, layout.coulomb.start + j] = 1.0 / coulomb_unit[j]
    if layout.kp is not None:
        gains = blocks['pd_linear'].start                            # (2, n): kp, kd
        for j in range(n):
            matrix[gains + j, layout.kp.start + j] = scales.error[j] / scales.torque[j]
            matrix[gains + n + j, layout.kd.start + j] = scales.error_rate[j] / scales.torque[j]
    return CoefficientMap(matrix, offset, layout, table)


class CoefficientProblem:
    """
    A :class:`~.fitness.FitnessProblem` seen through a :class:`CoefficientMap`.

    Its variables are the arm's coefficients divided by ``unit`` (so each is of order one
    at the start); it has what :func:`~.refine.refine_lm` and the optimizers use:
    ``rollouts``, ``cost``, ``scales``, ``x_meas``.
    """

    def __init__(self, problem: FitnessProblem, cmap: CoefficientMap, unit: np.ndarray):
        self.problem = problem
        self.cmap = cmap
        self.unit = np.asarray(unit, dtype=float)
        self.scales = problem.scales
        self.x_meas = problem.x_meas

    def genomes(self, x) -> np.ndarray:
        """Return the genomes of variable rows ``x`` (P, C)."""
        return self.cmap.genomes(np.atleast_2d(x) * self.unit)

    def rollouts(self, x) -> np.ndarray:
        """Rollouts of the problem for variable rows ``x``."""
        return self.problem.rollouts(self.genomes(x))

    def cost(self, x) -> np.ndarray:
        """Return J of variable rows ``x``, shape (P,)."""
        return self.problem.cost(self.genomes(x))


def variable_unit(coefficients, floor: float = 1e-3) -> np.ndarray:
    """Return per-coefficient units: |c|, at least ``floor`` of the largest |c|."""
    c = np.abs(np.asarray(coefficients, dtype=float))
    return np.maximum(c, floor * max(float(c.max()), 1e-300))


def closed_form_genome(spec: NetworkSpec, train: Sequence[Dataset], scales: Scales, kp=None,
                       kd=None) -> np.ndarray:
    """
    Return the genome of :func:`linear_fit` on ``train`` for ``spec``, shape (N,).

    The online search's start (:func:`..search_starts.warm_start`): the closed form, under
    a second; the rollout refinement over the coefficients
    (:func:`.global_search.fit_global`'s) takes tens of seconds, too long to hold a running
    search.
    """
    table = trig_table(spec)
    arm = linear_fit(list(train), spec.case, table, kp, kd, spec.coulomb_velocity)
    return coefficient_map(spec, scales, table, arm.layout_).genome(arm.full_coefficients)

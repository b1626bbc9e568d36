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
The global network's search within a wall-time budget: closed form, then rollouts.

:func:`fit_global` runs stages in order, each on what is left of the budget when it starts
(:class:`~.budget.Budget`: wall time, so on a busy machine the later stages get less), with
every rollout of the training data interruptible at the budget's end
(:meth:`~.budget.Budget.interrupting`), which they keep :data:`FINISH_SHARE` of it before:

1. ``linear``: the closed-form fit on the trigonometric basis
   (:func:`.global_fit.linear_fit`), mapped into the genome. It always runs and is the
   fallback: its rounds that keep M positive stop after :data:`CLOSED_FORM_SHARE` of the
   budget (``late``), so that it is mapped and scored in the rest;
2. ``lm``: Levenberg-Marquardt on the rollout residuals over the arm's coefficients, one
   stage per multiple-shooting interval, within ``lm_fraction`` of the time left after the
   closed form;
3. ``cmaes``: CMA-ES over the coefficients until the budget ends, a generation would not
   fit in what is left (the last one's duration), a generation or evaluation limit, or
   ``stall_generations`` generations without a lower J.

A stage is a function ``stage(search, budget, options)`` that hands coefficients to
:meth:`_Search.record`: they become the search's best only if they lower J on the training
data (later stages start from the best fit so far), and each best is scored on the
held-out data. Another fit of the arm's coefficients (a rigid-body regressor, say) is one
more function in :data:`STAGES`. The result is the best with the lowest held-out θ-NRMSE
(the training J when nothing is held out); when no stage has a finite J (every rollout
diverged, or the budget ended before the closed form was scored) it is the closed form,
and :attr:`GlobalFit.warning` says why. A closed form that cannot be fitted at all raises
a ValueError naming the cause.
"""

import math
from typing import Callable, List, NamedTuple, Optional, Sequence

import numpy as np

from .budget import Budget
from .fitness import FitnessProblem, Interrupted
from .global_fit import (coefficient_map, CoefficientProblem, linear_fit, trig_table,
                         variable_unit)
from .linear import LinearDynamics
from ..data import Dataset
from ..model.scales import Scales
from ..model.spec import NetworkSpec

__all__ = ['CLOSED_FORM_SHARE', 'FINISH_SHARE', 'GlobalFit', 'RolloutSetup', 'SearchOptions',
           'STAGES', 'fit_global']

#: Share of the budget after which the closed form's rounds that keep M positive stop.
CLOSED_FORM_SHARE = 0.4

#: Share of the budget the stages leave free at its end: the chunk of rollouts in progress
#: when their time is up, the scoring of a last result and the model finish in it.
FINISH_SHARE = 0.05


class GlobalFit(NamedTuple):
    """What :func:`fit_global` found."""

    genome: np.ndarray          # the selected genome
    cost: float                 # its J on the training data (inf: diverged; NaN: not scored)
    validation_nrmse: float     # its θ-NRMSE on the validation data (NaN: none held out)
    phase: str                  # the stage it comes from
    history: List[dict]
    evaluations: int            # rollouts of the training data (equation fits count none)
    generations: int            # CMA-ES generations
    arm: LinearDynamics         # the closed-form fit the search started from
    warning: str = ''           # why the closed form is returned unjudged ('' otherwise)


class SearchOptions(NamedTuple):
    """How :func:`fit_global`'s stages search (module docstring)."""

    shootings: Sequence[int] = (20, 0)  # LM's multiple-shooting intervals (samples), in order
    lm_nfev: int = 30                   # LM's residual evaluations per interval, at most
    lm_fraction: float = 0.7            # LM's share of the time left after the closed form
    polish_sigma: float = 0.01          # CMA-ES's spread (share of each coefficient)
    max_generations: Optional[int] = None   # CMA-ES's generations, at most (None: no limit)
    max_evaluations: Optional[int] = None   # rollouts, at most (None: no limit)
    stall_generations: int = 40         # CMA-ES stops after this many without a lower J
    seed: int = 0                       # of CMA-ES's and the coefficient map's generators


class RolloutSetup(NamedTuple):
    """What a genome is rolled out with: the network, its scales, the RKG steps, the servo."""

    spec: NetworkSpec
    scales: Scales
    substeps: int                       # RKG steps per sample
    kp: Optional[np.ndarray] = None     # known servo gains (case 'pd_gains')
    kd: Optional[np.ndarray] = None
    torque_interpolation: str = 'linear'


class _Search:
    """The coefficients a :func:`fit_global` run has tried, its bests and its history."""

    def __init__(self, train, validation, setup: RolloutSetup, cmap, unit, budget: Budget,
                 on_stage):
        from ..model.model import RKGNNModel
        self.train, self.cmap, self.unit, self.budget = list(train), cmap, unit, budget
        self._settings = setup
        spec, scales, substeps, kp, kd, interpolation = setup
        self._model = lambda genome: RKGNNModel(spec, scales, genome, kp=kp, kd=kd,
                                                dt=train[0].dt, substeps=substeps,
                                                torque_interpolation=interpolation)
        self.validation = list(validation)
        self.on_stage = on_stage
        self._timed: List[FitnessProblem] = []   # the problems made since the last timed()
        self.full = self.problem_for(0)
        self.history: List[dict] = []
        self.kept: List[tuple] = []     # (validation error, cost, phase, x) of every best
        self.evaluations = 0
        self.generations = 0
        self.best_x = None
        self.best_cost = math.inf

    def problem_for(self, shooting: int) -> CoefficientProblem:
        """Return the problem of ``shooting``, timed as the full rollout was last."""
        spec, scales, substeps, kp, kd, interpolation = self._settings
        fitness = FitnessProblem(spec, self.train, scales=scales, substeps=substeps, kp=kp,
                                 kd=kd, shooting=int(shooting),
                                 torque_interpolation=interpolation)
        if hasattr(self, 'full'):
            fitness.seconds_per_candidate = self.full.problem.seconds_per_candidate
            self._timed.append(fitness)
        return CoefficientProblem(fitness, self.cmap, self.unit)

    def timed(self) -> None:
        """Give the full rollout's problem the most seconds per candidate any problem took."""
        seen = [p.seconds_per_candidate for p in [self.full.problem] + self._timed
                if p.seconds_per_candidate is not None]
        self.full.problem.seconds_per_candidate = max(seen) if seen else None
        self._timed = []

    def cost(self, x) -> float:
        """Return J of the variables ``x`` on the training data (one rollout)."""
        self.evaluations += 1
        return float(self.full.cost(x)[0])

    def validation_error(self, x) -> float:
        """Return the held-out θ-NRMSE of ``x`` (NaN: nothing held out, or no time left)."""
        from ..scoring import nrmse
        if not self.validation or self.budget.spent():
            return math.nan
        model = self._model(self.full.genomes(x)[0])
        n = self.validation[0].n_joints
        predicted = np.vstack([model.predict(seg)[:, :n] for seg in self.validation])
        return nrmse(predicted, np.vstack([seg.theta for seg in self.validation]))

    def record(self, phase: str, x, cost: float, **extra) -> None:
        """Record a stage's coefficients ``x`` and their J; they become the best if lower."""
        better = bool(cost < self.best_cost)
        entry = dict(extra, phase=phase, cost=float(cost), kept=better)
        if better:
            self.best_x, self.best_cost = np.array(x, dtype=float), float(cost)
            entry['validation_nrmse'] = self.validation_error(self.best_x)
            self.kept.append((entry['validation_nrmse'], float(cost), phase, self.best_x))
        self._add(entry)

    def interrupted(self, phase: str) -> None:
        """Record that the budget ended during ``phase``."""
        self._add({'phase': phase, 'cost': math.nan, 'kept': False, 'interrupted': True})

    def skipped(self, phase: str, why: str) -> None:
        """Record that ``phase`` was not started: ``why``."""
        self._add({'phase': phase, 'cost': math.nan, 'kept': False, 'skipped': why})

    def _add(self, entry: dict) -> None:
        entry.update(best_cost=self.best_cost, evaluations=self.evaluations)
        self.history.append(entry)
        if self.on_stage is not None:
            self.on_stage(entry)


def _closed_form(search: _Search, budget: Budget, options: SearchOptions, arm) -> None:
    """Stage 1: score the closed form (its coefficients are the start of every search)."""
    search.best_x = arm.full_coefficients / search.unit
    search.record('linear', search.best_x, search.cost(search.best_x),
                  ridge=float(arm.ridge_), window_samples=int(arm.window_),
                  certified=bool(arm.certificate_ is not None and arm.certificate_.certified),
                  late=bool(getattr(arm, 'late_', False)))


def _levenberg_marquardt(search: _Search, budget: Budget, options: SearchOptions, arm) -> None:
    """Stage 2: LM per shooting interval, within ``lm_fraction`` of what is left."""
    from .refine import refine_lm
    lm = Budget(options.lm_fraction * budget.left(), budget.clock)
    for shooting in options.shootings:
        if lm.spent():
            break
        per = search.full.problem.seconds_per_candidate
        need = None if per is None else per * (search.best_x.size + 2)
        if need is not None and lm.left() < need:   # not one step: a residual and a Jacobian
            search.skipped('lm', f'one step ({search.best_x.size + 2} rollouts, about '
                                 f'{need:.0f} s) would not fit in {lm.left():.0f} s')
            break
        with lm.interrupting():
            x, steps = refine_lm(search.problem_for, search.best_x, (shooting,),
                                 options.lm_nfev, deadline=lm.deadline())
        search.timed()
        search.evaluations += steps[-1]['evaluations'] if steps else 0
        unchanged = np.array_equal(x, search.best_x)    # nothing better found: not scored
        search.record('lm', x, search.best_cost if unchanged else search.cost(x),
                      shooting=int(shooting))


def _cmaes(search: _Search, budget: Budget, options: SearchOptions, arm) -> None:
    """Stage 3: CMA-ES around the best coefficients until the budget or a limit ends it."""
    per = search.full.problem.seconds_per_candidate
    if per is not None and budget.left() < per:
        return                              # not one rollout would fit
    from .optimizers import make_optimizer
    optimizer = make_optimizer('cmaes', search.best_x.size, x0=search.best_x,
                               rng=np.random.default_rng(options.seed),
                               sigma=options.polish_sigma)
    optimizer.seed_best(search.best_x, search.best_cost)
    stall, generation_s = 0, (per or 0.0) * optimizer.population_size  # the first: predicted
    while (budget.left() > generation_s and stall < options.stall_generations
           and (options.max_generations is None
                or optimizer.generation < options.max_generations)
           and (options.max_evaluations is None
                or search.evaluations < options.max_evaluations)):
        t0 = budget.clock()
        xs = optimizer.ask()
        costs = search.full.cost(xs)
        optimizer.tell(xs, costs)
        search.generations = int(optimizer.generation)
        search.evaluations += xs.shape[0]
        i = int(np.argmin(np.where(np.isfinite(costs), costs, np.inf)))
        before = search.best_cost
        finite = costs[np.isfinite(costs)]
        search.record('cmaes', xs[i], float(costs[i]), generation=int(optimizer.generation),
                      mean_cost=float(np.mean(finite)) if finite.size else math.inf,
                      finite=int(finite.size), population=int(costs.size),
                      spread=float(optimizer.spread))
        stall = 0 if search.best_cost < before * (1.0 - 1e-6) else stall + 1
        generation_s = budget.clock() - t0


#: The stages of :func:`fit_global` in order: (phase, ``stage(search, budget, options, arm)``).
STAGES = (('linear', _closed_form), ('lm', _levenberg_marquardt), ('cmaes', _cmaes))


def fit_global(train: Sequence[Dataset], validation: Sequence[Dataset], setup: RolloutSetup,
               options: SearchOptions = SearchOptions(), *, budget: Budget,
               on_stage: Optional[Callable[[dict], None]] = None) -> GlobalFit:
    """
    Fit the global network within ``budget``: the stages of :data:`STAGES` (module docstring).

    ``setup``: the network (``setup.spec``, global) and what its rollouts use; ``options``:
    how the stages search.

    Each stage's result is scored by J on ``train`` and, when it lowers J, by the θ-NRMSE
    of the rollout of each ``validation`` segment from its first state; the result is,
    among those bests, the one with the lowest validation error (the training J when
    nothing is held out): how far to refine is decided on data the fit never saw. History
    entries: ``phase``, ``cost``, ``kept``, ``best_cost``, ``evaluations`` (and
    ``validation_nrmse`` when kept; ``interrupted`` for a stage the budget's end cut,
    ``skipped`` for one that its rollouts' measured time said would not fit).
    """
    if math.isfinite(budget.seconds):   # the stages end FINISH_SHARE before the budget
        budget = Budget(max(0.0, budget.left() - FINISH_SHARE * budget.seconds),
                        budget.clock)
    spec = setup.spec
    table = trig_table(spec)
    try:
        arm = linear_fit(train, spec.case, table, setup.kp, setup.kd, spec.coulomb_velocity,
                         deadline=budget.deadline(CLOSED_FORM_SHARE))
        cmap = coefficient_map(spec, setup.scales, table, arm.layout_, rng=options.seed)
    except (ValueError, np.linalg.LinAlgError) as error:
        samples = sum(seg.n_samples for seg in train)
        raise ValueError(f'the closed-form fit on the trigonometric basis failed on {samples} '
                         f'samples in {len(train)} segment(s): {error}') from error
    unit = variable_unit(arm.full_coefficients)
    search = _Search(train, validation, setup, cmap, unit, budget, on_stage)
    search.best_x = arm.full_coefficients / unit
    options = options._replace(shootings=tuple(options.shootings), lm_nfev=int(options.lm_nfev),
                               lm_fraction=float(options.lm_fraction),
                               polish_sigma=float(options.polish_sigma),
                               stall_generations=int(options.stall_generations),
                               seed=int(options.seed))
    with budget.interrupting():
        for k, (phase, stage) in enumerate(STAGES):
            if k and budget.spent():    # the closed form runs whatever is left
                break
            try:
                stage(search, budget, options, arm)
            except Interrupted:
                search.interrupted(phase)
                break
    return _chosen(search, arm, cmap, unit)


def _chosen(search: _Search, arm, cmap, unit) -> GlobalFit:
    """Return the best with the lowest validation error, or the closed form (module)."""
    finite = [k for k in search.kept if math.isfinite(k[0])]
    warning = ''
    if finite:
        chosen = min(finite, key=lambda k: (k[0], k[1]))
    elif search.kept:  # nothing held out (or every validation rollout diverged)
        chosen = min(search.kept, key=lambda k: k[1])
    else:
        first = search.history[0] if search.history else {}
        cost = float(first.get('cost', math.nan)) if first.get('phase') == 'linear' \
            else math.nan
        warning = ('every rollout diverged (no stage had a finite J): the closed form is '
                   'returned' if cost == math.inf else 'the budget ended before the closed '
                   'form was scored: it is returned unscored')
        chosen = (math.nan, cost, 'linear', arm.full_coefficients / unit)
    coef = chosen[3] * unit
    if cmap.layout.kp is not None:
        # case 3: the rollouts fix the arm and the servo only up to one common factor, which
        # the refinement may have moved; the model is given in units of mean Kp = 1
        coef = coef / float(np.mean(coef[cmap.layout.kp]))
    return GlobalFit(cmap.genome(coef), chosen[1], chosen[0], chosen[2], search.history,
                     search.evaluations, search.generations, arm, warning)

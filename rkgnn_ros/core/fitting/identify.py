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
Identification API: fit an RKGNN (:class:`..model.model.RKGNNModel`) on recorded samples.

- :class:`Evolution`: one generation per :meth:`Evolution.step`, on data that can be
  replaced between generations (what the identifier node runs in its worker thread).
- :func:`fit`: the offline loop (generations, evaluations or wall-time budget).
- :func:`fit_best`: our best pipeline inside a wall-time budget (by default the global
  network of :mod:`.global_search`: closed form, Levenberg-Marquardt and CMA-ES over the arm's
  coefficients, the stage chosen on held-out data; for RBF networks the equation error,
  Levenberg-Marquardt on rollout residuals, CMA-ES on the paper's cost).
- :func:`precompile`: compile every kernel the online identifier runs, before it spins.

Their options are records of :mod:`.options`.
"""

from dataclasses import dataclass, field, replace
import time
from typing import Callable, List, Optional

import numpy as np

from .fitness import FitnessProblem
from .optimizers import make_optimizer
from .options import FitOptions, Limits, RolloutChoices  # noqa: F401 (the API of identify)
from ..data import Dataset
from ..integration.rkg import choose_substeps
from ..model.model import RKGNNModel
from ..model.scales import Scales
from ..model.spec import NetworkSpec
from ..scoring import nrmse  # noqa: F401 (re-exported: the API of identify)

CASE_ALIASES = {'1': 'torque', 'torque': 'torque', '2': 'pd_gains', 'pd_gains': 'pd_gains',
                '3': 'unknown', 'unknown': 'unknown'}
CASE_NUMBERS = {'torque': 1, 'pd_gains': 2, 'unknown': 3}

# Largest RKG step by default: 4 substeps at 100 Hz. The paper's PD closed loop (point
# masses, friction) has eigenvalues down to about -545 1/s along the paper's reference and
# -576 1/s over all configurations, so h |λ| <= 1.44, inside RKG's stability limit of 2.785.
DEFAULT_MAX_STEP = 0.0025


def normalize_case(case) -> str:
    """Map 1/2/3 or the case names to 'torque' | 'pd_gains' | 'unknown'."""
    key = str(case).strip().lower()
    if key not in CASE_ALIASES:
        raise ValueError(f"case must be 1, 2, 3, 'torque', 'pd_gains' or 'unknown', got {case!r}")
    return CASE_ALIASES[key]


def default_substeps(dt, case='torque', kd=None, scales: Optional[Scales] = None) -> int:
    """
    Substeps per sample that keep rollouts stable at sampling interval ``dt``.

    The step is at most :data:`DEFAULT_MAX_STEP`; with known damping gains (case 2) the
    closed loop's fast eigenvalue is estimated as max(kd_i / M_ii) from the inertia scale.
    """
    stiffness = None
    if case == 'pd_gains' and kd is not None and scales is not None:
        stiffness = float(np.max(np.asarray(kd, dtype=float) / scales.inertia))
    return choose_substeps(dt, stiffness=stiffness, max_step=DEFAULT_MAX_STEP)


class Evolution:
    """
    An evolutionary identification that advances one generation per :meth:`step`.

    Parameters
    ----------
    spec : NetworkSpec
        Network structure.
    datasets : list of Dataset
        Training segments (replace them with :meth:`set_data` between generations).
    optimizer : str
        'cmaes', 'sep-cmaes' or 'paper'.
    settings : dict, optional
        Optimizer settings (see :mod:`rkgnn_ros.core.fitting.optimizers`).
    seed : int
        Seeds the optimizer's ``rng``.
    kp, kd : array_like, optional
        Known gains (case 2).
    **choices
        The fields of :class:`RolloutChoices`:
    substeps : int, optional
        RKG steps per sample (default from :func:`default_substeps`).
    shooting : int
        Multiple shooting interval in samples (0: one rollout per segment).
    torque_interpolation : str
        Case 1: 'hold' or 'linear'.
    scales : Scales, optional
        Fixed scales (default: measured on the first data; kept when the data change).
    x0 : array_like, optional
        Start genome (default ``spec.initial_genome()``).
    init : str
        'default' or 'least_squares' (equation-error warm start, ``inertia='penalty'``
        only; falls back to the default when its rollout diverges).

    """

    def __init__(self, spec: NetworkSpec, datasets, optimizer='cmaes', settings=None, seed=0,
                 kp=None, kd=None, **choices):
        choice = RolloutChoices(**choices)
        substeps, shooting, torque_interpolation = (choice.substeps, choice.shooting,
                                                    choice.torque_interpolation)
        scales, x0, init = choice.scales, choice.x0, choice.init
        if isinstance(datasets, Dataset):
            datasets = [datasets]
        self.spec = spec
        self.kp = kp
        self.kd = kd
        self.shooting = int(shooting)
        self.torque_interpolation = torque_interpolation
        self.scales = scales if scales is not None else Scales.from_datasets(
            datasets, spec.case, kp, kd)
        dt = datasets[0].dt
        self.substeps = int(substeps) if substeps else default_substeps(
            dt, spec.case, kd, self.scales)
        self.problem = self._problem(datasets)
        self.rng = np.random.default_rng(seed)
        start = np.asarray(x0, dtype=float) if x0 is not None else spec.initial_genome()
        if init == 'least_squares' and x0 is None:
            from .warmstart import least_squares_genome
            try:
                ls = least_squares_genome(spec, datasets, self.scales, start, kp=kp, kd=kd)
                if np.isfinite(self.problem.cost(ls[None])[0]):
                    start = ls
            except (ValueError, np.linalg.LinAlgError):
                pass
        elif init not in ('default', 'least_squares'):
            raise ValueError(f"init must be 'default' or 'least_squares', got {init!r}")
        self.optimizer = make_optimizer(optimizer, spec.genome_size, x0=start, rng=self.rng,
                                        **(settings or {}))
        self.wall_s = 0.0

    def _problem(self, datasets) -> FitnessProblem:
        return FitnessProblem(self.spec, datasets, scales=self.scales, substeps=self.substeps,
                              kp=self.kp, kd=self.kd, shooting=self.shooting,
                              torque_interpolation=self.torque_interpolation)

    def set_data(self, datasets) -> None:
        """Replace the training data (same scales); the best genome is re-scored on it."""
        self.problem = self._problem(datasets)
        best = self.optimizer.best_x
        if best is not None and np.isfinite(self.optimizer.best_cost):
            self.optimizer.rescore(float(self.problem.cost(best[None])[0]))

    def step(self) -> dict:
        """Run one generation; return its statistics (generation, best_cost, mean_cost, ...)."""
        t0 = time.perf_counter()
        genomes = self.optimizer.ask()
        costs = self.problem.cost(genomes)
        self.optimizer.tell(genomes, costs)
        self.wall_s += time.perf_counter() - t0
        finite = costs[np.isfinite(costs)]
        return {'generation': self.optimizer.generation,
                'best_cost': float(self.optimizer.best_cost),
                'mean_cost': float(np.mean(finite)) if finite.size else float('inf'),
                'spread': float(self.optimizer.spread),
                'evaluations': int(self.optimizer.evaluations),
                'finite': int(finite.size), 'population': int(costs.size)}

    def best_model(self, joint_names=None, info=None) -> RKGNNModel:
        """Return the best genome so far as a model."""
        meta = {'cost': float(self.optimizer.best_cost),
                'generation': int(self.optimizer.generation),
                'evaluations': int(self.optimizer.evaluations)}
        meta.update(info or {})
        return RKGNNModel(self.spec, self.scales, self.optimizer.best_x, joint_names,
                          self.kp, self.kd, dt=self.problem.dt, substeps=self.substeps,
                          torque_interpolation=self.torque_interpolation, info=meta)


@dataclass
class FitResult:
    """What :func:`fit` returns."""

    model: RKGNNModel
    history: List[dict] = field(default_factory=list)
    evaluations: int = 0
    generations: int = 0
    wall_s: float = 0.0
    final_cost: float = float('inf')


def fit(datasets, case, spec: Optional[NetworkSpec] = None, optimizer='cmaes', settings=None,
        callback: Optional[Callable[[dict], None]] = None, **options) -> FitResult:
    """
    Identify an RKGNN on recorded segments.

    Parameters
    ----------
    datasets : Dataset or list of Dataset
        Training data (uniformly sampled, same interval).
    case : int or str
        1/'torque', 2/'pd_gains' or 3/'unknown'.
    spec : NetworkSpec, optional
        Structure; ``NetworkSpec.recommended(n, case)`` by default.
    optimizer, settings, seed
        See :class:`Evolution`.
    kp, kd : array_like, shape (n,), optional
        Known PD gains (case 2).
    callback : callable, optional
        Called with each generation's statistics.
    **options
        The fields of :class:`Limits` (max_generations, max_evaluations, time_budget: stop
        at the first reached); the rest is passed to :class:`Evolution` (seed, kp, kd and
        :class:`RolloutChoices`'s substeps, shooting, torque_interpolation, init, x0).

    Returns
    -------
    FitResult

    """
    if isinstance(datasets, Dataset):
        datasets = [datasets]
    case = normalize_case(case)
    n = datasets[0].n_joints
    spec = spec if spec is not None else NetworkSpec.recommended(n, case)
    if spec.case != case:
        raise ValueError(f'spec.case {spec.case!r} differs from case {case!r}')
    limits = Limits(**{key: options.pop(key) for key in Limits._fields if key in options})
    max_generations, max_evaluations, time_budget = limits
    evo = Evolution(spec, datasets, optimizer, settings, **options)
    history = []
    t0 = time.perf_counter()
    while True:
        stats = evo.step()
        stats['wall_s'] = time.perf_counter() - t0
        history.append(stats)
        if callback is not None:
            callback(stats)
        if max_generations is not None and stats['generation'] >= max_generations:
            break
        if max_evaluations is not None and stats['evaluations'] >= max_evaluations:
            break
        if time_budget is not None and stats['wall_s'] >= time_budget:
            break
    model = evo.best_model(datasets[0].joint_names)
    return FitResult(model=model, history=history, evaluations=evo.optimizer.evaluations,
                     generations=evo.optimizer.generation, wall_s=time.perf_counter() - t0,
                     final_cost=float(evo.optimizer.best_cost))


def fit_best(datasets, case, options: Optional[FitOptions] = None, **changes) -> FitResult:
    """
    Identify with our best pipeline inside a wall-time budget.

    ``options`` (:class:`FitOptions`; default its defaults) with ``changes`` (option names:
    ``fit_best(data, 'torque', time_budget=10.0)``). ``time_budget`` (s, None: no limit) is
    wall time on ``clock``, counted from the call (:class:`.budget.Budget`): each stage
    gets what is left when it starts, the clock is checked between stages and inside them
    (every rollout of the training data stops at the budget's end), so the call returns
    within about a rollout of the budget whatever the machine's load. A budget of 0 gives
    the first stage's result at once.

    By default the network is global (:func:`.global_fit.global_spec` on ``basis``, the
    trigonometric basis of a planar arm: M, V, G, F right on the whole joint range, not only
    along the data), fitted by :func:`.global_search.fit_global`: the closed-form fit of the
    arm's coefficients, Levenberg-Marquardt on the rollouts over those coefficients (for
    ``lm_fraction`` of the time left after the closed form), CMA-ES over them (spread
    ``polish_sigma``, 0.01 of each coefficient by default) for the rest, ``max_generations``
    or ``max_evaluations``, or until it stalls. The newest ``validation_fraction`` of the
    data is held out, and of the stages' results the one with the lowest θ-NRMSE there is
    returned (``info['validation_nrmse']``, ``info['selected']``). When no stage has a
    finite cost J (every rollout diverged, or the budget ended first), the closed form is
    returned and ``info['warning']`` says why; a closed form that cannot be fitted raises a
    ValueError naming the cause. Each history entry has ``phase`` ('linear', 'lm',
    'cmaes'), ``cost``, ``kept``, ``best_cost``, ``evaluations``, ``wall_s`` and, when kept,
    ``validation_nrmse`` (``interrupted``: the budget's end cut that stage).

    With ``basis='rbf'``, ``theta_units`` or a ``spec`` that is not global, the paper-shaped
    RBF network is fitted by the earlier pipeline, on all the data:

    1. Equation error: the genome fitted to the inverse dynamics M θ̈ + V + G + F = τ at
       every sample (no rollout: fast, and it places gravity and inertia, which short
       shooting windows leave weakly constrained), for at most ``equation_nfev`` residual
       evaluations and ``equation_fraction`` of the budget
       (:func:`rkgnn_ros.core.fitting.refine.refine_equation_error`; skipped if ``equation_nfev``
       is 0);
    2. Levenberg-Marquardt on the rollout residuals, over a continuation of multiple-shooting
       windows (``shootings``), for ``lm_fraction`` of the time left after stage 1
       (:func:`rkgnn_ros.core.fitting.refine.refine_lm`);
    3. CMA-ES around the best genome on the paper's cost J of the full rollout for the rest
       of the budget (it tolerates the diverged candidates that stop a gradient method), or
       ``max_generations`` generations if that comes first.

    The result is the best genome by J so far: a stage's genome replaces it only if its J is
    lower, so every stage improves the result or hands it on unchanged (CMA-ES restarts
    around it, evaluates it in its first generation and is told its cost).

    The structure defaults to :meth:`NetworkSpec.recommended` with ``theta_units`` RBF units
    over θ (the equation-error stage places more units than a search from scratch can; by
    default 5 in cases 1 and 2, 8 in case 3). History: one entry per stage result and per
    CMA-ES generation, each with ``phase`` ('start', 'equation', 'lm' per shooting window,
    'cmaes'), ``cost`` (J of the stage's genome; CMA-ES: the generation's lowest), ``kept``
    (it became the result), ``best_cost`` (the pipeline's best J so far, never increasing),
    ``evaluations`` (rollouts so far; the equation-error stage needs none) and ``wall_s``;
    CMA-ES entries also carry :meth:`Evolution.step`'s statistics.

    With ``structure`` (the :class:`~rkgnn_ros.core.rigid.structure.RigidStructure` of a
    robot description) the arm's rigid body is fitted in closed form instead
    (:func:`.rigid_online.fit_rigid`, a second or less, whatever the budget):
    ``model`` is a :class:`~.rigid_model.RigidModel`, ``final_cost`` its held-out error.
    With ``learn_chain`` and no ``structure``, case 1 or 3 on 3 to 7 joints: the arm's
    chain is learned from the data first (:func:`.chain_online.learn_chain`, minutes, outside
    the budget) and, when it predicts the held-out torque (case 3: the closed loop's
    equation), its rigid body is fitted so (history's first entry: phase 'chain').
    """
    from . import global_fit
    opts = (FitOptions() if options is None else options).updated(**changes)
    structure = opts.structure
    history_first: List[dict] = []
    if (structure is None and opts.learn_chain
            and normalize_case(case) in ('torque', 'unknown')):
        from .chain_online import chain_case, learn_chain as learned_chain
        start = opts.clock()
        lines: List[str] = []
        structure = learned_chain([datasets] if isinstance(datasets, Dataset) else datasets,
                                  validation_fraction=opts.validation_fraction,
                                  log=lambda level, text: lines.append(text),
                                  case=chain_case(normalize_case(case)))
        history_first.append({'phase': 'chain', 'accepted': structure is not None,
                              'wall_s': opts.clock() - start, 'log': lines})
    if structure is not None:
        from .rigid_online import fit_rigid
        start = opts.clock()
        model = fit_rigid(datasets, normalize_case(case), structure, opts.kp, opts.kd,
                          opts.validation_fraction)
        return FitResult(model, history_first + [{'phase': 'rigid',
                                                  'cost': model.info['held_out_error']}],
                         wall_s=opts.clock() - start, final_cost=model.info['held_out_error'])
    from .budget import Budget
    budget = Budget(float('inf') if opts.time_budget is None else opts.time_budget, opts.clock)
    # default θ units per case: chosen on held-out data of the paper's arm (README)
    default_units = {'torque': 5, 'pd_gains': 5, 'unknown': 8}
    if isinstance(datasets, Dataset):
        datasets = [datasets]
    datasets = list(datasets)
    if not datasets:
        raise ValueError('fit_best: no data (an empty list of segments)')
    case = normalize_case(case)
    n = datasets[0].n_joints
    spec = opts.spec
    if spec is None and opts.theta_units is None and opts.basis != 'rbf':
        spec = global_fit.global_spec(n, case, opts.basis)
    if spec is not None and global_fit.is_global(spec):
        try:
            return _fit_global_best(datasets, spec, budget, opts)
        except ValueError as error:
            raise ValueError(f'fit_best: {error}') from error
    if spec is None:
        spec = NetworkSpec.recommended(n, case)
        units = default_units[case] if opts.theta_units is None else int(opts.theta_units)
        spec = replace(spec, theta_units=units)
    with budget.interrupting():
        return _fit_rbf_best(datasets, spec, budget, opts)


def _fit_rbf_best(datasets, spec, budget, opts: FitOptions) -> FitResult:
    """:func:`fit_best` for an RBF network (inside ``budget.interrupting()``)."""
    from .budget import Budget
    from .fitness import Interrupted
    from .refine import refine_equation_error, refine_lm
    kp, kd, callback = opts.kp, opts.kd, opts.callback
    polish_sigma = 0.05 if opts.polish_sigma is None else opts.polish_sigma
    equation_nfev, max_generations = opts.equation_nfev, opts.max_generations
    evo = Evolution(spec, datasets, 'cmaes', {'sigma': polish_sigma}, opts.seed, kp, kd,
                    **opts.evolution)

    def problem_for(shooting):
        problem = FitnessProblem(spec, datasets, scales=evo.scales, substeps=evo.substeps,
                                 kp=kp, kd=kd, shooting=shooting,
                                 torque_interpolation=evo.torque_interpolation)
        problem.seconds_per_candidate = evo.problem.seconds_per_candidate
        return problem

    history: List[dict] = []

    def on_stage(entry):
        entry = dict(entry, wall_s=budget.elapsed())
        history.append(entry)
        if callback is not None:
            callback(entry)

    evaluations = 0

    def full_cost(genome):
        nonlocal evaluations
        evaluations += 1
        return float(evo.problem.cost(genome[None])[0])

    # the pipeline's result: the best genome by J so far; a stage replaces it only if better
    best = {'genome': evo.optimizer.x0.copy(), 'cost': float('inf')}

    def stage_result(phase, genome, cost, **extra):
        kept = bool(cost < best['cost'])
        if kept:
            best.update(genome=np.array(genome, dtype=float), cost=cost)
        on_stage(dict(extra, phase=phase, cost=cost, kept=kept, best_cost=best['cost'],
                      evaluations=evaluations))

    try:
        best['cost'] = full_cost(best['genome'])
        on_stage({'phase': 'start', 'cost': best['cost'], 'kept': True,
                  'best_cost': best['cost'], 'evaluations': evaluations})
        if equation_nfev and not budget.spent():
            eq_genome, eq_cost = refine_equation_error(
                spec, datasets, evo.scales, best['genome'], kp, kd,
                max_nfev=int(equation_nfev), deadline=budget.deadline(opts.equation_fraction))
            stage_result('equation', eq_genome, full_cost(eq_genome), equation_cost=eq_cost)
        # LM continues from its own stage results (the continuation over shooting windows)
        # and starts from the best so far; the pipeline keeps a stage's genome only if J
        # improved
        genome = best['genome']
        lm = Budget(opts.lm_fraction * budget.left(), budget.clock)
        for shooting in opts.shootings:
            if lm.spent():
                break
            with lm.interrupting():
                genome, lm_hist = refine_lm(problem_for, genome, (shooting,), opts.lm_nfev,
                                            deadline=lm.deadline())
            evaluations += lm_hist[-1]['evaluations'] if lm_hist else 0
            stage_result('lm', genome, full_cost(genome), shooting=int(shooting),
                         residual_cost=lm_hist[-1]['cost'] if lm_hist else float('nan'))
        # CMA-ES around the best, which it evaluates in its first generation and reports as
        # its best until it finds a better one
        evo.optimizer.restart(best['genome'], polish_sigma, cost=best['cost'])
        before, generation_s = evaluations, 0.0
        while (budget.left() > generation_s
               and (max_generations is None or evo.optimizer.generation < max_generations)):
            t0 = budget.clock()
            stats = evo.step()
            generation_s = budget.clock() - t0
            evaluations = before + stats['evaluations']
            kept = stats['best_cost'] < best['cost']
            if kept:
                best.update(genome=evo.optimizer.best_x.copy(), cost=float(stats['best_cost']))
            on_stage(dict(stats, phase='cmaes', cost=evo.optimizer.history[-1]['min_cost'],
                          kept=kept, evaluations=evaluations))
    except Interrupted:
        on_stage({'phase': 'budget', 'cost': float('nan'), 'kept': False, 'interrupted': True,
                  'best_cost': best['cost'], 'evaluations': evaluations})
    info = {'cost': best['cost'], 'pipeline': 'equation+lm+cmaes' if equation_nfev
            else 'lm+cmaes'}
    if not np.isfinite(best['cost']):
        info['warning'] = ('no stage had a finite cost J (every rollout diverged, or the '
                           'budget ended first): the start genome is returned')
    model = RKGNNModel(spec, evo.scales, best['genome'], datasets[0].joint_names, kp, kd,
                       dt=evo.problem.dt, substeps=evo.substeps,
                       torque_interpolation=evo.torque_interpolation, info=info)
    return FitResult(model=model, history=history, evaluations=evaluations,
                     generations=evo.optimizer.generation,
                     wall_s=budget.elapsed(), final_cost=best['cost'])


def _fit_global_best(datasets, spec, budget, opts: FitOptions) -> FitResult:
    """:func:`fit_best` for a global network (:func:`.global_search.fit_global`)."""
    from .global_search import fit_global, RolloutSetup, SearchOptions
    from .validation import split_validation
    kp, kd, callback = opts.kp, opts.kd, opts.callback
    torque_interpolation = opts.evolution.get('torque_interpolation', 'linear')
    train, validation, _ = split_validation(datasets, opts.validation_fraction)
    if not train:
        train, validation = list(datasets), []
    scales = Scales.from_datasets(datasets, spec.case, kp, kd)
    substeps = default_substeps(datasets[0].dt, spec.case, kd, scales)

    def on_stage(entry):
        entry['wall_s'] = budget.elapsed()
        if callback is not None:
            callback(entry)

    setup = RolloutSetup(spec, scales, substeps, kp, kd, torque_interpolation)
    search = SearchOptions(
        shootings=opts.shootings, lm_nfev=opts.lm_nfev, lm_fraction=opts.lm_fraction,
        polish_sigma=0.01 if opts.polish_sigma is None else opts.polish_sigma,
        max_generations=opts.max_generations, max_evaluations=opts.max_evaluations,
        seed=opts.seed)
    result = fit_global(train, validation, setup, search, budget=budget, on_stage=on_stage)
    info = {'cost': result.cost, 'pipeline': 'linear+lm+cmaes', 'selected': result.phase,
            'validation_nrmse': result.validation_nrmse,
            'validation_s': float(sum(seg.duration for seg in validation))}
    if result.warning:
        info['warning'] = result.warning
    model = RKGNNModel(spec, scales, result.genome, datasets[0].joint_names, kp, kd,
                       dt=datasets[0].dt, substeps=substeps,
                       torque_interpolation=torque_interpolation, info=info)
    return FitResult(model=model, history=result.history, evaluations=result.evaluations,
                     generations=result.generations, wall_s=budget.elapsed(),
                     final_cost=result.cost)


def precompile(n_joints=3) -> float:
    """
    Compile (or load from numba's disk cache) every kernel the online identifier runs.

    numba compiles a kernel at its first call and holds the GIL while it does, for seconds.
    A node calls this before it starts spinning, so no compilation ever happens in its
    worker thread while callbacks and services wait. Tiny problems of every case and both
    inertia and velocity modes exercise the same type signatures as real data. Returns the
    seconds it took.
    """
    from .global_fit import global_spec
    from .refine import refine_equation_error
    from .trig_loop import precompile_trig_loop
    t0 = time.perf_counter()
    n = int(n_joints)
    t = np.arange(12) * 0.01
    theta = 0.1 * np.sin(t[:, None] + np.arange(n))
    theta_dot = 0.1 * np.cos(t[:, None] + np.arange(n))
    data = Dataset(t, theta, theta_dot, tau=np.zeros((t.size, n)), theta_d=theta,
                   theta_d_dot=theta_dot)
    gains = np.ones(n)
    for case in ('torque', 'pd_gains', 'unknown'):
        for spec in (NetworkSpec.recommended(n, case), NetworkSpec.paper(n, case),
                     global_spec(n, case)):
            scales = Scales.from_datasets([data], case, gains, gains)
            problem = FitnessProblem(spec, data, scales=scales, substeps=2, kp=gains,
                                     kd=gains)
            genomes = np.repeat(spec.initial_genome()[None], 2, axis=0)
            problem.cost(genomes)
            problem.rollouts(genomes)
            model = RKGNNModel(spec, scales, genomes[0], kp=gains, kd=gains, substeps=2)
            model.predict(data)
            if spec.inertia == 'cholesky':
                refine_equation_error(spec, [data], scales, genomes[0], gains, gains,
                                      max_nfev=1)
    precompile_trig_loop(n)
    return time.perf_counter() - t0

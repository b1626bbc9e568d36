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
PD gain tuning with the paper's evolutionary algorithm (section 4, eqs. 9 and 10).

The paper tuned the diagonal PD servo of eq. (9), τ = Kp (θd - θ) + Kd (θ̇d - θ̇), with
its EA (100 % mutation, 20 % crossover, tournament 6, 200 generations, 60 individuals)
minimising the tracking error of eq. (10) (:mod:`.tracking`), and found
Kp = diag(32.84, 42.05, 42.31), Kd = diag(42.44, 0.19, 4.86).

Genome. :func:`tune_pd_gains` searches a normalised genome z in R^(2n) that is mapped into
the bounds by reflection (:func:`genome_to_gains`): u = z on [0, 1], mirrored at 0 and 1
(a triangle wave of period 2), gain = lo + (hi - lo) u. Unlike clipping it has no flat
plateaus beyond the bounds (a mutation always moves the gain) and unlike a logistic map
it does not flatten near the bounds (a step of the genome is the same fraction of the
range everywhere), so a mutation spread means the same everywhere and optima on a bound
are reachable.
"""

from dataclasses import dataclass
import numbers
import time
from typing import Callable, NamedTuple, Optional, Union

import numpy as np

from .plant import PDController, PlanarArm
from .tracking import bounds_arrays, DEFAULT_BOUNDS, TrackingProblem, tuning_step
from .trajectories import Reference
from ..fitting.optimizers import PaperEA

__all__ = ['EA_SETTINGS', 'HISTORY_COLUMNS', 'TuningResult', 'genome_to_gains', 'paper_gains',
           'tune_pd_gains']

#: Settings of :class:`rkgnn_ros.core.fitting.optimizers.PaperEA` used by :func:`tune_pd_gains`,
#: besides ``population_size``. The paper's operators (tournament 6, 20 % crossover, 100 %
#: mutation); the genome is in units of the gain ranges, so the mutation spread starts at
#: 20 % of each range and shrinks to a floor of 0.5 % (Kp 0.5, Kd 0.25 with the default
#: bounds) by generation 150 of 200 (0.2 * 0.9757**150 = 0.005). The initial population is
#: the centre of the box plus 0.5 N(0, I), folded into the box by the reflection.
EA_SETTINGS = {'tournament_size': 6, 'crossover_rate': 0.2, 'mutation_rate': 1.0,
               'sigma': 0.2, 'sigma_min': 0.005, 'sigma_decay': 0.9757, 'n_elite': 1,
               'init_scale': 0.5}

#: Columns of :attr:`TuningResult.history`.
HISTORY_COLUMNS = ('best_cost', 'mean_cost')


# -- helpers ------------------------------------------------------------------------------


def genome_to_gains(genome, bounds=DEFAULT_BOUNDS, n_joints: Optional[int] = None):
    """
    Map normalised genomes into the gain bounds by reflection.

    u = z on [0, 1], mirrored at 0 and 1 (period 2); gain = lo + (hi - lo) u.

    Parameters
    ----------
    genome : array_like, shape (..., 2n)
        Normalised genomes [z_Kp, z_Kd].
    bounds : ((kp_lo, kp_hi), (kd_lo, kd_hi))
        Scalars or (n,) arrays.
    n_joints : int, optional
        n; default half the genome length.

    Returns
    -------
    ndarray, shape (..., 2n)
        Gain rows [Kp, Kd], inside the bounds.

    """
    z = np.asarray(genome, dtype=float)
    n = z.shape[-1] // 2 if n_joints is None else int(n_joints)
    if z.ndim == 0 or z.shape[-1] != 2 * n:
        raise ValueError(f'genome must have shape (..., {2 * n}), got {z.shape}')
    lo, hi = bounds_arrays(bounds, n)
    u = 1.0 - np.abs(np.mod(z, 2.0) - 1.0)
    return lo + (hi - lo) * u


def paper_gains() -> np.ndarray:
    """Return the paper's gains as one row [Kp, Kd], shape (6,)."""
    c = PDController.paper()
    return np.concatenate([np.diag(c.kp), np.diag(c.kd)])


# -- the tuning ---------------------------------------------------------------------------


@dataclass(frozen=True)
class TuningResult:
    """
    Outcome of :func:`tune_pd_gains`.

    Attributes
    ----------
    kp, kd : ndarray, shape (n,)
        The best diagonal gains found.
    cost : float
        Their tracking error, eq. (10).
    paper_cost : float or None
        The paper's gains' error on the same reference and step (None unless n = 3).
    history : ndarray, shape (G, 2)
        Per generation (columns :data:`HISTORY_COLUMNS`): the best cost so far and the
        mean of the generation's finite costs (NaN if none).
    evaluations : int
        Candidates evaluated.
    wall_s, cpu_s : float
        Wall-clock and process CPU time of the whole call (s), setup included.
    step : float
        The integration step h (s).
    genome : ndarray, shape (2n,)
        The best normalised genome (``genome_to_gains(genome, bounds)`` gives [kp, kd]).

    """

    kp: np.ndarray
    kd: np.ndarray
    cost: float
    paper_cost: Optional[float]
    history: np.ndarray
    evaluations: int
    wall_s: float
    cpu_s: float
    step: float
    genome: np.ndarray


def _check_count(name, value, lo) -> int:
    if (isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral)
            or value < lo):
        raise ValueError(f'{name} must be an integer >= {lo}, got {value!r}')
    return int(value)


class TuningOptions(NamedTuple):
    """The rate, step and evolution options of :func:`tune_pd_gains` (see there)."""

    callback: Optional[Callable[[dict], Optional[bool]]] = None
    rate: float = 100.0
    step: Optional[float] = None
    ea_settings: Optional[dict] = None
    problem: object = None


def tune_pd_gains(arm: PlanarArm, reference: Reference, duration: float = 10.0,
                  population_size: int = 60, generations: int = 200,
                  seed: Union[int, np.random.Generator, None] = 0, bounds=DEFAULT_BOUNDS, **options
                  ) -> TuningResult:
    """
    Tune diagonal PD gains with the paper's EA, minimising the tracking error of eq. (10).

    :class:`rkgnn_ros.core.fitting.optimizers.PaperEA` (ask/tell, :data:`EA_SETTINGS`) on the
    normalised genome of :func:`genome_to_gains`; every generation is one call of
    :meth:`TrackingProblem.cost`. The defaults are the paper's: 60 individuals, 200
    generations. On the paper's arm, ``paper_reference(3)`` over 10 s at 100 Hz, this is
    12,000 closed-loop simulations of 21,000 steps each.

    Eq. (10) has no torque term and the PD no torque limit, so on that arm and reference
    the error falls as the gains grow and the EA ends near the upper corner of the bounds:
    the bounds, i.e. what the actuators allow, decide the gains (figures, and the same for
    a digital servo, in ``bench/results/pd_tuning.json``).

    Parameters
    ----------
    arm : PlanarArm
        The plant.
    reference : Reference
        Desired trajectory.
    duration : float
        Simulated time per candidate (s).
    population_size : int
        Individuals per generation (>= 2).
    generations : int
        Generations (>= 1).
    seed : int, numpy.random.Generator or None
        Randomness of the EA (the optimizer keeps it as its ``rng``).
    bounds : ((kp_lo, kp_hi), (kd_lo, kd_hi))
        Gain bounds, scalars or (n,) arrays; they also set the step (:func:`tuning_step`).
    callback : callable, optional
        Called after every generation with the optimizer's history entry (``generation``,
        ``best_cost``, ``min_cost``, ``mean_cost``, ...) plus ``kp`` and ``kd`` of the best
        so far; returning True stops the tuning.
    rate : float
        Sampling rate of the error (Hz).
    step : float, optional
        Largest integration step; default :func:`tuning_step` for ``bounds``.
    ea_settings : dict, optional
        Overrides of :data:`EA_SETTINGS`.
    problem : object, optional
        The cost to minimise instead of the continuous PD's :class:`TrackingProblem` (which
        ``rate`` and ``step`` then do not build): anything with ``cost(gains) -> (P,)`` and
        a step ``h``, e.g. :class:`rkgnn_ros.core.sim.tuning_study.SampledTrackingProblem`.

    Returns
    -------
    TuningResult

    """
    callback, rate, step, ea_settings, problem = TuningOptions(**options)
    wall0, cpu0 = time.perf_counter(), time.process_time()
    population_size = _check_count('population_size', population_size, 2)
    generations = _check_count('generations', generations, 1)
    n = arm.n_joints
    bounds_arrays(bounds, n)                            # validate before the setup work
    if problem is None:
        step = tuning_step(arm, reference, duration, bounds) if step is None else step
        problem = TrackingProblem(arm, reference, duration, rate, step)
    settings = {**EA_SETTINGS, **(ea_settings or {}), 'population_size': population_size}
    ea = PaperEA(2 * n, x0=np.full(2 * n, 0.5), rng=seed, history_maxlen=None, **settings)
    for _ in range(generations):
        genomes = ea.ask()                                               # (P, 2n)
        ea.tell(genomes, problem.cost(genome_to_gains(genomes, bounds, n)))
        if callback is not None:
            best = genome_to_gains(ea.best_x, bounds, n)
            if callback({**ea.history[-1], 'kp': best[:n], 'kd': best[n:]}):
                break
    best = genome_to_gains(ea.best_x, bounds, n)
    paper_cost = float(problem.cost(paper_gains()[None])[0]) if n == 3 else None
    history = np.array([[e['best_cost'], e['mean_cost']] for e in ea.history])
    return TuningResult(kp=best[:n], kd=best[n:], cost=float(ea.best_cost),
                        paper_cost=paper_cost, history=history, evaluations=ea.evaluations,
                        wall_s=time.perf_counter() - wall0, cpu_s=time.process_time() - cpu0,
                        step=problem.h, genome=ea.best_x.copy())

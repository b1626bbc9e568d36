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
Where an online search starts, and how it takes new settings between two generations.

The equation-error fit places the start (and places it again when the window has grown),
case 3 first tries the servo's gains (:mod:`.case_three`), and a changed algorithm or
setting is handed to the running search. Used by :class:`.online.OnlineIdentification`.
"""

import math
import time
from typing import Optional

import numpy as np

from . import case_three, global_fit
from .identify import Evolution
from .online_records import OnlineSettings
from .optimizers import make_optimizer
from .policy import REWARM_GROWTH, REWARM_PERIOD_S, WARM_START_SIGMA
from .refine import refine_equation_error

__all__ = ['warm_start', 'rewarm', 'restart_around', 'hand_over_settings', 'RewarmSchedule']


class RewarmSchedule:
    """
    When :func:`rewarm` is due: the window grew :data:`REWARM_GROWTH` x since the last fit.

    An RBF case-3 search's fit also runs every :data:`REWARM_PERIOD_S` (its arm fitted
    again under its own gains on the sliding window: on the UR5 the 2 s error at 60 s went
    from 0.24-0.36 to 0.16-0.28 of following the reference's). Not the others': at 1 kHz
    a case-1 search's fit of the full window took its whole 5 s budget, the node's
    prediction latency p99 rose from 16 ms to 104 ms, and none of them was seen to gain.
    """

    def __init__(self):
        self.seconds, self.time = math.inf, -math.inf  # data (s) and clock at the last fit

    def placed(self, seconds: float, now: float) -> None:
        """Record a fit on ``seconds`` of data at clock ``now``."""
        self.seconds, self.time = seconds, now

    def due(self, spec, seconds: float, now: float) -> bool:
        """Return whether the fit of a search of ``spec`` runs again on ``seconds`` at ``now``."""
        if seconds >= REWARM_GROWTH * self.seconds:
            return True
        slides = spec.case == 'unknown' and not global_fit.is_global(spec)
        return slides and now - self.time >= REWARM_PERIOD_S


def _equation_error_fit(evo: Evolution, train, kp, kd, budget_s: float, nfev: int):
    """
    Return ``(genome, rollout cost, seconds)`` of the equation-error fit from the best.

    A fit the data cannot carry (too few samples, a singular system) gives the best genome
    with cost inf.
    """
    t0 = time.perf_counter()  # a computation budget: real time, whatever the clock
    try:
        genome, _ = refine_equation_error(evo.spec, train, evo.scales, evo.optimizer.best_x,
                                          kp, kd, max_nfev=nfev, deadline=t0 + budget_s)
    except (ValueError, np.linalg.LinAlgError):
        return evo.optimizer.best_x, math.inf, time.perf_counter() - t0
    cost = float(evo.problem.cost(genome[None])[0])
    return genome, cost, time.perf_counter() - t0


def _closed_form(evo: Evolution, train):
    """
    Return ``(genome, cost, seconds)`` of a global network's start.

    The arm's coefficients fitted on the trigonometric basis (case 3: with its PD servo),
    mapped into the genome (:func:`.global_fit.closed_form_genome`): the same model, no
    search needed; the search's CMA-ES refines it generation by generation. A fit the data
    cannot carry (too few samples, a singular system) gives the best genome with cost inf.
    """
    t0 = time.perf_counter()
    try:
        genome = global_fit.closed_form_genome(evo.spec, list(train), evo.scales, evo.kp,
                                               evo.kd)
    except (ValueError, np.linalg.LinAlgError):
        return evo.optimizer.best_x, math.inf, time.perf_counter() - t0
    return genome, float(evo.problem.cost(genome[None])[0]), time.perf_counter() - t0


def warm_start(evo: Evolution, train, kp, kd, budget_s: float, nfev: int) -> Optional[str]:
    """
    Place the start genome by the equation-error fit (the offline pipeline's first stage).

    Fitting M θ̈ + V + G + F = τ on the buffered samples needs no rollout: within its
    budget it puts gravity, inertia and friction where the data put them, which a search
    from the default genome takes many generations to find. Kept only when its rollout on
    the training data does not diverge (the optimizer then restarts around it); returns
    what the search starts from, None if not kept. A global network starts from its
    closed-form fit instead (:func:`.global_fit.linear_fit`, mapped into the genome).
    """
    if global_fit.is_global(evo.spec):
        genome, cost, seconds = _closed_form(evo, train)
        what = 'the closed-form fit on the trigonometric basis'
    else:
        genome, cost, seconds = _equation_error_fit(evo, train, kp, kd, budget_s, nfev)
        what = 'the equation-error fit'
    if not math.isfinite(cost):
        return None
    restart_around(evo.optimizer, genome, cost)
    return f'{what} ({seconds:.1f} s, J {cost:.4g})'


def rewarm(evo: Evolution, train, seconds: float, budget_s: float, nfev: int) -> str:
    """
    Fit again from the best genome on the grown window; return the line that says so.

    A global network fits its closed form again; an RBF case-3 search first tries the start
    from the linearly identified gains (:mod:`.case_three`: they may be determined by now),
    else the arm fitted again under the search's own linear PD gains (a case-2 fit: on a
    spatial arm, whose closed loop the trigonometric fit does not hold, the whole network's
    equation-error fit rarely improved the best once the search had begun), then the
    equation-error fit; a genome replaces the best (the optimizer restarts around it) only
    if its cost is lower.
    """
    before = float(evo.optimizer.best_cost)
    if global_fit.is_global(evo.spec):
        genome, cost, took = _closed_form(evo, train)
        what = 'closed-form fit'
    else:
        placed = case_three.start_genome(evo, train, budget_s, nfev)
        gains = case_three.search_gains(evo) if placed is None else None
        if gains is not None:  # the arm fitted anew under the search's own gains
            placed = case_three.start_genome(evo, train, budget_s, nfev, gains)
        if placed is not None and not placed.cost >= before:
            restart_around(evo.optimizer, placed.genome, placed.cost)
            return (f'{placed.origin} on {seconds:.1f} s of data: better than the best '
                    f'({before:.4g}), restarting around it')
        genome, cost, took = _equation_error_fit(evo, train, evo.kp, evo.kd, budget_s, nfev)
        what = 'equation-error fit'
    kept = math.isfinite(cost) and not cost >= before
    if kept:
        restart_around(evo.optimizer, genome, cost)
    return (f'{what} again on {seconds:.1f} s of data ({took:.1f} s): J {cost:.4g} vs the '
            f'best {before:.4g}, ' + ('restarting around it' if kept else 'kept the best'))


def restart_around(optimizer, genome, cost: float) -> None:
    """Make ``genome`` the best and restart the optimizer around it."""
    optimizer.seed_best(genome, cost)
    optimizer.restart(genome, max(WARM_START_SIGMA, optimizer.settings.get('sigma_min', 0.0)))


def hand_over_settings(evo: Evolution, running: str, settings: OnlineSettings,
                       upcoming: int) -> Optional[str]:
    """
    Give the search the optimizer the settings ask for (between two generations).

    A new algorithm replaces the optimizer, warm-started from the best genome; changed
    settings go to the running one. Returns the line saying so (None: no change).
    """
    algorithm, wanted = settings.optimizer, dict(settings.optimizer_settings)
    optimizer = evo.optimizer
    if algorithm != running:
        new = make_optimizer(algorithm, optimizer.dim, x0=optimizer.best_x, rng=evo.rng,
                             **wanted)
        if math.isfinite(optimizer.best_cost):
            new.rescore(optimizer.best_cost)
        evo.optimizer = new
        return (f'generation {upcoming} runs es.algorithm {algorithm!r} (population '
                f'{new.population_size}), warm-started from the best genome')
    current = optimizer.settings
    diff = {k: v for k, v in wanted.items() if current.get(k) != v}
    if not diff:
        return None
    optimizer.update_settings(**diff)
    shown = ', '.join(f'es.{k}={v}' for k, v in sorted(diff.items()))
    return (f'generation {upcoming} takes the new settings {shown} '
            f'(population {optimizer.population_size})')

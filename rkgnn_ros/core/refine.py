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
Levenberg-Marquardt refinement of a genome on the rollout (output-error) residuals.

The residuals are the weighted differences between the RKG rollout and every measured
state, ``(x̂_k - x_k) · w`` with w = [1/spread(θ), 0.3/rms(θ̇)]. Their Jacobian comes from
forward differences: the N + 1 perturbed genomes form one population that the compiled
kernel rolls out in parallel, so one Jacobian costs one generation of N + 1 individuals.

Long rollouts of a poor model diverge, which makes the residuals discontinuous. The
refinement therefore starts on short multiple-shooting windows (restarts from the measured
state every ``shooting`` samples; nearly linear residuals) and continues on longer ones
(continuation), ending with the full rollout. A diverged prediction contributes a fixed
residual, so a trust-region step into divergence is rejected.
"""

import time
from typing import List, Optional, Sequence

import numpy as np
from scipy.optimize import least_squares

from .fitness import FitnessProblem

DIVERGED_RESIDUAL = 10.0


class _Deadline(Exception):
    pass


def residual_weights(problem: FitnessProblem) -> np.ndarray:
    """Weights of the state residuals, shape (2n,): 1/spread(θ) and 0.3/rms(θ̇)."""
    s = problem.scales
    return np.concatenate([1.0 / s.theta_spread, 0.3 / s.velocity])


def refine_lm(problem_for, genome, shootings: Sequence[int] = (20, 0), max_nfev=30,
              deadline: Optional[float] = None, callback=None):
    """
    Refine ``genome`` by trust-region least squares over a continuation of shooting windows.

    Parameters
    ----------
    problem_for : callable
        ``problem_for(shooting) -> FitnessProblem`` (same data, scales and settings).
    genome : ndarray, shape (N,)
        Start genome.
    shootings : sequence of int
        Multiple-shooting intervals, one stage each (0 = the full rollout).
    max_nfev : int
        Residual evaluations per stage (scipy's ``max_nfev``).
    deadline : float, optional
        ``time.perf_counter()`` value at which to stop (the best genome so far is kept).
    callback : callable, optional
        Called with a dict after every stage.

    Returns
    -------
    genome : ndarray, shape (N,)
    history : list of dict
        One entry per stage: shooting, cost (mean squared weighted residual), evaluations.

    """
    g = np.array(genome, dtype=float)
    history: List[dict] = []
    evaluations = 0
    for shooting in shootings:
        problem = problem_for(int(shooting))
        w = residual_weights(problem)
        x_meas = problem.x_meas
        best = {'cost': np.inf, 'g': g.copy()}

        def residuals(population):
            pred = problem.rollouts(population)
            r = ((pred - x_meas[None]) * w).reshape(population.shape[0], -1)
            return np.nan_to_num(r, nan=DIVERGED_RESIDUAL, posinf=DIVERGED_RESIDUAL,
                                 neginf=-DIVERGED_RESIDUAL)

        def fun(x):
            nonlocal evaluations
            if deadline is not None and time.perf_counter() > deadline:
                raise _Deadline()
            r = residuals(x[None])[0]
            evaluations += 1
            cost = float(np.mean(np.square(r)))
            if cost < best['cost']:
                best['cost'] = cost
                best['g'] = x.copy()
            return r

        def jac(x):
            nonlocal evaluations
            if deadline is not None and time.perf_counter() > deadline:
                raise _Deadline()
            step = 1e-6 * np.maximum(1.0, np.abs(x))
            pop = np.vstack([x[None], x[None] + np.diag(step)])
            r = residuals(pop)
            evaluations += pop.shape[0]
            return ((r[1:] - r[0]) / step[:, None]).T

        try:
            least_squares(fun, g, jac=jac, method='trf', x_scale='jac', max_nfev=max_nfev)
        except _Deadline:
            pass
        g = best['g']
        entry = {'phase': 'lm', 'shooting': int(shooting), 'cost': best['cost'],
                 'evaluations': evaluations}
        history.append(entry)
        if callback is not None:
            callback(entry)
        if deadline is not None and time.perf_counter() > deadline:
            break
    return g, history

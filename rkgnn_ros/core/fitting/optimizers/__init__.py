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
Population optimizers behind one ask/tell interface: the paper's EA and CMA-ES (pycma).

The objective is batched: ``cost(X) -> f`` with ``X`` of shape (P, N), one normalised
genome per row, and ``f`` of shape (P,). An optimizer advances one generation per
``ask()``/``tell()`` pair, the way pycma does::

    opt = make_optimizer('paper', dim=N, rng=seed)
    while not stop_event.is_set():
        X = opt.ask()            # (P, N)
        opt.tell(X, cost(X))     # (P,)

so a ROS node can run it one generation at a time in a worker thread, check a stop event,
and swap in new data or settings between generations. An optimizer is not thread-safe:
the worker thread owns it and applies new settings between ``tell()`` and ``ask()``.

Non-finite costs. A diverged rollout costs ``+inf``; NaN and ``-inf`` are treated as
``+inf`` too. Such an individual never becomes ``best_x``, never is an elite, and only
wins a tournament in which every contestant diverged. pycma needs finite values, so
:func:`finite_costs` maps them to one finite value worse than every finite cost of the
generation (pycma only uses the ranking of the values).

Changing data. When the data window moves, the costs of the same genomes change. The
caller re-evaluates whatever it wants to keep (typically ``best_x``) and stores the new
value with :meth:`Optimizer.rescore`; the paper EA re-evaluates its elites anyway because
they are part of every population it asks to evaluate. :meth:`Optimizer.restart` warm
starts the search around a genome (by default the best one) and evaluates that genome in
its first generation, so the best is never lost; its cost, if known, is recorded at once.

Settings changes (:meth:`Optimizer.update_settings`, :meth:`Optimizer.set_population_size`,
:meth:`Optimizer.restart`) are validated at once and take effect when the next generation
is sampled, i.e. at the next ``ask()`` after a ``tell()``. A generation that was asked and
not yet told is left as it was, so its ``tell()`` stays valid.

Modules: :mod:`.base` (the interface, :class:`Optimizer`), :mod:`.paper_ea`
(:class:`PaperEA`), :mod:`.cmaes` (:class:`CMAES`); this package gathers them behind
:func:`make_optimizer` and runs them with :func:`minimize`.
"""

from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from .base import _check_int, finite_costs, Optimizer  # noqa: I101 (private last)
from .cmaes import CMAES, SEPARABLE_ABOVE
from .paper_ea import PaperEA

__all__ = ['CMAES', 'MinimizeResult', 'OPTIMIZERS', 'Optimizer', 'PaperEA',
           'SEPARABLE_ABOVE', 'finite_costs', 'make_optimizer', 'minimize']

#: Names accepted by :func:`make_optimizer`.
OPTIMIZERS = ('paper', 'cmaes', 'sep-cmaes')


def make_optimizer(name, dim, x0=None, rng=None, **settings) -> Optimizer:
    """
    Build an optimizer by name.

    Parameters
    ----------
    name : {'paper', 'cmaes', 'sep-cmaes'}
        'paper': :class:`PaperEA`. 'cmaes': :class:`CMAES`, full covariance unless
        N > ``SEPARABLE_ABOVE`` or ``separable=True``. 'sep-cmaes': :class:`CMAES` with
        ``separable=True``.
    dim : int
        Genome length N.
    x0 : array_like, shape (N,), optional
        Centre of the initial search distribution (default zeros).
    rng : numpy.random.Generator or int or None
        Random generator or seed.
    **settings
        Settings of the optimizer (and ``history_maxlen``).

    """
    if name == 'paper':
        return PaperEA(dim, x0, rng, **settings)
    if name == 'cmaes':
        return CMAES(dim, x0, rng, **settings)
    if name == 'sep-cmaes':
        if settings.get('separable', True) is not True:
            raise ValueError("'sep-cmaes' is separable; use 'cmaes' for the full variant")
        return CMAES(dim, x0, rng, **{**settings, 'separable': True})
    raise ValueError(f'unknown optimizer {name!r}; expected one of {OPTIMIZERS}')


@dataclass(frozen=True)
class MinimizeResult:
    """
    Outcome of :func:`minimize`.

    Attributes
    ----------
    x : ndarray, shape (N,)
        Best genome found.
    cost : float
        Its cost.
    generations : int
        Generations told to the optimizer in total.
    evaluations : int
        Evaluations told to the optimizer in total.
    message : str
        Why the loop stopped.

    """

    x: np.ndarray
    cost: float
    generations: int
    evaluations: int
    message: str


def minimize(cost: Callable[[np.ndarray], np.ndarray], optimizer: Optimizer,
             max_generations: int, callback: Optional[Callable[[Optimizer], bool]] = None,
             target: Optional[float] = None) -> MinimizeResult:
    """
    Run ``optimizer`` on a batched ``cost`` for up to ``max_generations`` generations.

    Parameters
    ----------
    cost : callable
        ``cost(X) -> f`` with ``X`` of shape (P, N) and ``f`` of shape (P,).
    optimizer : Optimizer
        Continued from its current state.
    max_generations : int
        Generations to run at most in this call.
    callback : callable, optional
        ``callback(optimizer)`` after every generation; a true return value stops.
    target : float, optional
        Stop as soon as ``optimizer.best_cost <= target``.

    """
    max_generations = _check_int('max_generations', max_generations, lo=0)
    message = 'max_generations reached'
    for _ in range(max_generations):
        X = optimizer.ask()
        f = np.asarray(cost(X), dtype=float)
        if f.shape != (X.shape[0],):
            raise ValueError(f'cost(X) must return shape ({X.shape[0]},), got {f.shape}')
        optimizer.tell(X, f)
        if target is not None and optimizer.best_cost <= target:
            message = 'target reached'
            break
        if callback is not None and callback(optimizer):
            message = 'stopped by callback'
            break
    return MinimizeResult(x=optimizer.best_x.copy(), cost=optimizer.best_cost,
                          generations=optimizer.generation,
                          evaluations=optimizer.evaluations, message=message)

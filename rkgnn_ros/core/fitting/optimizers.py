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
starts the search around a genome (by default the best one).

Settings changes (:meth:`Optimizer.update_settings`, :meth:`Optimizer.set_population_size`,
:meth:`Optimizer.restart`) are validated at once and take effect when the next generation
is sampled, i.e. at the next ``ask()`` after a ``tell()``. A generation that was asked and
not yet told is left as it was, so its ``tell()`` stays valid.
"""

from abc import ABC, abstractmethod
from dataclasses import dataclass
import math
import numbers
from typing import Callable, Optional

import cma
import numpy as np

__all__ = ['CMAES', 'MinimizeResult', 'OPTIMIZERS', 'Optimizer', 'PaperEA',
           'SEPARABLE_ABOVE', 'finite_costs', 'make_optimizer', 'minimize']

#: Names accepted by :func:`make_optimizer`.
OPTIMIZERS = ('paper', 'cmaes', 'sep-cmaes')

#: Genome length above which :class:`CMAES` defaults to the separable (diagonal) variant.
#: Full CMA-ES keeps an N x N covariance matrix and decomposes it every few generations,
#: O(N^3); with N in the thousands that costs more than the rollouts, and a full matrix
#: needs O(N^2) evaluations to learn anyway. sep-CMA-ES is O(N) per sample and learns the
#: diagonal about N times faster (Ros & Hansen 2008).
SEPARABLE_ABOVE = 300


def finite_costs(costs) -> np.ndarray:
    """
    Map non-finite costs to one finite value worse than every finite cost.

    Parameters
    ----------
    costs : array_like, shape (P,)
        Costs of one generation; NaN and ``±inf`` mean a diverged evaluation.

    Returns
    -------
    ndarray, shape (P,)
        A copy in which every non-finite entry is ``hi + max(1, |hi|, hi - lo)``, with
        ``lo``/``hi`` the smallest/largest finite cost: strictly above ``hi`` and on the
        scale of the finite costs. If that overflows it is the largest float (a tie only
        when ``hi`` is itself the largest float). If no cost is finite, all entries are 0
        (a flat generation). Finite entries are unchanged, so the ranking is preserved.

    """
    f = np.array(costs, dtype=float).reshape(-1)
    bad = ~np.isfinite(f)
    if not bad.any():
        return f
    if bad.all():
        f[:] = 0.0
        return f
    lo, hi = float(f[~bad].min()), float(f[~bad].max())
    fill = hi + max(1.0, abs(hi), hi - lo)  # Python floats: overflow gives inf, no error
    f[bad] = fill if math.isfinite(fill) else np.finfo(float).max
    return f


def _interval(lo, hi, lo_open, hi_open) -> str:
    if hi is None:
        return f'{">" if lo_open else ">="} {lo}'
    if lo is None:
        return f'{"<" if hi_open else "<="} {hi}'
    return f'in {"(" if lo_open else "["}{lo}, {hi}{")" if hi_open else "]"}'


def _bound(bound):
    """Return (label, value) of a bound given as a number or a (setting name, value) pair."""
    if isinstance(bound, tuple):
        return f'{bound[0]} ({bound[1]})', bound[1]
    return bound, bound


def _check_real(name, value, lo=None, hi=None, lo_open=False, hi_open=False) -> float:
    """
    Return ``value`` as a float, or raise ValueError naming the setting and its bound.

    ``lo``/``hi`` may be numbers or ``(label, number)`` pairs for bounds set by another
    setting, e.g. ``('sigma', 0.3)``.
    """
    lo_label, lo_val = _bound(lo)
    hi_label, hi_val = _bound(hi)
    bound = _interval(lo_label, hi_label, lo_open, hi_open)
    if (isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real)
            or not math.isfinite(value)):
        raise ValueError(f'{name} must be a finite number {bound}, got {value!r}')
    value = float(value)
    if lo_val is not None and (value <= lo_val if lo_open else value < lo_val):
        raise ValueError(f'{name} must be {bound}, got {value!r}')
    if hi_val is not None and (value >= hi_val if hi_open else value > hi_val):
        raise ValueError(f'{name} must be {bound}, got {value!r}')
    return value


def _check_int(name, value, lo=None, hi=None) -> int:
    """Return ``value`` as an int, or raise ValueError naming the setting and its bound."""
    lo_label, lo_val = _bound(lo)
    hi_label, hi_val = _bound(hi)
    bound = _interval(lo_label, hi_label, False, False)
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral):
        raise ValueError(f'{name} must be an integer {bound}, got {value!r}')
    value = int(value)
    if (lo_val is not None and value < lo_val) or (hi_val is not None and value > hi_val):
        raise ValueError(f'{name} must be {bound}, got {value!r}')
    return value


def _as_genome(x, dim, name) -> np.ndarray:
    x = np.array(x, dtype=float)
    if x.shape != (dim,):
        raise ValueError(f'{name} must have shape ({dim},), got {x.shape}')
    if not np.all(np.isfinite(x)):
        raise ValueError(f'{name} contains NaN or inf')
    return x


class Optimizer(ABC):
    """
    One generation per ``ask()``/``tell()`` pair, for a batched objective.

    Parameters
    ----------
    dim : int
        Genome length N.
    x0 : array_like, shape (N,), optional
        Centre of the initial search distribution (default zeros).
    rng : numpy.random.Generator or int or None
        Random generator, or a seed for ``np.random.default_rng``; kept as ``self.rng``.
    history_maxlen : int or None
        Keep at most this many entries in ``history`` (oldest dropped); None keeps all.
    **settings
        Algorithm settings, see the subclass; validated like :meth:`update_settings`.

    Attributes
    ----------
    generation : int
        Number of generations told so far.
    evaluations : int
        Number of cost evaluations told so far.
    best_x : ndarray, shape (N,)
        Best genome ever told with a finite cost (``x0`` until one is told).
    best_cost : float
        Its cost (``inf`` until a finite cost is told); see :meth:`rescore`.
    history : list of dict
        One entry per generation: ``generation``, ``best_cost`` (best ever),
        ``min_cost`` (best of the generation, may be inf), ``mean_cost`` (mean of the
        finite costs of the generation, NaN if none), ``n_finite``, ``spread`` (after the
        generation, i.e. the one the next generation is sampled with), ``evaluations``.

    """

    #: Name of the algorithm, as in :data:`OPTIMIZERS`.
    name = ''
    #: Default settings of the algorithm.
    DEFAULTS = {}

    def __init__(self, dim, x0=None, rng=None, *, history_maxlen=10_000, **settings):
        self.dim = _check_int('dim', dim, lo=1)
        self.x0 = np.zeros(self.dim) if x0 is None else _as_genome(x0, self.dim, 'x0')
        self.rng = np.random.default_rng(rng)
        self.history_maxlen = (None if history_maxlen is None
                               else _check_int('history_maxlen', history_maxlen, lo=1))
        self._check_names(settings)
        self._settings = self._validated({**self.DEFAULTS, **settings})
        self.generation = 0
        self.evaluations = 0
        self.best_x = self.x0.copy()
        self.best_cost = math.inf
        self.history = []

    # -- the interface ------------------------------------------------------------------

    @abstractmethod
    def ask(self) -> np.ndarray:
        """
        Return the candidates of the current generation, shape (P, N).

        Calling it again before :meth:`tell` returns the same candidates (a copy).
        """

    @abstractmethod
    def tell(self, X, costs) -> None:
        """
        Take the costs of the candidates and advance one generation.

        Parameters
        ----------
        X : array_like, shape (P, N)
            The evaluated candidates, normally what :meth:`ask` returned.
        costs : array_like, shape (P,)
            Their costs; NaN and ``±inf`` are treated as ``+inf`` (diverged).

        """

    @property
    @abstractmethod
    def population_size(self) -> int:
        """Size of the next sampled generation (number of candidates)."""

    @property
    @abstractmethod
    def spread(self) -> float:
        """Mutation standard deviation (EA) or step size sigma (CMA-ES) in use."""

    @abstractmethod
    def restart(self, x0=None, sigma=None) -> None:
        """
        Warm start the search around ``x0`` from the next generation on.

        ``x0`` defaults to ``best_x`` (if a finite cost was ever told). ``best_x``,
        ``best_cost``, ``generation``, ``evaluations`` and ``history`` are kept.
        """

    @property
    def settings(self) -> dict:
        """Copy of the current settings."""
        return dict(self._settings)

    def update_settings(self, **settings) -> None:
        """
        Change settings between generations (effective at the next sampled generation).

        All given settings are validated together with the current ones (cross-setting
        rules included) before any is applied.

        Raises
        ------
        ValueError
            Unknown setting, or a value out of range; the message names the setting and
            its bound. Nothing is changed then.

        """
        self._check_names(settings)
        new = self._validated({**self._settings, **settings})
        old, self._settings = self._settings, new
        self._settings_changed(old, new)

    def set_population_size(self, population_size) -> None:
        """Change the population size from the next sampled generation on."""
        self.update_settings(population_size=population_size)

    def seed_best(self, x, cost) -> None:
        """
        Record ``x`` as the best so far with ``cost``, e.g. a warm start scored outside.

        A non-finite cost is ignored; a finite one replaces ``best_x``/``best_cost`` only if
        it is lower (elitism holds). Call :meth:`restart` as well to search around ``x``.
        """
        x = _as_genome(x, self.dim, 'x')
        cost = float(cost)
        if math.isfinite(cost) and cost < self.best_cost:
            self.best_x = x.copy()
            self.best_cost = cost

    def rescore(self, best_cost) -> None:
        """
        Replace the stored ``best_cost``, e.g. by the cost of ``best_x`` on new data.

        A non-finite value is stored as ``inf`` (the next finite cost told replaces it).
        """
        best_cost = float(best_cost)
        self.best_cost = best_cost if math.isfinite(best_cost) else math.inf

    @classmethod
    def validate_settings(cls, **settings) -> dict:
        """Return the settings with defaults filled in, validated, or raise ValueError."""
        unknown = sorted(set(settings) - set(cls.DEFAULTS))
        if unknown:
            raise ValueError(f'unknown setting(s) {unknown} for {cls.__name__}; '
                             f'known: {sorted(cls.DEFAULTS)}')
        return cls._validated({**cls.DEFAULTS, **settings})

    # -- shared machinery ---------------------------------------------------------------

    @classmethod
    @abstractmethod
    def _validated(cls, settings) -> dict:
        """Return the validated settings dict, or raise ValueError."""

    def _settings_changed(self, old, new) -> None:
        """React to validated new settings (hook)."""

    def _check_names(self, settings) -> None:
        unknown = sorted(set(settings) - set(self.DEFAULTS))
        if unknown:
            raise ValueError(f'unknown setting(s) {unknown} for {type(self).__name__}; '
                             f'known: {sorted(self.DEFAULTS)}')

    def _check_told(self, X, costs):
        """Return (X, f) as fresh float arrays (M, N), (M,) with non-finite f set to inf."""
        X = np.array(X, dtype=float)
        if X.ndim != 2 or X.shape[0] < 1 or X.shape[1] != self.dim:
            raise ValueError(f'X must have shape (P, {self.dim}) with P >= 1, got {X.shape}')
        f = np.array(costs, dtype=float)
        if f.shape != (X.shape[0],):
            raise ValueError(f'costs must have shape ({X.shape[0]},), got {f.shape}')
        f[~np.isfinite(f)] = np.inf
        return X, f

    def _record(self, X, f) -> None:
        """Count the generation, update the best ever and append to ``history``."""
        self.generation += 1
        self.evaluations += f.size
        i = int(np.argmin(f))
        if math.isfinite(f[i]) and f[i] < self.best_cost:
            self.best_cost = float(f[i])
            self.best_x = X[i].copy()
        finite = f[np.isfinite(f)]
        self.history.append({
            'generation': self.generation,
            'best_cost': self.best_cost,
            'min_cost': float(f[i]),
            'mean_cost': float(finite.mean()) if finite.size else math.nan,
            'n_finite': int(finite.size),
            'spread': float(self.spread),
            'evaluations': self.evaluations,
        })
        if self.history_maxlen is not None and len(self.history) > self.history_maxlen:
            del self.history[:len(self.history) - self.history_maxlen]

    def _restart_centre(self, x0) -> np.ndarray:
        if x0 is not None:
            return x0
        return self.best_x.copy() if math.isfinite(self.best_cost) else None


class PaperEA(Optimizer):
    """
    The paper's evolutionary algorithm: tournament selection, crossover, mutation, elitism.

    Sections 1 and 4 of the paper: 100 individuals, tournament size 6, 20 % crossover,
    100 % mutation, 200 generations, and a mutation spread that shrinks over the run while
    "sustaining adequate standard deviation of mutation throughout the optimization".

    One generation, from the evaluated population (X, f) of M individuals:

    1. Elitism: the ``n_elite`` best individuals with a finite cost are copied unchanged
       into the next population (its first rows). They are evaluated again with it, so a
       change of data is seen at once.
    2. Selection: each of the remaining ``P - n_elite`` parents wins a tournament of
       ``tournament_size`` contestants drawn uniformly without replacement from the M
       evaluated individuals (``min(tournament_size, M)`` if the population just grew);
       the lowest cost wins, ties broken at random.
    3. Crossover: consecutive parents form pairs; with probability ``crossover_rate`` a
       pair is replaced by two BLX-alpha children (an odd last parent passes unchanged).
    4. Mutation: each offspring is mutated with probability ``mutation_rate`` (1.0, i.e.
       every offspring, in the paper); a mutated offspring gets independent Gaussian noise
       of standard deviation ``spread`` on every gene.

    The spread starts at ``sigma`` and shrinks by ``sigma_decay`` each generation, never
    below ``sigma_min``: generation g is mutated with ``max(sigma_min, sigma *
    sigma_decay**g)``. The defaults 0.3, 0.02 and 0.982 (``= (0.02 / 0.3)**(1 / 150)``
    rounded) reach the floor at generation 150 (ln 15 / -ln 0.982 = 149.1), so the last
    quarter of the paper's 200 generations searches at the sustained floor.

    Settings
    --------
    population_size : int >= 2, default 100
    tournament_size : int in [1, population_size], default 6
    crossover_rate : float in [0, 1], default 0.2
    mutation_rate : float in [0, 1], default 1.0
        Fraction of offspring mutated (each mutated one on every gene).
    sigma : float > 0, default 0.3
        Initial mutation standard deviation, in genome units. Changing it restarts the
        schedule from the new value.
    sigma_min : float in [0, sigma], default 0.02
        Floor of the mutation standard deviation.
    sigma_decay : float in (0, 1], default 0.982
        Per-generation multiplicative decay of the mutation standard deviation.
    n_elite : int in [0, population_size - 1], default 1
    init_scale : float >= 0, default 1.0
        The initial population is ``x0 + init_scale * N(0, I)``.
    blx_alpha : float >= 0, default 0.5
        Extension of the BLX-alpha crossover box.

    """

    name = 'paper'
    DEFAULTS = {
        'population_size': 100,
        'tournament_size': 6,
        'crossover_rate': 0.2,
        'mutation_rate': 1.0,
        'sigma': 0.3,
        'sigma_min': 0.02,
        'sigma_decay': 0.982,
        'n_elite': 1,
        'init_scale': 1.0,
        'blx_alpha': 0.5,
    }

    def __init__(self, dim, x0=None, rng=None, *, history_maxlen=10_000, **settings):
        super().__init__(dim, x0, rng, history_maxlen=history_maxlen, **settings)
        self._spread = self._settings['sigma']
        self._reset_spread = False
        self._pending = None  # (P, N) asked and not yet told
        self._parents = None  # (X (M, N), f (M,)) last told population
        self._restart = None  # (x0 or None, sigma) requested warm start

    @classmethod
    def _validated(cls, s) -> dict:
        v = dict(s)
        v['population_size'] = p = _check_int('population_size', s['population_size'], lo=2)
        v['tournament_size'] = _check_int('tournament_size', s['tournament_size'],
                                          lo=1, hi=('population_size', p))
        v['crossover_rate'] = _check_real('crossover_rate', s['crossover_rate'], lo=0, hi=1)
        v['mutation_rate'] = _check_real('mutation_rate', s['mutation_rate'], lo=0, hi=1)
        v['sigma'] = sigma = _check_real('sigma', s['sigma'], lo=0, lo_open=True)
        v['sigma_min'] = _check_real('sigma_min', s['sigma_min'], lo=0, hi=('sigma', sigma))
        v['sigma_decay'] = _check_real('sigma_decay', s['sigma_decay'], lo=0, hi=1,
                                       lo_open=True)
        v['n_elite'] = _check_int('n_elite', s['n_elite'],
                                  lo=0, hi=('population_size - 1', p - 1))
        v['init_scale'] = _check_real('init_scale', s['init_scale'], lo=0)
        v['blx_alpha'] = _check_real('blx_alpha', s['blx_alpha'], lo=0)
        return v

    def _settings_changed(self, old, new) -> None:
        # A new sigma restarts the schedule from it (at the next sampled generation);
        # re-sending an unchanged value (a node pushing all its parameters) does not.
        if new['sigma'] != old['sigma']:
            self._reset_spread = True

    @property
    def population_size(self) -> int:
        """Size of the next sampled generation (number of candidates)."""
        return self._settings['population_size']

    @property
    def spread(self) -> float:
        """Mutation standard deviation the next sampled generation will use."""
        s = self._settings
        if self._restart is not None:
            spread = self._restart[1]
        elif self._reset_spread:
            spread = s['sigma']
        else:
            spread = self._spread
        return max(spread, s['sigma_min'])

    def restart(self, x0=None, sigma=None) -> None:
        """
        Warm start around ``x0`` from the next generation on.

        The next population is ``x0`` itself (so a warm start never loses it) plus
        ``P - 1`` individuals ``x0 + sigma * N(0, I)``, and the mutation schedule restarts
        from ``sigma`` (default: the ``sigma`` setting; at least ``sigma_min``).
        ``x0`` defaults to ``best_x`` when the restart takes effect, or to the initial
        ``x0`` if no finite cost was told yet.
        """
        if x0 is not None:
            x0 = _as_genome(x0, self.dim, 'x0')
        sigma = self._settings['sigma'] if sigma is None else sigma
        sigma = _check_real('sigma', sigma, lo=('sigma_min', self._settings['sigma_min']))
        self._restart = (x0, sigma)

    def ask(self) -> np.ndarray:
        """
        Return the population of the current generation, shape (P, N).

        Calling it again before :meth:`tell` returns the same population (a copy).
        """
        if self._pending is None:
            self._pending = self._sample()
        return self._pending.copy()

    def tell(self, X, costs) -> None:
        """
        Take the costs of the evaluated population and advance one generation.

        Parameters
        ----------
        X : array_like, shape (M, N)
            The evaluated population, normally what :meth:`ask` returned. Any M >= 1
            individuals are accepted (e.g. to seed the search with known genomes); the
            next generation is bred from them.
        costs : array_like, shape (M,)
            Their costs; NaN and ``±inf`` are treated as ``+inf`` (diverged).

        """
        X, f = self._check_told(X, costs)
        s = self._settings
        self._parents = (X, f)
        self._pending = None
        self._spread = max(s['sigma_min'], self._spread * s['sigma_decay'])
        self._record(X, f)

    # -- one generation -------------------------------------------------------------------

    def _sample(self) -> np.ndarray:
        """Sample the next population (P, N), applying pending settings and restarts."""
        s = self._settings
        P, N = s['population_size'], self.dim
        if self._reset_spread:
            self._spread = s['sigma']
            self._reset_spread = False
        if self._restart is not None:
            x0, sigma = self._restart
            self._restart = None
            self._spread = max(sigma, s['sigma_min'])
            centre = self._restart_centre(x0)
            centre = self.x0 if centre is None else centre
            pop = centre + self._spread * self.rng.standard_normal((P, N))
            pop[0] = centre
            return pop
        self._spread = max(self._spread, s['sigma_min'])
        if self._parents is None:
            return self.x0 + s['init_scale'] * self.rng.standard_normal((P, N))
        return self._breed(*self._parents, P)

    def _breed(self, X, f, P) -> np.ndarray:
        """Return the next population (P, N) bred from the evaluated X (M, N), f (M,)."""
        s = self._settings
        n_elite = min(s['n_elite'], int(np.count_nonzero(np.isfinite(f))))
        elite = X[np.argsort(f, kind='stable')[:n_elite]]  # (n_elite, N), finite costs only
        n_off = P - n_elite
        parents = X[self._tournament(f, n_off, min(s['tournament_size'], f.size))]
        children = self._crossover(parents)  # (n_off, N)
        mutate = self.rng.random(n_off) < s['mutation_rate']
        noise = self.rng.standard_normal(children.shape)
        children[mutate] += self._spread * noise[mutate]
        return np.vstack([elite, children])

    def _tournament(self, f, n, size) -> np.ndarray:
        """
        Return the indices (n,) of the winners of n tournaments.

        Each tournament draws ``size`` distinct contestants uniformly (the first ``size``
        of a random permutation of the M individuals); the lowest cost wins. The
        contestants are in random order, so ``argmin`` breaks ties at random.
        """
        contestants = np.argsort(self.rng.random((n, f.size)), axis=1)[:, :size]  # (n, size)
        return contestants[np.arange(n), np.argmin(f[contestants], axis=1)]

    def _crossover(self, parents) -> np.ndarray:
        """
        Return BLX-alpha children (n, N) of consecutive parent pairs, with crossover_rate.

        BLX-alpha rather than uniform crossover: the genome is real-valued (RBF centres,
        widths, weights), and uniform crossover can only swap values the parents already
        have, so it adds no new values once the population has contracted. BLX-alpha
        samples every gene uniformly from the parents' interval widened by alpha times its
        length on each side; with alpha = 0.5 the children keep (slightly widen) the spread
        of the parents instead of contracting it (Eshelman & Schaffer 1993).
        """
        s = self._settings
        children = parents.copy()
        n_pairs = parents.shape[0] // 2
        a, b = parents[0:2 * n_pairs:2], parents[1:2 * n_pairs:2]  # (n_pairs, N) each
        cross = self.rng.random(n_pairs) < s['crossover_rate']
        u = self.rng.random((2,) + a.shape)  # (2, n_pairs, N)
        span = np.abs(a - b)
        low = np.minimum(a, b) - s['blx_alpha'] * span
        kids = low + u * (1.0 + 2.0 * s['blx_alpha']) * span
        children[0:2 * n_pairs:2][cross] = kids[0][cross]
        children[1:2 * n_pairs:2][cross] = kids[1][cross]
        return children


class _GeneratorRandn:
    """``randn(*shape)`` for pycma, drawing from our own Generator."""

    def __init__(self, rng):
        self.rng = rng

    def __call__(self, *shape):
        return self.rng.standard_normal(shape)


class CMAES(Optimizer):
    """
    CMA-ES through pycma's ask/tell (``cma.CMAEvolutionStrategy``).

    Randomness: pycma's ``seed`` option calls ``np.random.seed`` and then samples from the
    global numpy state, which two optimizers (or two threads) would share. Instead pycma's
    ``randn`` option is given a function drawing from ``self.rng`` and ``seed`` is NaN (no
    global seeding), so runs are reproducible from ``rng`` and the global state is never
    touched. pycma writes nothing (``verbose=-9``, ``verb_log=0``, ``verb_disp=0``), has
    no bounds, and its own iteration/evaluation limits are off: the caller decides when to
    stop.

    ``set_population_size``, a change of ``separable`` and :meth:`restart` start a new
    ``CMAEvolutionStrategy`` at the next ``ask()``, because pycma cannot change these in
    place: a resize starts at the current mean with the current sigma, a restart at
    ``x0`` with ``sigma``. The covariance matrix and evolution paths start afresh;
    ``best_x``, ``best_cost``, ``generation``, ``evaluations`` and ``history`` are kept.

    Settings
    --------
    population_size : int >= 2 or None, default None
        None: pycma's default ``4 + floor(3 ln N)``.
    sigma : float > 0, default 0.5
        Initial step size, in genome units (the genome is normalised, elements of order
        1). Changing it sets the current step size at the next generation.
    separable : bool or None, default None
        True: sep-CMA-ES (``CMA_diagonal=True``, diagonal covariance). None: True when
        N > ``SEPARABLE_ABOVE`` (300).

    """

    name = 'cmaes'
    DEFAULTS = {'population_size': None, 'sigma': 0.5, 'separable': None}

    def __init__(self, dim, x0=None, rng=None, *, history_maxlen=10_000, **settings):
        super().__init__(dim, x0, rng, history_maxlen=history_maxlen, **settings)
        self._randn = _GeneratorRandn(self.rng)
        self._es = self._new_es(self.x0, self._settings['sigma'])
        self._pending = None  # (pycma's list of P arrays, (P, N) array) asked, not told
        self._request = None  # dict(new_es, centre, sigma) applied at the next sampling

    @classmethod
    def _validated(cls, s) -> dict:
        v = dict(s)
        if s['population_size'] is not None:
            v['population_size'] = _check_int('population_size', s['population_size'], lo=2)
        v['sigma'] = _check_real('sigma', s['sigma'], lo=0, lo_open=True)
        if s['separable'] is not None:
            if not isinstance(s['separable'], (bool, np.bool_)):
                raise ValueError(f'separable must be True, False or None, '
                                 f'got {s["separable"]!r}')
            v['separable'] = bool(s['separable'])
        return v

    @property
    def separable(self) -> bool:
        """Whether the (next) strategy is sep-CMA-ES."""
        sep = self._settings['separable']
        return self.dim > SEPARABLE_ABOVE if sep is None else sep

    @property
    def es(self) -> cma.CMAEvolutionStrategy:
        """Strategy object of pycma in use (read it, do not drive it)."""
        return self._es

    @property
    def mean(self) -> np.ndarray:
        """Mean of the current search distribution, shape (N,)."""
        return np.array(self._es.mean, dtype=float)

    @property
    def population_size(self) -> int:
        """Size of the next sampled generation (number of candidates)."""
        if self._request is not None and self._request['new_es']:
            p = self._settings['population_size']
            return 4 + int(3 * math.log(self.dim)) if p is None else p
        return int(self._es.popsize)

    @property
    def spread(self) -> float:
        """Step size sigma the next sampled generation will use."""
        if self._request is not None and self._request['sigma'] is not None:
            return float(self._request['sigma'])
        return float(self._es.sigma)

    def _settings_changed(self, old, new) -> None:
        request = self._request or {'new_es': False, 'centre': 'mean', 'sigma': None}
        sep_old = self.dim > SEPARABLE_ABOVE if old['separable'] is None else old['separable']
        if new['population_size'] != old['population_size'] or self.separable != sep_old:
            request['new_es'] = True
        if new['sigma'] != old['sigma']:
            request['sigma'] = new['sigma']
        if request['new_es'] or request['sigma'] is not None:
            self._request = request

    def restart(self, x0=None, sigma=None) -> None:
        """
        Start a new strategy at ``x0`` with step size ``sigma`` from the next generation on.

        ``x0`` defaults to ``best_x`` when the restart takes effect (the current mean if no
        finite cost was told yet), ``sigma`` to the ``sigma`` setting.
        """
        if x0 is not None:
            x0 = _as_genome(x0, self.dim, 'x0')
        sigma = self._settings['sigma'] if sigma is None else sigma
        sigma = _check_real('sigma', sigma, lo=0, lo_open=True)
        self._request = {'new_es': True, 'centre': x0, 'sigma': sigma}

    def ask(self) -> np.ndarray:
        """
        Return the candidates of the current generation, shape (P, N).

        Calling it again before :meth:`tell` returns the same candidates (a copy).
        """
        if self._pending is None:
            self._apply_request()
            solutions = self._es.ask()
            self._pending = (solutions, np.array(solutions, dtype=float))
        return self._pending[1].copy()

    def tell(self, X, costs) -> None:
        """
        Take the costs of the asked candidates and advance one generation.

        Parameters
        ----------
        X : array_like, shape (P, N)
            The candidates of the pending :meth:`ask`. Modified candidates are passed to
            pycma as injected solutions (pycma may shorten unusually long steps).
        costs : array_like, shape (P,)
            Their costs; non-finite ones are mapped by :func:`finite_costs` for pycma.

        Raises
        ------
        RuntimeError
            No generation is pending (pycma learns only from the generation it sampled).

        """
        X, f = self._check_told(X, costs)
        if self._pending is None:
            raise RuntimeError('CMAES.tell() without a pending ask()')
        solutions, asked = self._pending
        if X.shape != asked.shape:
            raise ValueError(f'X must have the asked shape {asked.shape}, got {X.shape}')
        if not np.array_equal(X, asked):
            solutions = list(X)
        self._es.tell(solutions, finite_costs(f).tolist())
        self._pending = None
        self._record(X, f)

    def _apply_request(self) -> None:
        request, self._request = self._request, None
        if request is None:
            return
        if not request['new_es']:
            self._es.sigma = request['sigma']
            return
        if isinstance(request['centre'], str):  # 'mean': resize, keep the distribution
            centre = self.mean
        else:
            centre = self._restart_centre(request['centre'])
            centre = self.mean if centre is None else centre
        sigma = request['sigma'] if request['sigma'] is not None else self._es.sigma
        self._es = self._new_es(centre, sigma)

    def _new_es(self, centre, sigma) -> cma.CMAEvolutionStrategy:
        opts = {
            'seed': np.nan,  # no np.random.seed: samples come from self.rng via 'randn'
            'randn': self._randn,
            'verbose': -9,
            'verb_log': 0,
            'verb_disp': 0,
            'maxiter': np.inf,
            'maxfevals': np.inf,
            'CMA_diagonal': self.separable,
        }
        if self._settings['population_size'] is not None:
            opts['popsize'] = self._settings['population_size']
        return cma.CMAEvolutionStrategy(np.array(centre, dtype=float), float(sigma), opts)


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

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
The ask/tell interface every optimizer speaks, and the checks they share.

:class:`Optimizer` holds what is common to the algorithms: settings validated by name and
bound, the best genome ever told, the per-generation history, warm restarts and the
bookkeeping of a changing objective. A subclass adds one way to sample a generation and to
learn from its costs (:mod:`.paper_ea`, :mod:`.cmaes`).
"""

from abc import ABC, abstractmethod
import math
import numbers

import numpy as np

__all__ = ['Optimizer', 'finite_costs']


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

    The first generation contains ``x0`` itself, and so does the first after a
    :meth:`restart`: an optimizer never ends worse than the genome it started from.

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
        Best genome ever told with a finite cost, or seeded (:meth:`seed_best`,
        :meth:`restart` with a cost); ``x0`` until then.
    best_cost : float
        Its cost (``inf`` until a finite cost is told or seeded); see :meth:`rescore`.
    failures : int
        Numerical failures of the algorithm it recovered from by restarting around
        ``best_x`` (CMA-ES: pycma's assertions); ``last_failure`` says the latest.
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
        self.failures = 0
        self.last_failure = ''
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

    def restart(self, x0=None, sigma=None, cost=None) -> None:
        """
        Warm start the search around ``x0`` from the next generation on.

        The next generation contains ``x0`` itself, so once it is told ``best_cost`` is at
        most the cost of ``x0``: a restart never loses the genome it was given. A caller
        that knows that cost passes it as ``cost``; it is recorded at once
        (:meth:`seed_best`), so ``best_x`` / ``best_cost`` report the genome before any
        generation is told. ``best_x``, ``best_cost``, ``generation``, ``evaluations`` and
        ``history`` are kept.

        Parameters
        ----------
        x0 : array_like, shape (N,), optional
            Centre; default ``best_x`` when the restart takes effect (if a finite cost was
            ever told; otherwise the subclass's own centre).
        sigma : float, optional
            Spread of the new search (default the ``sigma`` setting).
        cost : float, optional
            Cost of ``x0`` on the current data (needs ``x0``).

        """
        if x0 is not None:
            x0 = _as_genome(x0, self.dim, 'x0')
        sigma = self._check_restart_sigma(self._settings['sigma'] if sigma is None else sigma)
        if cost is not None:
            if x0 is None:
                raise ValueError('cost is the cost of x0: give x0 with it')
            self.seed_best(x0, cost)
        self._request_restart(x0, sigma)

    @abstractmethod
    def _check_restart_sigma(self, sigma) -> float:
        """Return the validated spread of a restart, or raise ValueError."""

    @abstractmethod
    def _request_restart(self, x0, sigma) -> None:
        """Start the search around ``x0`` (None: ``best_x``) at the next sampling."""

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

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
CMA-ES through pycma's ask/tell, driven by our own random generator.

pycma samples from the global numpy state and cannot change its population size or
restart in place; :class:`CMAES` hides both behind the interface of :class:`.Optimizer`.
pycma also asserts on numbers it cannot handle (a subnormal step size, genomes near the
largest float); such a failure restarts the strategy around the best genome instead of
ending the search (:attr:`.Optimizer.failures` counts them).
"""

import math
from typing import TYPE_CHECKING

import numpy as np

from .base import _check_int, _check_real, finite_costs, Optimizer

if TYPE_CHECKING:  # pragma: no cover - for the annotations only
    import cma

__all__ = ['CMAES', 'SEPARABLE_ABOVE', 'load_pycma']


def load_pycma():
    """
    Return pycma, imported at the first call.

    Its import takes about 1.5 s (it brings scipy.stats and matplotlib.pyplot): imported with
    this module, it was 60 % of the identifier's start-up, before the node could take its
    first joint_states. The identifier's worker thread loads it while data are buffered.
    """
    import cma
    return cma


#: What pycma raises when its state stops being numbers (checked finite by assertions).
_NUMERIC_FAILURES = (AssertionError, ArithmeticError, ValueError, np.linalg.LinAlgError)

#: Genome length above which :class:`CMAES` defaults to the separable (diagonal) variant.
#: Full CMA-ES keeps an N x N covariance matrix and decomposes it every few generations,
#: O(N^3); with N in the thousands that costs more than the rollouts, and a full matrix
#: needs O(N^2) evaluations to learn anyway. sep-CMA-ES is O(N) per sample and learns the
#: diagonal about N times faster (Ros & Hansen 2008).
SEPARABLE_ABOVE = 300


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
    The first generation and the first after a restart contain the centre itself (one of
    the ``population_size`` candidates), so the genome a search starts from is always
    evaluated and never lost; a resize does not (its mean was never a candidate).

    When pycma fails numerically in ``ask`` or ``tell`` (its assertions that its state is
    finite, an overflow, a singular decomposition), the generation's costs are still
    recorded, the strategy restarts around ``best_x`` (its centre if nothing finite was
    told yet) with the ``sigma`` setting (at least :attr:`SIGMA_FLOOR`), and
    :attr:`failures` / :attr:`last_failure` say so: the search keeps its best and goes on,
    nothing is raised.

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
    #: The smallest step a recovery restarts with: far below any useful step in genome
    #: units (elements of order 1), far above what pycma fails on (subnormal numbers).
    SIGMA_FLOOR = 1e-6

    def __init__(self, dim, x0=None, rng=None, *, history_maxlen=10_000, **settings):
        super().__init__(dim, x0, rng, history_maxlen=history_maxlen, **settings)
        self._randn = _GeneratorRandn(self.rng)
        self._es = self._new_es(self.x0, self._settings['sigma'], evaluate_centre=True)
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
    def es(self) -> 'cma.CMAEvolutionStrategy':
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

    def _check_restart_sigma(self, sigma) -> float:
        return _check_real('sigma', sigma, lo=0, lo_open=True)

    def _request_restart(self, x0, sigma) -> None:
        # a new strategy at x0 (default best_x when it takes effect, else the current mean)
        self._request = {'new_es': True, 'centre': x0, 'sigma': sigma}

    def ask(self) -> np.ndarray:
        """
        Return the candidates of the current generation, shape (P, N).

        Calling it again before :meth:`tell` returns the same candidates (a copy).
        """
        if self._pending is None:
            self._apply_request()
            try:
                solutions = self._sample()
            except _NUMERIC_FAILURES as exc:
                self._recover(exc)
                solutions = self._sample()
            self._pending = (solutions, np.array(solutions, dtype=float))
        return self._pending[1].copy()

    def _sample(self) -> list:
        with np.errstate(all='ignore'):
            solutions = self._es.ask()
        if not np.isfinite(solutions).all():
            raise FloatingPointError('pycma sampled non-finite candidates')
        return solutions

    def _recover(self, exc: BaseException) -> None:
        """Restart the strategy around the best genome after a numerical failure of pycma."""
        self.failures += 1
        self.last_failure = f'{type(exc).__name__}: {exc}'.rstrip(': ')
        centre = self._restart_centre(None)
        self._es = self._new_es(self.x0 if centre is None else centre,
                                max(self._settings['sigma'], self.SIGMA_FLOOR),
                                evaluate_centre=True)

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
        self._pending = None
        try:
            with np.errstate(all='ignore'):
                self._es.tell(solutions, finite_costs(f).tolist())
        except _NUMERIC_FAILURES as exc:
            self._record(X, f)  # the costs are sound: the best is kept
            self._recover(exc)
            return
        self._record(X, f)

    def _apply_request(self) -> None:
        request, self._request = self._request, None
        if request is None:
            return
        if not request['new_es']:
            self._es.sigma = request['sigma']
            return
        resize = isinstance(request['centre'], str)  # 'mean': keep the distribution
        if resize:
            centre = self.mean
        else:
            centre = self._restart_centre(request['centre'])
            centre = self.mean if centre is None else centre
        sigma = request['sigma'] if request['sigma'] is not None else self._es.sigma
        self._es = self._new_es(centre, sigma, evaluate_centre=not resize)

    def _new_es(self, centre, sigma, evaluate_centre=False) -> 'cma.CMAEvolutionStrategy':
        """
        Return a new strategy at ``centre``; with ``evaluate_centre`` its first generation.

        The centre is put in the first generation with pycma's ``inject(force=True)``: it is
        asked and told like any candidate (so ``best_cost`` is at most its cost afterwards)
        and pycma does not shorten its (zero) step from the mean.
        """
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
        es = load_pycma().CMAEvolutionStrategy(np.array(centre, dtype=float), float(sigma),
                                               opts)
        if evaluate_centre:
            es.inject([np.array(centre, dtype=float)], force=True)
        return es

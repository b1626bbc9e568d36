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
The paper's evolutionary algorithm (sections 1 and 4): tournament, crossover, mutation.

The paper gives its operators and budget but not how it initialises the population; the
choice made here (the start genome in the first generation, the rest spread around it by
the initial mutation spread) is documented on :class:`PaperEA`; the study of that spread
(``tools/paper.py --spread-study``) is in ``bench/results/paper_ea_spread.json`` and the
README's results.
"""

import numpy as np

from .base import _check_int, _check_real, Optimizer  # noqa: I101 (private first)

__all__ = ['PaperEA']


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
    init_scale : float >= 0 or None, default None
        Spread of the first generation around ``x0`` (None: ``sigma``).
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
        'init_scale': None,
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
        if s['init_scale'] is not None:
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

    def _check_restart_sigma(self, sigma) -> float:
        return _check_real('sigma', sigma, lo=('sigma_min', self._settings['sigma_min']))

    def _request_restart(self, x0, sigma) -> None:
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
            scale = s['sigma'] if s['init_scale'] is None else s['init_scale']
            pop = self.x0 + scale * self.rng.standard_normal((P, N))
            pop[0] = self.x0
            return pop
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

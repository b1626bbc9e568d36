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
Tests of the population optimizers (paper EA, CMA-ES) behind the ask/tell interface.

Plain pytest, no middleware. Every run is seeded, so the statistical checks are exact
reproductions, not flaky draws.
"""

import math

from hypothesis import given
from hypothesis import strategies as st
import numpy as np
import pytest
from rkgnn_ros.core.fitting.optimizers import (CMAES, finite_costs, make_optimizer, minimize,
                                               OPTIMIZERS, PaperEA, SEPARABLE_ABOVE)
from scipy import stats

SHIFT20 = np.linspace(-1.0, 1.0, 20) + 0.3  # optimum of the shifted sphere, shape (20,)
SHIFT10 = np.linspace(-0.5, 1.0, 10)  # optimum of the shifted Rosenbrock, shape (10,)


def sphere(X, shift=SHIFT20):
    """Shifted sphere, X (P, N) -> (P,)."""
    return np.sum((X - shift) ** 2, axis=1)


def rosenbrock(X, shift=SHIFT10):
    """Shifted Rosenbrock with its minimum 0 at ``shift``, X (P, N) -> (P,)."""
    Z = X - shift + 1.0
    return np.sum(100.0 * (Z[:, 1:] - Z[:, :-1] ** 2) ** 2 + (1.0 - Z[:, :-1]) ** 2, axis=1)


def bowl(X):
    """Sphere centred at 0.5 in any dimension, X (P, N) -> (P,)."""
    return np.sum((X - 0.5) ** 2, axis=1)


def run(opt, cost, generations):
    """Run ``generations`` generations; return the list of asked populations."""
    asked = []
    for _ in range(generations):
        X = opt.ask()
        asked.append(X)
        opt.tell(X, cost(X))
    return asked


# -- convergence ---------------------------------------------------------------------------

def test_paper_ea_reduces_shifted_sphere():
    opt = PaperEA(20, rng=1)
    result = minimize(sphere, opt, 200)
    first = opt.history[0]['min_cost']
    assert first > 5.0
    assert result.cost < 1e-2 * first  # two orders of magnitude in 20 000 evaluations
    assert result.cost == pytest.approx(sphere(result.x[None])[0])
    assert result.evaluations == 200 * 100


@pytest.mark.parametrize('name', ['cmaes', 'sep-cmaes'])
def test_cmaes_reduces_shifted_sphere(name):
    opt = make_optimizer(name, 20, rng=1)
    result = minimize(sphere, opt, 150)
    first = opt.history[0]['min_cost']
    assert first > 5.0
    assert result.cost < 1e-6 * first
    assert result.evaluations == 150 * opt.population_size


def test_paper_ea_beats_random_search_on_rosenbrock():
    opt = PaperEA(10, rng=3)
    result = minimize(rosenbrock, opt, 200)
    rng = np.random.default_rng(3)
    # random search with the EA's initial distribution and the same number of evaluations
    random_best = rosenbrock(rng.standard_normal((result.evaluations, 10))).min()
    assert result.cost < 0.2 * random_best


# -- reproducibility -----------------------------------------------------------------------

@pytest.mark.parametrize('name', OPTIMIZERS)
def test_same_seed_same_asks_different_seed_different(name):
    a = run(make_optimizer(name, 8, rng=42, population_size=10), bowl, 5)
    b = run(make_optimizer(name, 8, rng=np.random.default_rng(42), population_size=10),
            bowl, 5)
    c = run(make_optimizer(name, 8, rng=43, population_size=10), bowl, 5)
    for Xa, Xb in zip(a, b):
        np.testing.assert_array_equal(Xa, Xb)
    assert not np.array_equal(a[0], c[0])
    assert not np.array_equal(a[-1], c[-1])


def test_cmaes_leaves_global_numpy_random_state_alone():
    before = np.random.get_state()
    opt = CMAES(6, rng=0)
    run(opt, lambda X: np.sum(X ** 2, axis=1), 3)
    after = np.random.get_state()
    np.testing.assert_array_equal(before[1], after[1])
    assert before[2] == after[2]


def test_ask_is_idempotent_until_tell():
    for opt in (PaperEA(5, rng=0, population_size=8), CMAES(5, rng=0)):
        X1 = opt.ask()
        X1[:] = 99.0  # the caller owns the copy
        X2 = opt.ask()
        assert not np.any(X2 == 99.0)
        np.testing.assert_array_equal(X2, opt.ask())
        opt.tell(X2, bowl(X2))
        assert not np.array_equal(X2, opt.ask())


# -- elitism ---------------------------------------------------------------------------------

def test_elitism_generation_best_never_worsens():
    opt = PaperEA(20, rng=5)
    run(opt, sphere, 60)
    mins = [h['min_cost'] for h in opt.history]
    assert all(b <= a for a, b in zip(mins, mins[1:]))
    best = [h['best_cost'] for h in opt.history]
    assert all(b <= a for a, b in zip(best, best[1:]))
    assert best == mins  # on a fixed objective the elite is the best ever


def test_without_elitism_generation_best_does_worsen():
    # the check above has power: without the elite the generation best goes up at times
    opt = PaperEA(20, rng=5, n_elite=0)
    run(opt, sphere, 60)
    mins = [h['min_cost'] for h in opt.history]
    assert any(b > a for a, b in zip(mins, mins[1:]))


def test_best_individual_appears_unchanged_in_next_population():
    opt = PaperEA(20, rng=6, n_elite=3)
    X = opt.ask()
    for _ in range(20):
        f = sphere(X)
        opt.tell(X, f)
        X_next = opt.ask()
        order = np.argsort(f)
        np.testing.assert_array_equal(X_next[:3], X[order[:3]])
        np.testing.assert_array_equal(opt.best_x, X_next[0])
        X = X_next


# -- non-finite costs ------------------------------------------------------------------------

def diverging_sphere(X):
    """
    Shifted sphere that diverges on a half-space through its optimum.

    Around the optimum about half of every population diverges (inf), some of it as NaN.
    """
    f = sphere(X)
    diverged = X[:, 7] > SHIFT20[7]  # SHIFT20[7] = 0.037: half of N(0, I) diverges
    f[diverged] = np.where(X[diverged, 1] > 0.0, np.nan, np.inf)
    return f


@pytest.mark.parametrize('name', OPTIMIZERS)
def test_inf_and_nan_costs_never_make_the_best(name):
    opt = make_optimizer(name, 20, rng=7)
    X = opt.ask()
    f = diverging_sphere(X)
    assert np.isnan(f).any() and np.isinf(f).any()
    assert 0.25 < np.mean(~np.isfinite(f)) < 0.75
    run(opt, diverging_sphere, 80)
    diverged = [1.0 - h['n_finite'] / opt.population_size for h in opt.history[-20:]]
    assert 0.05 < np.mean(diverged) < 0.8  # still pressing against the diverged region
    assert math.isfinite(opt.best_cost)
    assert opt.best_x[7] <= SHIFT20[7]
    assert opt.best_cost == sphere(opt.best_x[None])[0]
    assert np.isfinite(diverging_sphere(opt.best_x[None])[0])
    assert all(math.isfinite(h['mean_cost']) for h in opt.history)
    assert opt.history[-1]['best_cost'] < 0.1 * opt.history[0]['best_cost']
    assert math.isfinite(opt.spread) and opt.spread > 0


def test_inf_individuals_are_never_elite_or_parents_of_finite_winners():
    opt = PaperEA(4, rng=0, population_size=6, n_elite=3, tournament_size=6)
    X = np.arange(24.0).reshape(6, 4)
    f = np.array([np.inf, np.nan, 5.0, np.inf, -np.inf, np.nan])
    opt.tell(X, f)
    assert opt.best_cost == 5.0
    np.testing.assert_array_equal(opt.best_x, X[2])
    X_next = opt.ask()
    np.testing.assert_array_equal(X_next[0], X[2])  # the only finite individual is elite
    for row in X_next[1:]:  # no diverged individual was copied as an elite
        assert not any(np.array_equal(row, x) for x in X)
    # tournament of the whole population: every offspring descends from X[2]
    assert np.all(np.abs(X_next[1:] - X[2]).max(axis=1) < 2.0)


@pytest.mark.parametrize('name', OPTIMIZERS)
def test_all_diverged_generation_is_survivable(name):
    opt = make_optimizer(name, 5, rng=0, population_size=8)
    for _ in range(3):
        X = opt.ask()
        opt.tell(X, np.full(len(X), np.inf))
    assert opt.best_cost == math.inf
    np.testing.assert_array_equal(opt.best_x, np.zeros(5))
    assert math.isnan(opt.history[-1]['mean_cost'])
    X = opt.ask()
    assert X.shape == (8, 5) and np.all(np.isfinite(X))
    opt.tell(X, bowl(X))
    assert math.isfinite(opt.best_cost)


@given(st.lists(st.one_of(st.floats(allow_nan=True, allow_infinity=True),
                          st.sampled_from([np.inf, -np.inf, np.nan])), min_size=1, max_size=30))
def test_finite_costs_is_finite_worse_and_order_preserving(costs):
    costs = np.array(costs, dtype=float)
    mapped = finite_costs(costs)
    ok = np.isfinite(costs)
    assert mapped.shape == costs.shape
    assert np.all(np.isfinite(mapped))
    np.testing.assert_array_equal(mapped[ok], costs[ok])
    if ok.any() and not ok.all():
        fill = mapped[~ok]
        assert np.all(fill == fill[0])
        top = costs[ok].max()
        assert fill[0] > top or top == np.finfo(float).max


# -- spread ----------------------------------------------------------------------------------

def test_paper_spread_schedule_reaches_floor_at_generation_150_and_stays():
    opt = PaperEA(5, rng=0, population_size=10)
    run(opt, bowl, 300)
    spreads = np.array([h['spread'] for h in opt.history])  # spread after generation g
    g = np.arange(1, 301)
    np.testing.assert_allclose(spreads, np.maximum(0.02, 0.3 * 0.982 ** g), rtol=1e-12)
    assert np.all(spreads >= 0.02)
    assert spreads[148] > 0.02 and spreads[149] == 0.02  # generations 149 and 150
    assert opt.spread == 0.02


def test_paper_mutation_spread_is_measurable_in_offspring():
    # no crossover, no elite, tournament of 1: offspring = random parent + N(0, spread^2)
    opt = PaperEA(50, rng=0, population_size=200, tournament_size=1, crossover_rate=0.0,
                  n_elite=0, sigma=0.25)
    X = np.zeros((200, 50))
    opt.tell(X, np.zeros(200))
    spread = opt.spread
    assert spread == pytest.approx(0.25 * 0.982)
    noise = opt.ask()
    assert np.all(noise != 0.0)  # every offspring mutated on every gene
    assert noise.std() == pytest.approx(spread, rel=0.02)


def test_paper_mutation_rate_zero_copies_parents():
    opt = PaperEA(5, rng=0, population_size=10, crossover_rate=0.0, mutation_rate=0.0)
    X = opt.ask()
    opt.tell(X, bowl(X))
    for row in opt.ask():
        assert any(np.array_equal(row, x) for x in X)


def test_blx_alpha_children_fill_the_widened_box():
    a, b = np.zeros(3), np.array([1.0, 2.0, -1.0])
    opt = PaperEA(3, rng=0, population_size=2000, tournament_size=1, crossover_rate=1.0,
                  mutation_rate=0.0, n_elite=0)
    opt.tell(np.vstack([a, b]), np.array([1.0, 2.0]))
    kids = opt.ask()
    low, high = np.minimum(a, b), np.maximum(a, b)
    span = high - low
    assert np.all(kids >= low - 0.5 * span) and np.all(kids <= high + 0.5 * span)
    outside = (kids < low) | (kids > high)
    assert 0.05 < outside.mean() < 0.4  # BLX-0.5 reaches beyond the parents; uniform does not


@pytest.mark.parametrize('name', ['cmaes', 'sep-cmaes'])
def test_cmaes_sigma_stays_positive(name):
    opt = make_optimizer(name, 10, rng=0)
    run(opt, lambda X: np.sum((X - 0.2) ** 2, axis=1), 300)
    spreads = np.array([h['spread'] for h in opt.history])
    assert np.all(spreads > 0) and np.all(np.isfinite(spreads))
    assert spreads[-1] < 1e-3 * spreads[0]  # it did contract
    assert opt.spread == opt.es.sigma


# -- settings --------------------------------------------------------------------------------

@pytest.mark.parametrize('kwargs, match', [
    ({'population_size': 0}, r'population_size must be >= 2'),
    ({'population_size': 1}, r'population_size must be >= 2'),
    ({'population_size': 10.0}, r'population_size must be an integer'),
    ({'tournament_size': 0}, r'tournament_size must be in \[1, population_size \(100\)\]'),
    ({'tournament_size': 101}, r'tournament_size must be in \[1, population_size \(100\)\]'),
    ({'population_size': 5}, r'tournament_size must be in \[1, population_size \(5\)\]'),
    ({'crossover_rate': 1.5}, r'crossover_rate must be in \[0, 1\]'),
    ({'crossover_rate': -0.1}, r'crossover_rate must be in \[0, 1\]'),
    ({'mutation_rate': 1.01}, r'mutation_rate must be in \[0, 1\]'),
    ({'crossover_rate': math.nan}, r'crossover_rate must be a finite number in \[0, 1\]'),
    ({'sigma': 0.0}, r'sigma must be > 0'),
    ({'sigma': -1.0}, r'sigma must be > 0'),
    ({'sigma': math.nan}, r'sigma must be a finite number > 0'),
    ({'sigma': math.inf}, r'sigma must be a finite number > 0'),
    ({'sigma_min': 0.5}, r'sigma_min must be in \[0, sigma \(0.3\)\]'),
    ({'sigma_min': -0.01}, r'sigma_min must be in \[0, sigma \(0.3\)\]'),
    ({'sigma_decay': 0.0}, r'sigma_decay must be in \(0, 1\]'),
    ({'sigma_decay': 1.1}, r'sigma_decay must be in \(0, 1\]'),
    ({'n_elite': 100}, r'n_elite must be in \[0, population_size - 1 \(99\)\]'),
    ({'n_elite': -1}, r'n_elite must be in \[0, population_size - 1 \(99\)\]'),
    ({'init_scale': -1.0}, r'init_scale must be >= 0'),
    ({'blx_alpha': math.nan}, r'blx_alpha must be a finite number >= 0'),
    ({'tournament_size': True}, r'tournament_size must be an integer'),
    ({'tournamentsize': 6}, r'unknown setting.*tournamentsize'),
])
def test_paper_invalid_settings_name_setting_and_bound(kwargs, match):
    with pytest.raises(ValueError, match=match):
        PaperEA(4, **kwargs)
    opt = PaperEA(4)
    before = opt.settings
    with pytest.raises(ValueError, match=match):
        opt.update_settings(**kwargs)
    assert opt.settings == before  # nothing applied


@pytest.mark.parametrize('kwargs', [
    {'crossover_rate': 0.0}, {'crossover_rate': 1.0},
    {'mutation_rate': 0.0}, {'mutation_rate': 1.0},
    {'tournament_size': 100}, {'tournament_size': 1},
    {'population_size': 6, 'tournament_size': 6, 'n_elite': 5},
    {'population_size': 2, 'tournament_size': 2, 'n_elite': 0},
    {'sigma_min': 0.3}, {'sigma_min': 0.0}, {'sigma_decay': 1.0},
    {'init_scale': 0.0}, {'blx_alpha': 0.0}, {'n_elite': 0},
])
def test_paper_boundary_settings_accepted(kwargs):
    opt = PaperEA(4, rng=0, **kwargs)
    for key, value in kwargs.items():
        assert opt.settings[key] == value
    run(opt, lambda X: np.sum(X ** 2, axis=1), 3)
    assert opt.ask().shape == (opt.population_size, 4)


@pytest.mark.parametrize('kwargs, match', [
    ({'population_size': 1}, r'population_size must be >= 2'),
    ({'sigma': 0.0}, r'sigma must be > 0'),
    ({'sigma': math.nan}, r'sigma must be a finite number > 0'),
    ({'separable': 1}, r'separable must be True, False or None'),
    ({'tournament_size': 6}, r'unknown setting.*tournament_size'),
])
def test_cmaes_invalid_settings(kwargs, match):
    with pytest.raises(ValueError, match=match):
        CMAES(4, **kwargs)
    opt = CMAES(4)
    with pytest.raises(ValueError, match=match):
        opt.update_settings(**kwargs)


def test_restart_sigma_below_floor_rejected():
    with pytest.raises(ValueError, match=r'sigma must be >= sigma_min \(0.02\)'):
        PaperEA(4).restart(sigma=0.01)
    with pytest.raises(ValueError, match=r'x0 must have shape \(4,\)'):
        CMAES(4).restart(x0=np.zeros(3))


def test_paper_sigma_change_restarts_schedule_between_generations():
    opt = PaperEA(4, rng=0, population_size=10)
    run(opt, bowl, 10)
    assert opt.spread == pytest.approx(0.3 * 0.982 ** 10)
    opt.update_settings(sigma=0.3)  # unchanged value: no reset
    assert opt.spread == pytest.approx(0.3 * 0.982 ** 10)
    opt.update_settings(sigma=0.5)
    assert opt.spread == 0.5
    run(opt, bowl, 1)
    assert opt.spread == pytest.approx(0.5 * 0.982)
    opt.update_settings(sigma_min=0.495)
    assert opt.spread == 0.495


# -- population size -------------------------------------------------------------------------

@pytest.mark.parametrize('new_size', [30, 150])
def test_paper_set_population_size_keeps_the_best(new_size):
    opt = PaperEA(20, rng=2, n_elite=2)
    run(opt, sphere, 5)
    X = opt.ask()
    f = sphere(X)
    opt.tell(X, f)
    opt.set_population_size(new_size)
    assert opt.population_size == new_size
    X_next = opt.ask()
    assert X_next.shape == (new_size, 20)
    np.testing.assert_array_equal(X_next[:2], X[np.argsort(f)[:2]])
    opt.tell(X_next, sphere(X_next))
    assert opt.best_cost <= f.min()
    assert opt.evaluations == 6 * 100 + new_size


def test_paper_shrinking_below_tournament_size_is_rejected():
    opt = PaperEA(5)
    with pytest.raises(ValueError, match=r'tournament_size must be in \[1, population_size'):
        opt.set_population_size(4)
    opt.update_settings(population_size=4, tournament_size=4)  # both together are fine
    assert opt.ask().shape == (4, 5)


def test_size_change_waits_for_the_pending_generation():
    opt = PaperEA(5, rng=0, population_size=10)
    X = opt.ask()
    opt.set_population_size(20)
    assert opt.ask().shape == (10, 5)  # the pending generation is left as it was
    opt.tell(X, bowl(X))
    assert opt.ask().shape == (20, 5)


@pytest.mark.parametrize('separable', [False, True])
def test_cmaes_set_population_size_restarts_at_mean_and_keeps_best(separable):
    opt = CMAES(10, rng=4, separable=separable)
    run(opt, lambda X: np.sum((X - 0.2) ** 2, axis=1), 20)
    best_x, best_cost = opt.best_x.copy(), opt.best_cost
    mean, sigma = opt.mean, opt.spread
    opt.set_population_size(25)
    assert opt.population_size == 25
    X = opt.ask()
    assert X.shape == (25, 10)
    np.testing.assert_array_equal(opt.mean, mean)
    assert opt.spread == sigma
    assert opt.es.popsize == 25
    np.testing.assert_array_equal(opt.best_x, best_x)
    assert opt.best_cost == best_cost
    opt.tell(X, np.sum((X - 0.2) ** 2, axis=1))
    assert opt.generation == 21
    assert opt.best_cost <= best_cost


def test_cmaes_tell_needs_the_pending_generation():
    opt = CMAES(4, rng=0)
    with pytest.raises(RuntimeError, match='without a pending ask'):
        opt.tell(np.zeros((8, 4)), np.zeros(8))
    X = opt.ask()
    with pytest.raises(ValueError, match='asked shape'):
        opt.tell(X[:-1], np.zeros(len(X) - 1))
    with pytest.raises(ValueError, match='costs must have shape'):
        opt.tell(X, np.zeros(len(X) + 1))


# -- selection pressure ----------------------------------------------------------------------

def test_full_tournament_always_selects_the_best():
    P = 30
    opt = PaperEA(6, rng=9, population_size=P, tournament_size=P, crossover_rate=0.0,
                  mutation_rate=0.0, n_elite=0)
    rng = np.random.default_rng(1)
    for _ in range(20):
        X = rng.standard_normal((P, 6))
        f = rng.random(P)
        opt.tell(X, f)
        np.testing.assert_array_equal(opt.ask(), np.repeat(X[[np.argmin(f)]], P, axis=0))


def test_tournament_win_frequencies_match_theory():
    # size-2 tournaments drawn without replacement from P: the individual of rank r
    # (0 = best) wins with probability 2 (P - 1 - r) / (P (P - 1))
    P, t = 10, 2
    opt = PaperEA(1, rng=11, population_size=P, tournament_size=t, crossover_rate=0.0,
                  mutation_rate=0.0, n_elite=0)
    X = np.arange(P, dtype=float)[:, None]  # individual i has rank i
    counts = np.zeros(P)
    for _ in range(400):
        opt.tell(X, X[:, 0])
        counts += np.bincount(opt.ask()[:, 0].astype(int), minlength=P)
    expected = 2.0 * (P - 1 - np.arange(P)) / (P * (P - 1)) * counts.sum()
    assert counts[-1] == 0  # the worst never wins a tournament of two
    _, p_value = stats.chisquare(counts[:-1], expected[:-1])
    assert p_value > 1e-3
    # and the test has power: uniform selection is rejected
    _, p_uniform = stats.chisquare(counts, np.full(P, counts.sum() / P))
    assert p_uniform < 1e-6


# -- restart, rescore, loop, factory ---------------------------------------------------------

def test_paper_restart_around_x0():
    opt = PaperEA(40, rng=0, population_size=50)
    run(opt, bowl, 5)
    x0 = np.full(40, 3.0)
    opt.restart(x0, sigma=0.1)
    assert opt.spread == 0.1
    X = opt.ask()
    np.testing.assert_array_equal(X[0], x0)
    assert np.std(X[1:] - x0) == pytest.approx(0.1, rel=0.05)
    opt.tell(X, bowl(X))
    assert opt.generation == 6


def test_paper_restart_defaults_to_best():
    opt = PaperEA(5, rng=0, population_size=10)
    run(opt, bowl, 5)
    opt.restart()
    np.testing.assert_array_equal(opt.ask()[0], opt.best_x)
    assert opt.spread == 0.3


def test_cmaes_restart_around_x0():
    opt = CMAES(8, rng=0)
    run(opt, bowl, 5)
    opt.restart(np.full(8, -2.0), sigma=0.05)
    assert opt.spread == 0.05
    X = opt.ask()
    np.testing.assert_array_equal(opt.mean, np.full(8, -2.0))
    assert np.abs(X + 2.0).max() < 0.05 * 6
    opt.restart()  # default centre: the best so far, sigma from the settings
    opt.tell(X, bowl(X))
    opt.ask()
    np.testing.assert_array_equal(opt.mean, opt.best_x)
    assert opt.spread == 0.5


@pytest.mark.parametrize('name', OPTIMIZERS)
@pytest.mark.parametrize('give_cost', [False, True])
def test_restart_reports_the_genome_cost_until_it_finds_better(name, give_cost):
    floor = {'sigma_min': 1e-4} if name == 'paper' else {}
    opt = make_optimizer(name, 20, rng=4, population_size=12, **floor)
    run(opt, sphere, 3)                      # its own best is far from the optimum
    genome = SHIFT20 + 0.01                  # sphere(genome) = 0.002, far below that best
    g_cost = float(sphere(genome[None])[0])
    assert opt.best_cost > 10 * g_cost
    opt.restart(genome, sigma=3.0, cost=g_cost if give_cost else None)
    if give_cost:                            # known cost: reported before any generation
        assert opt.best_cost == g_cost
        np.testing.assert_array_equal(opt.best_x, genome)
    X = opt.ask()
    assert np.any(np.all(X == genome, axis=1))   # the genome itself is evaluated
    opt.tell(X, sphere(X))
    # a spread of 3 puts every other candidate near cost 20 * 9: none is better
    assert opt.best_cost == g_cost
    np.testing.assert_array_equal(opt.best_x, genome)
    opt.restart(sigma=0.002)                 # around the best, small enough to improve on it
    costs = []
    for _ in range(30):
        X = opt.ask()
        opt.tell(X, sphere(X))
        costs.append(opt.best_cost)
    assert all(c <= g_cost for c in costs) and costs == sorted(costs, reverse=True)
    assert costs[-1] < g_cost


@pytest.mark.parametrize('name', OPTIMIZERS)
def test_restart_around_a_worse_genome_keeps_the_better_best(name):
    opt = make_optimizer(name, 20, rng=5, population_size=12)
    run(opt, sphere, 3)
    best_x, best_cost = opt.best_x.copy(), opt.best_cost
    worse = SHIFT20 + 10.0
    opt.restart(worse, sigma=0.1, cost=float(sphere(worse[None])[0]))
    assert opt.best_cost == best_cost
    np.testing.assert_array_equal(opt.best_x, best_x)
    X = opt.ask()
    np.testing.assert_allclose(X.mean(axis=0), worse, atol=1.0)   # searches there
    opt.tell(X, sphere(X))
    assert opt.best_cost == best_cost


def test_restart_cost_needs_the_genome():
    with pytest.raises(ValueError, match='cost is the cost of x0'):
        PaperEA(3, rng=0).restart(cost=1.0)


@pytest.mark.parametrize('name', OPTIMIZERS)
def test_first_generation_contains_x0(name):
    x0 = np.linspace(-1.0, 1.0, 20)
    opt = make_optimizer(name, 20, x0=x0, rng=6)
    X = opt.ask()
    assert np.all(X[0] == x0)
    assert not np.any(np.all(X[1:] == x0, axis=1))
    opt.tell(X, sphere(X))
    assert opt.best_cost <= sphere(x0[None])[0]


def test_cmaes_resize_does_not_re_evaluate_the_mean():
    opt = CMAES(8, rng=0, population_size=6)
    run(opt, bowl, 3)
    opt.set_population_size(10)
    X = opt.ask()
    assert X.shape == (10, 8)
    assert not np.any(np.all(X == opt.mean, axis=1))


@pytest.mark.parametrize('name', OPTIMIZERS)
def test_rescore_replaces_best_cost(name):
    opt = make_optimizer(name, 4, rng=0, population_size=6)
    run(opt, bowl, 3)
    opt.rescore(math.nan)
    assert opt.best_cost == math.inf
    opt.rescore(1e6)  # the data changed: the stored best is now much worse
    assert opt.best_cost == 1e6
    X = opt.ask()
    f = bowl(X) + 10.0  # worse than every cost told before the change
    opt.tell(X, f)
    assert opt.best_cost == f.min()
    np.testing.assert_array_equal(opt.best_x, X[np.argmin(f)])


def test_minimize_stops_on_target_callback_and_limit():
    opt = CMAES(5, rng=0)
    result = minimize(bowl, opt, 500, target=1e-3)
    assert result.message == 'target reached'
    assert result.cost <= 1e-3 and result.generations < 500

    seen = []
    result = minimize(bowl, PaperEA(5, rng=0, population_size=10), 50,
                      callback=lambda o: seen.append(o.generation) or o.generation >= 7)
    assert result.message == 'stopped by callback'
    assert seen == list(range(1, 8)) and result.generations == 7

    result = minimize(bowl, PaperEA(5, rng=0, population_size=10), 4)
    assert result.message == 'max_generations reached' and result.evaluations == 40

    with pytest.raises(ValueError, match=r'cost\(X\) must return shape \(10,\)'):
        minimize(lambda X: np.zeros((len(X), 1)), PaperEA(5, population_size=10), 1)


def test_make_optimizer_names_and_separable_default():
    assert isinstance(make_optimizer('paper', 3), PaperEA)
    assert make_optimizer('paper', 3).settings == PaperEA.DEFAULTS
    assert not make_optimizer('cmaes', SEPARABLE_ABOVE).separable
    long_genome = make_optimizer('cmaes', SEPARABLE_ABOVE + 1)
    assert long_genome.separable and long_genome.es.opts['CMA_diagonal'] is True
    assert not make_optimizer('cmaes', SEPARABLE_ABOVE + 1, separable=False).separable
    assert make_optimizer('sep-cmaes', 5).separable
    with pytest.raises(ValueError, match="unknown optimizer 'de'"):
        make_optimizer('de', 5)
    with pytest.raises(ValueError, match='sep-cmaes'):
        make_optimizer('sep-cmaes', 5, separable=False)


def test_history_entries_and_bound():
    opt = PaperEA(4, rng=0, population_size=6, history_maxlen=5)
    X = opt.ask()
    f = np.array([1.0, 2.0, np.inf, 3.0, np.nan, 6.0])
    opt.tell(X, f)
    h = opt.history[-1]
    assert h == {'generation': 1, 'best_cost': 1.0, 'min_cost': 1.0, 'mean_cost': 3.0,
                 'n_finite': 4, 'spread': opt.spread, 'evaluations': 6}
    run(opt, bowl, 10)
    assert len(opt.history) == 5
    assert [e['generation'] for e in opt.history] == list(range(7, 12))


def test_x0_centres_the_initial_population():
    x0 = np.linspace(5.0, 6.0, 30)
    X = PaperEA(30, x0=x0, rng=0, population_size=400, init_scale=0.5).ask()
    np.testing.assert_array_equal(X[0], x0)
    np.testing.assert_allclose(X.mean(axis=0), x0, atol=0.1)
    assert (X[1:] - x0).std() == pytest.approx(0.5, rel=0.05)
    X = PaperEA(30, x0=x0, rng=0, population_size=400, sigma=0.2).ask()
    assert (X[1:] - x0).std() == pytest.approx(0.2, rel=0.05)   # init_scale None: sigma
    with pytest.raises(ValueError, match='x0 contains NaN'):
        PaperEA(2, x0=[0.0, math.nan])


def test_validate_settings_fills_defaults_and_names_the_bad_setting():
    s = PaperEA.validate_settings(population_size=10)
    assert s['population_size'] == 10 and s['tournament_size'] == PaperEA.DEFAULTS[
        'tournament_size']
    with pytest.raises(ValueError, match='crossover_rate'):
        PaperEA.validate_settings(crossover_rate=1.5)
    with pytest.raises(ValueError, match='unknown setting'):
        CMAES.validate_settings(tournament=3)


@pytest.mark.parametrize('name', ['paper', 'cmaes'])
def test_seed_best_records_a_better_outside_solution_only(name):
    opt = make_optimizer(name, 4, rng=np.random.default_rng(0))
    x = opt.ask()
    opt.tell(x, np.arange(x.shape[0], dtype=float) + 1.0)
    assert opt.best_cost == 1.0
    opt.seed_best(np.full(4, 7.0), 0.5)
    assert opt.best_cost == 0.5 and np.all(opt.best_x == 7.0)
    opt.seed_best(np.zeros(4), 0.9)      # worse: ignored
    opt.seed_best(np.zeros(4), np.inf)   # diverged: ignored
    assert opt.best_cost == 0.5 and np.all(opt.best_x == 7.0)

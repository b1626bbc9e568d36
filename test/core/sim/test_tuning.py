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

"""PD gain tuning: the genome's reflection into the bounds and the paper's EA on eq. (10)."""

import numpy as np
import pytest
from rkgnn_ros.core.sim.plant import PlanarArm
from rkgnn_ros.core.sim.tracking import DEFAULT_BOUNDS, tracking_cost
from rkgnn_ros.core.sim.trajectories import paper_reference
from rkgnn_ros.core.sim.tuning import genome_to_gains, HISTORY_COLUMNS, paper_gains, tune_pd_gains

ARM = PlanarArm.paper()
REFERENCE = paper_reference(3)


@pytest.fixture
def rng():
    return np.random.default_rng(20260601)


# -- the genome ---------------------------------------------------------------------------

def test_genome_reflects_into_the_bounds(rng):
    lo = np.array([0.0] * 3 + [0.0] * 3)
    hi = np.array([100.0] * 3 + [50.0] * 3)
    u = rng.uniform(0.0, 1.0, (5, 6))
    np.testing.assert_allclose(genome_to_gains(u), lo + (hi - lo) * u)
    for shifted in (-u, 2.0 - u, u + 2.0, u - 4.0):            # mirrored at 0 and 1, period 2
        np.testing.assert_allclose(genome_to_gains(shifted), lo + (hi - lo) * u, atol=1e-12)
    wild = genome_to_gains(rng.normal(0.0, 50.0, (100, 6)))
    assert np.all((wild >= lo) & (wild <= hi))
    per_joint = (([1.0, 2.0, 3.0], 10.0), (0.0, [4.0, 5.0, 6.0]))
    np.testing.assert_allclose(genome_to_gains(np.ones(6), per_joint), [10, 10, 10, 4, 5, 6])
    np.testing.assert_allclose(genome_to_gains(np.zeros(6), per_joint), [1, 2, 3, 0, 0, 0])
    with pytest.raises(ValueError, match='bounds'):
        genome_to_gains(np.zeros(6), ((0.0, 100.0), (50.0, 0.0)))


# -- the tuning ---------------------------------------------------------------------------

def test_short_tuning_improves_and_is_seed_reproducible():
    kwargs = {'duration': 2.0, 'population_size': 20, 'generations': 10}
    result = tune_pd_gains(ARM, REFERENCE, seed=3, **kwargs)
    again = tune_pd_gains(ARM, REFERENCE, seed=3, **kwargs)
    other = tune_pd_gains(ARM, REFERENCE, seed=4, **kwargs)
    assert result.history.shape == (10, len(HISTORY_COLUMNS))
    assert result.evaluations == 200
    assert result.cost == result.history[-1, 0] < result.history[0, 0]
    assert np.all(np.diff(result.history[:, 0]) <= 0.0)
    np.testing.assert_array_equal(result.kp, again.kp)
    np.testing.assert_array_equal(result.kd, again.kd)
    np.testing.assert_array_equal(result.history, again.history)
    assert not np.array_equal(result.history, other.history)
    # the reported gains are inside the bounds and have the reported cost
    (kp_lo, kp_hi), (kd_lo, kd_hi) = DEFAULT_BOUNDS
    assert np.all((result.kp >= kp_lo) & (result.kp <= kp_hi))
    assert np.all((result.kd >= kd_lo) & (result.kd <= kd_hi))
    cost = tracking_cost(ARM, REFERENCE, np.concatenate([result.kp, result.kd])[None], 2.0)
    assert cost[0] == pytest.approx(result.cost, rel=1e-12)
    paper = tracking_cost(ARM, REFERENCE, paper_gains()[None], 2.0)
    assert result.paper_cost == pytest.approx(paper[0], rel=1e-12)
    assert result.wall_s > 0.0 and result.step == pytest.approx(0.01 / 21)


def test_callback_sees_every_generation_and_can_stop():
    seen = []

    def callback(entry):
        seen.append(entry)
        return entry['generation'] == 3

    result = tune_pd_gains(ARM, REFERENCE, duration=0.5, population_size=10, generations=10,
                           callback=callback)
    assert [e['generation'] for e in seen] == [1, 2, 3]
    assert result.history.shape == (3, 2) and result.evaluations == 30
    assert seen[-1]['best_cost'] == result.cost
    np.testing.assert_array_equal(seen[-1]['kp'], result.kp)


@pytest.mark.parametrize('kwargs, match', [
    ({'population_size': 1}, 'population_size'),
    ({'generations': 0}, 'generations'),
    ({'bounds': ((0.0, np.inf), (0.0, 50.0))}, 'bounds'),
    ({'bounds': (0.0, 100.0)}, 'bounds'),
])
def test_tuning_validates_its_settings(kwargs, match):
    with pytest.raises(ValueError, match=match):
        tune_pd_gains(ARM, REFERENCE, duration=0.5, **kwargs)

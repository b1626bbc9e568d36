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

"""The prediction record's inputs (rkgnn_ros.core.scoring), without a node."""

import numpy as np
import pytest
from rkgnn_ros.core.scoring import PredictionRecord


def _stream(seed, size=6000, n=3):
    """Return times at 1 kHz (with repeats, steps back), θ (with NaN rows) and θd."""
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.choice([0.001] * 6 + [0.0, -0.002], size=size)) + 5.0
    theta = np.sin(t[:, None] * np.arange(1, n + 1)) + 0.01 * rng.standard_normal((size, n))
    theta[rng.random(size) < 0.01, rng.integers(n)] = np.nan
    theta_d = theta + 0.1
    return t, theta, theta_d


def _predictions(record, t):
    offsets = np.linspace(0.0, 0.5, 51)
    for t0 in np.arange(t.min() + 0.1, t.max() - 0.6, 0.05):
        theta = np.sin((t0 + offsets)[:, None] * np.arange(1, 4)) + 0.02
        record.add_prediction(t0, offsets, theta, follow=theta + 0.1)


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_states_and_commands_in_bulk_are_the_same_record_as_one_by_one(seed):
    t, theta, theta_d = _stream(seed)
    one = PredictionRecord(3, horizons=(0.1, 0.5), window=1.0)
    bulk = PredictionRecord(3, horizons=(0.1, 0.5), window=1.0)
    for chunk in np.array_split(np.arange(t.size), 37):
        for k in chunk:
            one.add_reference(t[k], theta_d[k])
            one.add_state(t[k], theta[k])
        bulk.add_references(t[chunk], theta_d[chunk])
        bulk.add_states(t[chunk], theta[chunk])
    assert one.rejected == bulk.rejected
    assert one.rejected['out_of_order'] > 0 and one.rejected['non_finite'] > 0
    np.testing.assert_array_equal(one.theta_range, bulk.theta_range)
    _predictions(one, t)
    _predictions(bulk, t)
    assert one.scores() == bulk.scores()
    assert one.scores()[0.5]['count'] > 0


def test_a_wrong_width_is_counted_and_nothing_taken():
    record = PredictionRecord(3)
    record.add_states([1.0, 1.1], np.zeros((2, 2)))
    assert record.rejected['wrong_shape'] == 2
    assert np.all(np.isnan(record.theta_range))


def test_scores_are_computed_again_after_new_data_at_most_every_rescore_every():
    t, theta, theta_d = _stream(3)
    fresh = PredictionRecord(3, horizons=(0.1, 0.5), window=1.0)
    lazy = PredictionRecord(3, horizons=(0.1, 0.5), window=1.0, rescore_every=0.2)
    half = t.size // 2
    for record in (fresh, lazy):
        record.add_references(t, theta_d)
        record.add_states(t[:half], theta[:half])
        _predictions(record, t[:half])
    first = lazy.scores()
    assert first == fresh.scores()
    # new states within 0.2 s of the last scoring: the lazy record answers as before
    kept = lazy._states.t[-1]
    soon = (t > kept) & (t < kept + 0.15)
    fresh.add_states(t[soon], theta[soon])
    lazy.add_states(t[soon], theta[soon])
    assert lazy.scores() == first
    assert fresh.scores() != first
    # once the states are 0.2 s on, the same as computing every time
    fresh.add_states(t, theta)
    lazy.add_states(t, theta)
    assert lazy.scores() == fresh.scores()


def test_rescore_every_must_be_a_finite_non_negative_time():
    for bad in (-0.1, float('nan'), float('inf')):
        with pytest.raises(ValueError, match='rescore_every'):
            PredictionRecord(3, rescore_every=bad)

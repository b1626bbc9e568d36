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

"""The band a prediction must stay in (rkgnn_ros.core.band) and the withdrawal it drives."""

import numpy as np
from rkgnn_ros.core.band import BAND_FACTOR, band_width, leaves_band
from rkgnn_ros.core.selfcheck import SelfCheck

OFFSETS = np.arange(0.0, 2.001, 0.01)
HORIZONS = (0.5, 1.0, 2.0)


def _table(values):
    return {h: np.asarray(v, dtype=float) for h, v in zip(HORIZONS, values)}


def test_the_width_is_the_recent_errors_at_each_offset_held_past_the_horizons():
    follow = _table([[0.1, 0.2], [0.1, 0.2], [0.3, 0.2]])
    model = _table([[0.0, 0.01], [0.02, 0.01], [0.02, 0.01]])
    width = band_width(OFFSETS, HORIZONS, follow, model, [1e-4, 1e-4])
    assert width.shape == (OFFSETS.size, 2)
    np.testing.assert_allclose(width[0], BAND_FACTOR * np.array([0.1 + 1e-4, 0.21 + 1e-4]))
    np.testing.assert_allclose(width[-1], BAND_FACTOR * np.array([0.32 + 1e-4, 0.21 + 1e-4]))
    k = np.searchsorted(OFFSETS, 1.5 - 1e-9)
    np.testing.assert_allclose(width[k, 0], BAND_FACTOR * (0.2 + 0.02 + 1e-4))
    # nothing to judge the model by before it has a score; following unscored counts 0
    unscored = _table([[np.nan] * 2] * 3)
    assert band_width(OFFSETS, HORIZONS, follow, unscored, [0.0, 0.0]) is None
    zeros = _table([[0.0] * 2] * 3)
    np.testing.assert_allclose(band_width(OFFSETS, HORIZONS, unscored, model, [0.0, 0.0]),
                               band_width(OFFSETS, HORIZONS, zeros, model, [0.0, 0.0]))


def test_an_arm_on_its_way_to_a_step_stays_inside_and_a_diverging_rollout_leaves():
    # the plan steps from 0 to 1 rad at the start; the arm follows with a 0.2 s lag and
    # overshoots by 17 % of the step (a servo's step response); errors of 0.02 rad lately
    theta_d = np.ones((OFFSETS.size, 1))
    lag = 1.0 - np.exp(-OFFSETS / 0.2) * np.cos(8.0 * OFFSETS)
    arm = lag[:, None]
    assert 1.15 < arm.max() < 1.2
    width = np.full((OFFSETS.size, 1), BAND_FACTOR * 0.02)
    assert leaves_band(OFFSETS, arm, [0.0], theta_d, width) is None
    # the model predicts the arm going the other way, growing (a divergence)
    diverging = arm - 1e-3 * np.expm1(OFFSETS / 0.25)[:, None]
    excursion = leaves_band(OFFSETS, diverging, [0.0], theta_d, width)
    assert excursion is not None and excursion.joint == 0
    assert excursion.outside > excursion.width and excursion.offset <= 2.0
    # an exploding rollout (inf) leaves, whatever the width
    assert leaves_band(OFFSETS, np.full_like(arm, np.inf), [0.0], theta_d, width * 1e9)


def _feed(check, start, seconds, model, omega=1.5):
    decisions = []
    for k in range(int(start * 100), int((start + seconds) * 100)):
        t = k / 100.0
        check.add_state(t, [np.sin(omega * (t - 0.1))])
        check.add_reference(t, [np.sin(omega * t)])
        if k % 10 == 0:
            decisions.append(check.decide())
            check.add_prediction(t, OFFSETS, model(t), decisions[-1].source)
    return decisions


def test_a_withdrawn_model_is_published_again_only_once_its_predictions_since_are_scored():
    def exact(t):
        return np.sin(1.5 * (t + OFFSETS - 0.1))[:, None]

    check = SelfCheck(1, joint_names=('j1',))
    assert _feed(check, 0.0, 15.0, exact)[-1].source == 'model'
    t = 15.0
    plan = np.sin(1.5 * (t + OFFSETS))[:, None]
    theta0 = np.sin(1.5 * (t - 0.1))
    assert check.excursion(OFFSETS, exact(t), [theta0], plan) is None     # as lately
    wild = exact(t) + 1e-3 * np.expm1(OFFSETS / 0.2)[:, None]
    excursion = check.excursion(OFFSETS, wild, [theta0], plan)
    assert excursion is not None and excursion.offset < 2.0
    assert check.withdraw(t, 'it left') and not check.withdraw(t + 0.1, 'it diverged')
    decisions = _feed(check, 15.0, 6.0, exact)
    held = [d for d in decisions if d.source != 'model']
    assert held and 'withdrawn' in held[0].reason and 'it diverged' in held[0].reason
    # held for the longest horizon + the short span (2 + 2 s), then judged on its scores
    assert 3.9 <= len(held) * 0.1 <= 4.2 and decisions[-1].source == 'model'


def test_a_model_scored_at_its_shortest_horizon_only_is_not_judged_by_the_band():
    # 0.8 s of predictions: a few scored 0.5 s ahead, none 1 or 2 s ahead; what the error
    # will be 2 s ahead is not known yet, so no band (the model is not published either)
    def exact(t):
        return np.sin(1.5 * (t + OFFSETS - 0.1))[:, None]

    check = SelfCheck(1, joint_names=('j1',))
    _feed(check, 0.0, 1.0, exact)
    assert check.scores()[0.5]['count'] > 0 and not check.scores()[2.0]
    t = 1.0
    wild = exact(t) + 1e-3 * np.expm1(OFFSETS / 0.2)[:, None]
    plan = np.sin(1.5 * (t + OFFSETS))[:, None]
    assert check.excursion(OFFSETS, wild, [np.sin(1.5 * (t - 0.1))], plan) is None

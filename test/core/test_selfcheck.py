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

"""The self-check: predictions scored against the baselines, and what is fit to publish."""

import numpy as np
import pytest
from rkgnn_ros.core.selfcheck import baseline, rollout_spread, SelfCheck

N = 2
RATE = 100.0
OFFSETS = np.arange(0.0, 2.01, 0.05)


def motion(t):
    """Return the arm's true θ (..., 2): it follows θd with a 0.1 s delay."""
    t = np.asarray(t, dtype=float)[..., None]
    return np.concatenate([np.sin(1.5 * (t - 0.1)), 0.5 * np.cos(0.9 * (t - 0.1))], axis=-1)


def desired(t):
    """Return the commanded θd (..., 2)."""
    t = np.asarray(t, dtype=float)[..., None]
    return np.concatenate([np.sin(1.5 * t), 0.5 * np.cos(0.9 * t)], axis=-1)


def run(check, seconds, model, start=0.0, predict_every=10):
    """Feed states and commands at 100 Hz and a prediction every 0.1 s; return decisions."""
    decisions = []
    for k in range(int(round(start * RATE)), int(round((start + seconds) * RATE))):
        t = k / RATE
        check.add_state(t, motion(t))
        check.add_reference(t, desired(t))
        if k % predict_every == 0:
            decision = check.decide()
            decisions.append(decision)
            check.add_prediction(t, OFFSETS, model(t), decision.source)
    return decisions


def perfect(t):
    return motion(t + OFFSETS)


def broken(t):
    return motion(t + OFFSETS) + np.array([0.3, -0.2])


def test_a_perfect_model_earns_publication_and_scores_zero():
    check = SelfCheck(N, min_scored=5)
    decisions = run(check, 15.0, perfect)
    assert decisions[0].source != 'model' and not decisions[0].scored
    assert 'not been scored yet' in decisions[0].reason
    assert decisions[-1].source == 'model' and decisions[-1].scored
    scores = check.scores()
    for h in (0.5, 1.0, 2.0):
        assert scores[h]['model'] < 1e-12
        assert scores[h]['count'] >= 90                 # 10 s window, a prediction per 0.1 s
        assert scores[h]['hold_last'] > scores[h]['follow_reference'] > 0.0
        assert scores[h]['published'] < 1e-12


def test_a_broken_model_is_replaced_by_the_better_baseline_with_the_reason():
    check = SelfCheck(N)
    decisions = run(check, 15.0, broken)
    last = decisions[-1]
    assert last.source == 'follow_reference' and last.is_baseline and last.scored
    assert "the model's" in last.reason and 'follow_reference' in last.reason
    scores = check.scores()
    # what was published is the baseline's error, not the model's
    assert scores[2.0]['published'] == pytest.approx(scores[2.0]['follow_reference'], rel=1e-9)
    assert scores[2.0]['model'] > 3 * scores[2.0]['follow_reference']


def test_the_model_must_earn_publication_and_loses_it_at_once():
    check = SelfCheck(N, margin=0.2)
    run(check, 12.0, broken)
    assert check.decide().source == 'follow_reference'
    lag = 0.1       # the follow-reference baseline's error: the arm's 0.1 s delay

    def delayed(factor):   # the model's error: that delay times ``factor``
        return lambda t: motion(t + OFFSETS - factor * lag)

    decisions = run(check, 12.0, delayed(0.9), start=12.0)   # 10 % better: not enough
    ratio = check.scores()[2.0]['model'] / check.scores()[2.0]['follow_reference']
    assert 0.85 < ratio < 0.95
    assert decisions[-1].source == 'follow_reference' and 'must be 20% better' in \
        decisions[-1].reason
    decisions = run(check, 12.0, perfect, start=24.0)
    assert decisions[-1].source == 'model'
    assert sum('at least 20% better' in d.reason for d in decisions) == 1   # one switch
    # worse than following the reference: set aside within the short span
    decisions = run(check, 6.0, delayed(1.3), start=36.0)
    switch = next(i for i, d in enumerate(decisions) if d.source != 'model')
    assert switch * 0.1 <= 2.0 + 1.0 and 'last 2 s' in decisions[switch].reason


def test_without_commands_hold_last_is_the_only_baseline():
    check = SelfCheck(N)
    for k in range(1500):                                   # no plan, no command
        t = k / RATE
        check.add_state(t, motion(t))
        if k % 10 == 0:
            wrong = motion(t + OFFSETS) + 2.0               # worse than standing still
            check.add_prediction(t, OFFSETS, wrong, check.decide(publishable=()).source)
    decision = check.decide(publishable=())
    assert decision.source == 'hold_last'
    assert 'follow_reference' not in check.scores()[1.0]
    # a plan, but no command recorded yet to score it: following it is preferred
    assert SelfCheck(N).decide().source == 'follow_reference'


def test_uncertainty_is_the_recent_error_per_horizon():
    check = SelfCheck(N)
    run(check, 15.0, broken)
    rmse = check.rmse('model')
    sigma = check.uncertainty([0.0, 0.5, 0.75, 2.0, 3.0], 'model')
    np.testing.assert_allclose(sigma[0], 0.0)
    np.testing.assert_allclose(sigma[1], rmse[0.5])
    np.testing.assert_allclose(sigma[2], 0.5 * (rmse[0.5] + rmse[1.0]))
    np.testing.assert_allclose(sigma[3], rmse[2.0])
    assert np.all(sigma[4] >= sigma[3])
    np.testing.assert_allclose(rmse[2.0], [0.3, 0.2], rtol=1e-9)
    assert np.all(np.isnan(SelfCheck(N).uncertainty([1.0])))


def test_bad_input_is_counted_and_memory_stays_bounded():
    check = SelfCheck(N, window=2.0)
    check.add_state(1.0, [0.0, 0.0])
    check.add_state(0.5, [0.0, 0.0])                    # older than the last
    check.add_state(2.0, [np.nan, 0.0])
    check.add_state(3.0, [0.0, 0.0, 0.0])
    check.add_prediction(1.0, OFFSETS, np.full((OFFSETS.size, N), np.inf))
    assert check.rejected == {'non_finite': 2, 'out_of_order': 1, 'wrong_shape': 1}
    with pytest.raises(ValueError, match='source'):
        check.add_prediction(1.0, OFFSETS, np.zeros((OFFSETS.size, N)), 'guess')
    run(check, 30.0, perfect, start=2.0)
    assert len(check._states) <= (2.0 + 2.0 + 1.0) * RATE + 2
    assert len(check._predictions) <= (2.0 + 2.0 + 1.0) * 10 + 2


def test_a_new_plan_replaces_the_tail_of_the_old_one():
    check = SelfCheck(1)
    check.add_reference(np.arange(0.0, 3.0, 0.5), np.zeros((6, 1)))
    check.add_reference(np.arange(1.0, 4.0, 0.5), np.ones((6, 1)))
    values = check._reference.interp(np.array([0.5, 1.0, 3.5]))
    np.testing.assert_array_equal(values[:, 0], [0.0, 1.0, 1.0])


def test_rollout_spread_and_baselines():
    rollouts = np.stack([np.full((4, 2), v) for v in (1.0, 2.0, 3.0, np.nan)])
    np.testing.assert_allclose(rollout_spread(rollouts), 1.0)
    assert np.all(np.isnan(rollout_spread(rollouts[2:])))
    theta, theta_dot = baseline('hold_last', [0.0, 1.0], [0.3, 0.4])
    np.testing.assert_array_equal(theta, [[0.3, 0.4], [0.3, 0.4]])
    assert np.all(theta_dot == 0.0)
    plan = np.arange(4.0).reshape(2, 2)
    assert baseline('follow_reference', [0.0, 1.0], None, plan, plan)[0] is not None
    with pytest.raises(ValueError, match='theta_d'):
        baseline('follow_reference', [0.0], [0.0, 0.0])


def test_a_candidate_replaces_the_model_only_when_it_scored_better_on_the_same_targets():
    check = SelfCheck(N)
    worse = (lambda t: motion(t + OFFSETS) + 0.05)
    for k in range(800):                     # the model in use: 0.05 rad off everywhere
        t = k / RATE
        check.add_state(t, motion(t))
        check.add_reference(t, desired(t))
        if k % 10 == 0:
            check.add_prediction(t, OFFSETS, worse(t), check.decide().source)
    assert check.trial() is None             # no candidate yet
    verdicts = []
    for k in range(800, 1400):               # a perfect candidate beside it
        t = k / RATE
        check.add_state(t, motion(t))
        check.add_reference(t, desired(t))
        if k % 10 == 0:
            check.add_prediction(t, OFFSETS, worse(t), check.decide().source,
                                 candidate=perfect(t))
            verdict = check.trial()
            if verdict is not None:
                verdicts.append(verdict)
                break
    verdict, = verdicts
    assert verdict.better and verdict.candidate < 1e-12 < verdict.model
    assert 1.9 <= t - 8.0 <= 3.0                # decided once 5 predictions at 2 s were scored
    before = check.scores()[2.0]['published']
    check.promote()
    scores = check.scores()
    assert scores[2.0]['model'] < 1e-12 and 'candidate' not in scores[2.0]
    assert scores[2.0]['published'] == pytest.approx(before)   # what was published stays
    # a broken candidate is judged worse and dropped; the model stays
    for k in range(1400, 1800):
        t = k / RATE
        check.add_state(t, motion(t))
        check.add_reference(t, desired(t))
        if k % 10 == 0:
            check.add_prediction(t, OFFSETS, perfect(t), 'model', candidate=broken(t))
    verdict = check.trial()
    assert verdict is not None and not verdict.better
    check.discard_candidate()
    assert 'candidate' not in check.scores()[2.0] and check.trial() is None


def test_only_publishable_baselines_are_chosen_and_horizons_not_reached_are_not_required():
    check = SelfCheck(N)
    short = OFFSETS[OFFSETS <= 1.0 + 1e-9]      # predictions that end at 1 s (the plan's end)
    for k in range(1500):
        t = k / RATE
        check.add_state(t, motion(t))
        check.add_reference(t, desired(t))
        if k % 10 == 0:
            decision = check.decide(publishable=())
            check.add_prediction(t, short, motion(t + short) + 2.0, decision.source)
    decision = check.decide(publishable=())
    assert decision.scored and decision.source == 'hold_last'   # the plan is not publishable
    assert "the model's" in decision.reason and 'for hold_last' in decision.reason
    assert check.scores()[2.0] == {} or check.scores()[2.0].get('count', 0) == 0
    assert check.decide().source == 'follow_reference'


def test_the_error_integral_is_what_a_servo_integrates():
    check = SelfCheck(1)
    for k in range(301):
        t = k / RATE
        check.add_state(t, [0.0])
        check.add_reference(t, [2.0 * t])            # e = θd − θ = 2 t
    np.testing.assert_allclose(check.error_integral(1.0, 2.5), [2.5 ** 2 - 1.0], rtol=1e-9)
    np.testing.assert_allclose(check.error_integral(1.005, 1.005), [0.0])
    assert check.error_integral(-1.0, 2.0) is None   # older than what is recorded


def test_following_is_scored_as_the_plan_said_and_gaps_are_not_scored():
    check = SelfCheck(N)
    late = 0.3   # the plan known at each start is 0.3 s late (a stale plan)
    for k in range(1200):
        t = k / RATE
        check.add_state(t, motion(t))
        check.add_reference(t, desired(t))
        if k % 10 == 0:
            check.add_prediction(t, OFFSETS, motion(t + OFFSETS), 'follow_reference',
                                 follow=desired(t + OFFSETS - late))
    stale = check.scores()[2.0]['follow_reference']
    fresh = SelfCheck(N)
    run(fresh, 12.0, perfect)
    assert stale > 2 * fresh.scores()[2.0]['follow_reference']   # scored as published
    # a 1 s gap in the states (the arm's driver stalled): no prediction over it is scored
    check = SelfCheck(N)
    run(check, 6.0, perfect)
    run(check, 6.0, perfect, start=7.0)
    before = check.scores()[2.0]['count']
    t0 = np.array(check._predictions.t)
    spanning = np.sum((t0 < 7.0) & (t0 + 2.0 > 6.0 - 0.01) & (t0 + 2.0 >= 13.0 - 10.0))
    assert spanning > 0
    assert before == np.sum((t0 + 2.0 <= 12.99) & (t0 + 2.0 >= 2.99)) - spanning


# ------------------------------------------------------------------ per joint (issue 31)

SEVEN = tuple(f'j{k}' for k in range(1, 8))
AMPLITUDE = np.linspace(0.6, 1.2, 7)
OMEGA = np.linspace(0.8, 1.6, 7)


def motion7(t, idle=()):
    """Return the 7-joint arm's θ (..., 7): θd 0.1 s late; ``idle`` joints stay at 0.2."""
    t = np.asarray(t, dtype=float)[..., None]
    theta = AMPLITUDE * np.sin(OMEGA * (t - 0.1))
    theta[..., list(idle)] = 0.2
    return theta


def desired7(t, idle=()):
    """Return the 7-joint arm's θd (..., 7)."""
    t = np.asarray(t, dtype=float)[..., None]
    theta_d = AMPLITUDE * np.sin(OMEGA * t)
    theta_d[..., list(idle)] = 0.2
    return theta_d


def run7(check, seconds, model, start=0.0, idle=(), noise=0.0, candidate=None, seed=0):
    """Feed 7 joints at 100 Hz (θ with white ``noise``, rad) and a prediction every 0.1 s."""
    rng = np.random.default_rng(seed)
    decisions = []
    for k in range(int(round(start * RATE)), int(round((start + seconds) * RATE))):
        t = k / RATE
        check.add_state(t, motion7(t, idle) + noise * rng.standard_normal(7))
        check.add_reference(t, desired7(t, idle))
        if k % 10 == 0:
            decision = check.decide()
            decisions.append(decision)
            check.add_prediction(t, OFFSETS, model(t), decision.source,
                                 candidate=None if candidate is None else candidate(t))
    return decisions


def test_a_model_broken_on_one_joint_of_seven_is_not_published():
    def one_broken(t):   # exact on six joints, 0.3 rad off on the seventh
        return motion7(t + OFFSETS) + 0.3 * (np.arange(7) == 6)

    check = SelfCheck(7, joint_names=SEVEN)
    decisions = run7(check, 15.0, one_broken)
    scores, joints = check.scores(), check.joint_scores()
    # averaged over the joints, it is far better than following the reference ...
    assert scores[2.0]['model'] < 0.5 * scores[2.0]['follow_reference']
    # ... but on j7 it is worse: it is never published, and the reason names the joint
    assert joints[2.0]['model'][6] > 1.5 * joints[2.0]['follow_reference'][6]
    assert np.all(joints[2.0]['model'][:6] < 1e-12)
    assert all(d.source == 'follow_reference' for d in decisions)
    last = decisions[-1]
    assert last.scored and last.reason.startswith('on j7, ') and 'for follow_reference' in \
        last.reason
    # the same model without the broken joint is published
    check = SelfCheck(7, joint_names=SEVEN)
    assert run7(check, 15.0, lambda t: motion7(t + OFFSETS))[-1].source == 'model'


def test_a_joint_where_both_are_at_the_noise_floor_does_not_hold_the_model_back():
    # j7 stays still under 1e-4 rad of encoder noise: following the reference (θd is where
    # it is) and the exact model both score the noise there; no predictor can be better
    sigma = 1e-4
    check = SelfCheck(7, joint_names=SEVEN)
    decisions = run7(check, 15.0, lambda t: motion7(t + OFFSETS, idle=(6,)), idle=(6,),
                     noise=sigma)
    joints = check.joint_scores()[2.0]
    assert joints['model'][6] > 0.8 * joints['follow_reference'][6]   # not 20 % better
    floor = check.noise_floor()
    assert floor.shape == (7,)
    span = check.theta_range
    np.testing.assert_allclose(floor * span, 2.0 * sigma, rtol=0.2)  # twice the noise (rad)
    assert joints['model'][6] <= floor[6] and joints['follow_reference'][6] <= floor[6]
    assert decisions[-1].source == 'model'
    # a model that drifts 1 mrad (10 × the noise) on that joint is above the floor: refused
    check = SelfCheck(7, joint_names=SEVEN)
    drift = run7(check, 15.0, lambda t: motion7(t + OFFSETS, idle=(6,)) + 1e-3 * OFFSETS[:, None]
                 * (np.arange(7) == 6), idle=(6,), noise=sigma)
    assert drift[-1].source == 'follow_reference' and drift[-1].reason.startswith('on j7, ')


def test_a_candidate_better_on_average_but_broken_on_one_joint_does_not_earn_the_swap():
    def in_use(t):       # 0.05 rad off on every joint
        return motion7(t + OFFSETS) + 0.05

    def candidate(t):    # exact on six joints, 0.2 rad off on j7: better on average
        return motion7(t + OFFSETS) + 0.2 * (np.arange(7) == 6)

    check = SelfCheck(7, joint_names=SEVEN)
    run7(check, 8.0, in_use)
    run7(check, 6.0, in_use, start=8.0, candidate=candidate)
    verdict = check.trial()
    assert verdict is not None and verdict.candidate < verdict.model   # the mean says yes
    assert not verdict.better and 'j7' in verdict.why


def test_after_a_change_a_candidate_is_scored_on_predictions_made_again_since_it():
    check = SelfCheck(N, horizons=(0.5, 1.0, 2.0))
    run(check, 12.0, broken)
    assert check.replay_from() is None                # no change: nothing made again
    check.dynamics_changed(11.5)
    assert check.replay_from() == 11.5
    run(check, 3.0, broken, start=12.0)
    # the candidate's predictions from the starts since the change, as a replay makes them
    starts = np.arange(1150, 1500, 10) / RATE        # the starts, as run() makes them
    assert all(check.set_candidate(t0, OFFSETS, perfect(t0)) for t0 in starts)
    assert not check.set_candidate(11.55, OFFSETS, perfect(11.55))   # no prediction there
    verdict = check.trial()
    assert verdict is not None and verdict.better and verdict.candidate < 1e-12
    check.promote()
    assert check.decide().source == 'model'           # 5 scored 2 s ahead are enough now
    run(check, 4.0, perfect, start=15.0)
    assert check.decide().source == 'model' and check.replay_from() == 11.5
    run(check, 3.0, perfect, start=19.0)        # a window (10 s) of states since the change
    assert check.decide().source == 'model' and check.replay_from() is None

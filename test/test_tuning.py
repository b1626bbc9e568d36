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
PD gain tuning: the eq. (10) cost against simulate(), kernel against numpy, divergence, EA.

The digital servo's cost (tuning_study) is held to adaptive integration between its instants.

The reference errors come from :func:`rkgnn_ros.core.sim.simulate.simulate` (LSODA at rtol
1e-9), independent of the fixed-step kernel under test.
"""

import numpy as np
import pytest
from rkgnn_ros.core.sim.plant import PDController, PlanarArm, RK4_REAL_STABILITY_LIMIT
from rkgnn_ros.core.sim.simulate import simulate
from rkgnn_ros.core.sim.trajectories import paper_reference
from rkgnn_ros.core.sim.tuning import (DEFAULT_BOUNDS, genome_to_gains, HISTORY_COLUMNS,
                                       paper_gains, STEP_SAFETY, tracking_cost, TrackingProblem,
                                       tune_pd_gains, tuning_step)
from rkgnn_ros.core.sim.tuning_study import SampledTrackingProblem

ARM = PlanarArm.paper()
REFERENCE = paper_reference(3)
CORNER = np.array([100.0, 100.0, 100.0, 50.0, 50.0, 50.0])     # the largest default gains


@pytest.fixture
def rng():
    return np.random.default_rng(20260601)


@pytest.fixture(scope='module')
def short_problem():
    return TrackingProblem(ARM, REFERENCE, 0.5)


def simulated_error(gains, duration):
    """Return eq. (10) from an accurate adaptive simulation with the given [Kp, Kd]."""
    data = simulate(ARM, PDController(gains[:3], gains[3:]), REFERENCE, duration, rate=100.0)
    err = (np.linalg.norm(data.theta_d - data.theta, axis=1)
           + np.linalg.norm(data.theta_d_dot - data.theta_dot, axis=1))
    return err[1:].mean()


# -- the cost -----------------------------------------------------------------------------

def test_paper_gains_cost_equals_simulate_error(rng):
    gains = np.array([paper_gains(), genome_to_gains(rng.uniform(0.0, 1.0, 6))])
    cost = tracking_cost(ARM, REFERENCE, gains, 5.0)
    assert cost.shape == (2,)
    expected = [simulated_error(g, 5.0) for g in gains]
    np.testing.assert_allclose(cost, expected, rtol=1e-6)


def test_zero_gains_cost_much_more_than_paper_gains():
    cost = tracking_cost(ARM, REFERENCE, np.array([paper_gains(), np.zeros(6)]), 10.0)
    assert np.all(np.isfinite(cost))
    assert cost[1] > 3.0 * cost[0]


def test_compiled_kernel_equals_numpy_reference(short_problem, rng):
    gains = genome_to_gains(rng.uniform(-0.5, 1.5, (8, 6)))
    gains[0] = paper_gains()
    gains[1] = [30.0, 30.0, 30.0, -20.0, -20.0, -20.0]                  # diverges
    compiled = short_problem.cost(gains)
    numpy_cost = short_problem.cost_numpy(gains)
    assert np.isposinf(compiled[1]) and np.isposinf(numpy_cost[1])
    np.testing.assert_allclose(compiled, numpy_cost, rtol=1e-10)


def test_diverging_and_unstable_candidates_cost_inf_never_nan(short_problem):
    gains = np.array([
        paper_gains(),
        [30.0, 30.0, 30.0, -20.0, -20.0, -20.0],        # negative damping: speed runs away
        [-500.0, 30.0, 30.0, 5.0, 5.0, 5.0],             # repelled from the reference
        [100.0, 100.0, 100.0, 50.0, 50.0, 500.0],        # too stiff for the step
        [1e6, 1e6, 1e6, 1e5, 1e5, 1e5],                  # far too stiff: overflows
    ])
    for cost in (short_problem.cost(gains), short_problem.cost_numpy(gains)):
        assert np.isfinite(cost[0])
        assert np.all(np.isposinf(cost[1:])), cost
        assert not np.any(np.isnan(cost))
    np.testing.assert_array_equal(short_problem.unstable(gains),
                                  [False, False, False, True, True])


def test_an_unstable_step_costs_inf_however_it_is_caught():
    # 10 ms steps for the stiffest gains: caught by the stability check and by the kernel
    problem = TrackingProblem(ARM, REFERENCE, 1.0, step=0.01)
    assert problem.substeps == 1
    gains = np.array([CORNER, [5.0, 5.0, 5.0, 0.5, 0.5, 0.2]])
    np.testing.assert_array_equal(problem.unstable(gains), [True, False])
    cost = problem.cost(gains)
    assert np.isposinf(cost[0]) and np.isfinite(cost[1])


def test_step_is_stable_for_every_gain_in_the_bounds():
    h = tuning_step(ARM, REFERENCE, 10.0)
    problem = TrackingProblem(ARM, REFERENCE, 10.0)
    assert problem.h <= h and problem.substeps == int(np.ceil(0.01 / h - 1e-9))
    # the stiffest configuration is covered, not only the reference's states
    stretched = np.array([-np.pi / 2, 0.0, 0.0])
    stiffness = ARM.closed_loop_stiffness(stretched, np.zeros(3), CORNER[:3], CORNER[3:])
    assert h * stiffness <= STEP_SAFETY * RK4_REAL_STABILITY_LIMIT * (1.0 + 1e-6)
    theta_d, theta_d_dot = REFERENCE.evaluate(np.linspace(0.0, 10.0, 200))
    assert h < ARM.stable_step(CORNER[:3], CORNER[3:], theta_d, theta_d_dot, safety=1.0)
    corners = np.array([[kp] * 3 + [kd] * 3 for kp in (0.0, 100.0) for kd in (0.0, 50.0)])
    assert not np.any(problem.unstable(corners))


def test_problem_validates_its_input(short_problem):
    with pytest.raises(ValueError, match='shape'):
        short_problem.cost(np.zeros(6))
    with pytest.raises(ValueError, match='finite'):
        short_problem.cost(np.full((1, 6), np.nan))
    with pytest.raises(ValueError, match='duration'):
        TrackingProblem(ARM, REFERENCE, 0.0)
    with pytest.raises(ValueError, match='joints'):
        TrackingProblem(ARM, paper_reference(2), 1.0)
    assert short_problem.cost(np.empty((0, 6))).shape == (0,)


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


# -- the digital servo (tuning_study) -------------------------------------------------------

def held_torque_error(gains, duration, servo_rate, limit):
    """Eq. (10) of the sampled, held, clipped PD from adaptive integration between instants."""
    from scipy.integrate import solve_ivp
    kp, kd = gains[:3], gains[3:]
    t_servo = np.arange(int(round(duration * servo_rate)) + 1) / servo_rate
    theta_d, theta_d_dot = REFERENCE.evaluate(t_servo)
    x = np.concatenate([theta_d[0], theta_d_dot[0]])
    states = [x]
    for k in range(t_servo.size - 1):
        tau = np.clip(kp * (theta_d[k] - x[:3]) + kd * (theta_d_dot[k] - x[3:]), -limit, limit)
        sol = solve_ivp(lambda t, y: ARM.dynamics(y, tau), (t_servo[k], t_servo[k + 1]), x,
                        method='LSODA', rtol=1e-10, atol=1e-12)
        x = sol.y[:, -1]
        states.append(x)
    states = np.array(states)[::int(round(servo_rate / 100.0))]      # the 100 Hz samples
    qd, qd_dot = REFERENCE.evaluate(np.arange(states.shape[0]) / 100.0)
    err = (np.linalg.norm(qd - states[:, :3], axis=1)
           + np.linalg.norm(qd_dot - states[:, 3:], axis=1))
    return err[1:].mean()


def test_sampled_cost_equals_an_adaptive_held_torque_rollout():
    limit = np.array([14.0, 8.0, 1.5])        # below the loop's peaks: the clip acts
    gains = np.array([paper_gains(), [60.0, 50.0, 30.0, 20.0, 5.0, 1.0]])
    problem = SampledTrackingProblem(ARM, REFERENCE, 1.0, 200.0, limit)
    expected = [held_torque_error(g, 1.0, 200.0, limit) for g in gains]
    np.testing.assert_allclose(problem.cost(gains), expected, rtol=1e-7)


@pytest.mark.parametrize('limit, duration', [(None, 0.5), ([10.0, 8.0, 2.0], 0.1)])
def test_sampled_kernel_equals_numpy_reference(rng, limit, duration):
    # a saturated loop chatters between the limits and amplifies rounding differences (by
    # about e every 20 ms): it is compared over a shorter span
    problem = SampledTrackingProblem(ARM, REFERENCE, duration, 200.0, limit)
    gains = np.vstack([paper_gains(), genome_to_gains(rng.uniform(0.0, 1.0, (4, 6))),
                       CORNER])
    compiled, reference = problem.cost(gains), problem.cost_numpy(gains)
    # at 200 Hz the corner diverges within 0.5 s without a limit
    assert np.isinf(compiled[-1]) == np.isinf(reference[-1]) == (limit is None)
    np.testing.assert_allclose(compiled, reference, rtol=1e-11)


def test_fast_servo_approaches_the_continuous_pd():
    gains = np.array([paper_gains(), [60.0, 50.0, 30.0, 20.0, 5.0, 1.0]])
    fast = SampledTrackingProblem(ARM, REFERENCE, 2.0, 5000.0).cost(gains)
    continuous = TrackingProblem(ARM, REFERENCE, 2.0).cost(gains)
    np.testing.assert_allclose(fast, continuous, rtol=2e-3)
    assert not np.allclose(fast, continuous, rtol=1e-6)     # but it is a different loop


def test_slow_servo_destabilises_gains_a_fast_one_holds():
    gains = paper_gains()[None]
    assert np.isinf(SampledTrackingProblem(ARM, REFERENCE, 1.0, 100.0).cost(gains)[0])
    assert np.isfinite(SampledTrackingProblem(ARM, REFERENCE, 1.0, 1000.0).cost(gains)[0])


def test_a_limit_above_every_torque_changes_nothing():
    gains = np.array([paper_gains()])
    free = SampledTrackingProblem(ARM, REFERENCE, 1.0, 500.0).cost(gains)
    loose = SampledTrackingProblem(ARM, REFERENCE, 1.0, 500.0, 1e3).cost(gains)
    tight = SampledTrackingProblem(ARM, REFERENCE, 1.0, 500.0, 5.0).cost(gains)
    assert loose[0] == free[0] and tight[0] > free[0]


@pytest.mark.parametrize('servo_rate, per_servo, per_sample', [
    (100.0, 10, 10), (200.0, 5, 10), (1000.0, 1, 10), (50.0, 20, 10), (5000.0, 1, 50)])
def test_servo_and_error_samples_share_one_step(servo_rate, per_servo, per_sample):
    problem = SampledTrackingProblem(ARM, REFERENCE, 0.2, servo_rate)
    assert (problem.per_servo, problem.per_sample) == (per_servo, per_sample)
    assert problem.h * per_servo == pytest.approx(1.0 / servo_rate, rel=1e-12)
    assert problem.h * per_sample == pytest.approx(0.01, rel=1e-12)
    with pytest.raises(ValueError, match='integer multiple'):
        SampledTrackingProblem(ARM, REFERENCE, 0.2, 150.0)
    with pytest.raises(ValueError, match='torque_limit'):
        SampledTrackingProblem(ARM, REFERENCE, 0.2, 200.0, [1.0, 0.0, 1.0])


def test_tuning_runs_the_ea_on_a_given_problem():
    problem = SampledTrackingProblem(ARM, REFERENCE, 1.0, 200.0, [16.5, 10.0, 2.5])
    result = tune_pd_gains(ARM, REFERENCE, population_size=10, generations=4, seed=1,
                           problem=problem)
    best = np.concatenate([result.kp, result.kd])[None]
    assert result.cost == problem.cost(best)[0] and result.step == problem.h
    assert result.paper_cost == problem.cost(paper_gains()[None])[0]
    assert result.history[0, 0] <= problem.cost(genome_to_gains(np.full((1, 6), 0.5)))[0]

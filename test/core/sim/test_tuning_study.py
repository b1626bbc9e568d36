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
The digital servo's eq. (10) cost (tuning_study): adaptive integration, numpy, the EA on it.

The reference errors come from scipy's LSODA between the servo instants (rtol 1e-10),
independent of the fixed-step kernel under test.
"""

import numpy as np
import pytest
from rkgnn_ros.core.sim.plant import PlanarArm
from rkgnn_ros.core.sim.tracking import TrackingProblem
from rkgnn_ros.core.sim.trajectories import paper_reference
from rkgnn_ros.core.sim.tuning import genome_to_gains, paper_gains, tune_pd_gains
from rkgnn_ros.core.sim.tuning_study import SampledTrackingProblem
from scipy.integrate import solve_ivp

ARM = PlanarArm.paper()
REFERENCE = paper_reference(3)
CORNER = np.array([100.0, 100.0, 100.0, 50.0, 50.0, 50.0])     # the largest default gains


@pytest.fixture
def rng():
    return np.random.default_rng(20260601)


def held_torque_error(gains, duration, servo_rate, limit):
    """Eq. (10) of the sampled, held, clipped PD from adaptive integration between instants."""
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

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
The PD tracking cost of eq. (10): against simulate(), compiled kernel against numpy, divergence.

The reference errors come from :func:`rkgnn_ros.core.sim.simulate.simulate` (LSODA at rtol
1e-9), independent of the fixed-step kernel under test.
"""

import numpy as np
import pytest
from rkgnn_ros.core.integration.rkg import STABILITY_LIMIT
from rkgnn_ros.core.sim.plant import PDController, PlanarArm
from rkgnn_ros.core.sim.simulate import simulate
from rkgnn_ros.core.sim.tracking import STEP_SAFETY, tracking_cost, TrackingProblem, tuning_step
from rkgnn_ros.core.sim.trajectories import paper_reference
from rkgnn_ros.core.sim.tuning import genome_to_gains, paper_gains

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
    assert h * stiffness <= STEP_SAFETY * STABILITY_LIMIT * (1.0 + 1e-6)
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

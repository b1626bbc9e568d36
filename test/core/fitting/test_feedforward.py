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

"""The feed-forward along a plan, θ̈d from its points, and the computed-torque law."""

import numpy as np
import pytest
from rkgnn_ros.core.control.feedforward import (computed_torque, feedforward_torque,
                                                hermite_acceleration, plan_feedforward)
from rkgnn_ros.core.model.model import RKGNNModel
from rkgnn_ros.core.model.scales import Scales
from rkgnn_ros.core.model.spec import NetworkSpec
from rkgnn_ros.core.sim.parameters import ArmParameters
from rkgnn_ros.core.sim.plant import PDController, PlanarArm
from rkgnn_ros.core.sim.simulate import simulate
from rkgnn_ros.core.sim.trajectories import paper_reference
from scipy.integrate import solve_ivp


def planar_arm(n):
    """Return an n-link arm with friction (the paper's for n = 3)."""
    if n == 3:
        return PlanarArm.paper()
    return PlanarArm(ArmParameters(masses=np.linspace(4.0, 1.0, n),
                                   lengths=np.linspace(0.3, 0.1, n),
                                   viscous=np.full(n, 0.2), coulomb=np.full(n, 0.1)))


def exact_plan(reference, t):
    """Return θd, θ̇d and the exact θ̈d of a sum of sines at times ``t``."""
    theta_d, theta_d_dot = reference.evaluate(t)
    arg = reference._omega * t[:, None, None] + reference.phases
    acc = -np.sum(reference.amplitudes * reference._omega ** 2 * np.sin(arg), axis=-1)
    return theta_d, theta_d_dot, acc


@pytest.mark.parametrize('n', [2, 3, 6])
def test_true_model_feedforward_is_the_arms_inverse_dynamics(n):
    arm = planar_arm(n)
    t = np.arange(0.0, 4.0, 0.02)
    theta_d, theta_d_dot, acc = exact_plan(paper_reference(n), t)
    truth = arm.inverse_dynamics(theta_d, theta_d_dot, acc)
    # with θ̈d given, exactly the inverse dynamics
    plan = plan_feedforward(arm, t, theta_d, theta_d_dot, acc)
    np.testing.assert_allclose(plan.effort, truth, rtol=1e-13, atol=1e-13)
    # with θ̈d from the points, second order in the spacing: halving it quarters the error
    errors = []
    for step in (0.02, 0.01):
        t = np.arange(0.0, 4.0, step)
        theta_d, theta_d_dot, acc = exact_plan(paper_reference(n), t)
        plan = plan_feedforward(arm, t, theta_d, theta_d_dot)
        errors.append(np.max(np.abs(plan.effort
                                    - arm.inverse_dynamics(theta_d, theta_d_dot, acc))))
    assert errors[0] < 1e-3 * np.max(np.abs(truth))
    assert 3.5 < errors[0] / errors[1] < 4.5, errors


def test_hermite_acceleration_is_exact_for_cubics_on_uneven_points():
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.uniform(0.01, 0.05, 40))
    c = rng.normal(size=(4, 2))
    theta = c[0] + np.outer(t, c[1]) + np.outer(t ** 2, c[2]) + np.outer(t ** 3, c[3])
    theta_dot = c[1] + 2 * np.outer(t, c[2]) + 3 * np.outer(t ** 2, c[3])
    np.testing.assert_allclose(hermite_acceleration(t, theta, theta_dot),
                               2 * c[2] + 6 * np.outer(t, c[3]), rtol=1e-7, atol=1e-7)


def test_hermite_acceleration_errs_half_as_much_as_a_centred_difference():
    t = np.arange(0.0, 6.0, 0.02)
    theta_d, theta_d_dot, acc = exact_plan(paper_reference(3), t)
    hermite = np.abs(hermite_acceleration(t, theta_d, theta_d_dot) - acc)[1:-1].max()
    centred = np.abs(np.gradient(theta_d_dot, t, axis=0) - acc)[1:-1].max()
    assert 0.4 < hermite / centred < 0.6, (hermite, centred)


def test_identified_model_feedforward_is_its_inverse_dynamics():
    arm, pd = PlanarArm.paper(), PDController.paper()
    data = simulate(arm, pd, paper_reference(3), 2.0)
    for case, gains in (('torque', {}), ('pd_gains', {'kp': np.diag(pd.kp),
                                                      'kd': np.diag(pd.kd)})):
        spec = NetworkSpec.recommended(3, case)
        scales = Scales.from_datasets([data], case, gains.get('kp'), gains.get('kd'))
        genome = spec.initial_genome() + 0.1 * np.random.default_rng(1).standard_normal(
            spec.genome_size)
        model = RKGNNModel(spec, scales, genome, **gains)
        acc = hermite_acceleration(data.t, data.theta_d, data.theta_d_dot)
        plan = plan_feedforward(model, data.t, data.theta_d, data.theta_d_dot)
        np.testing.assert_allclose(plan.effort, model.inverse_dynamics(
            data.theta_d, data.theta_d_dot, acc), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(
            feedforward_torque(model, data.theta_d, data.theta_d_dot, acc, torque_scale=2.5),
            2.5 * plan.effort, rtol=1e-14)


def test_computed_torque_with_the_true_model_gives_the_chosen_error_dynamics():
    # with the true model the error obeys ë + Kd ė + Kp e = 0 on every joint: critically
    # damped at ω = 10 rad/s, e(t) = (e0 + (ė0 + ω e0) t) exp(−ω t)
    arm, reference = PlanarArm.paper(), paper_reference(3)
    omega = 10.0
    kp, kd = omega ** 2, 2 * omega
    e0 = np.array([0.1, -0.05, 0.08])

    def rate(s, x):
        theta_d, theta_d_dot, acc = exact_plan(reference, np.array([s]))
        tau = computed_torque(arm, x[:3], x[3:], theta_d[0], theta_d_dot[0], acc[0], (kp, kd))
        return arm.dynamics(x, tau)

    theta_d, theta_d_dot, _ = exact_plan(reference, np.array([0.0]))
    x0 = np.concatenate([theta_d[0] - e0, theta_d_dot[0]])
    times = np.array([0.1, 0.3, 0.6])
    sol = solve_ivp(rate, (0.0, 0.6), x0, t_eval=times, rtol=1e-10, atol=1e-12)
    theta_d, _, _ = exact_plan(reference, times)
    error = theta_d - sol.y[:3].T
    expected = (e0 + omega * e0 * times[:, None]) * np.exp(-omega * times[:, None])
    np.testing.assert_allclose(error, expected, atol=1e-7)


def test_bad_plans_are_refused_with_the_reason():
    arm = PlanarArm.paper()
    t = np.arange(5) * 0.02
    theta = np.zeros((5, 3))
    with pytest.raises(ValueError, match='strictly increasing'):
        plan_feedforward(arm, t[::-1], theta, theta)
    with pytest.raises(ValueError, match='at least 2 points'):
        plan_feedforward(arm, t[:1], theta[:1], theta[:1])
    bad = theta.copy()
    bad[2, 1] = np.nan
    with pytest.raises(ValueError, match='theta_d_dot must be finite'):
        plan_feedforward(arm, t, theta, bad)
    with pytest.raises(ValueError, match='shape'):
        plan_feedforward(arm, t, theta, theta[:, :2])
    with pytest.raises(ValueError, match='kp must be >= 0'):
        computed_torque(arm, theta, theta, theta, theta, theta, (-1.0, 1.0))

    class WrongShape:

        def inverse_dynamics(self, theta, theta_dot, theta_ddot):
            return np.zeros(3)

    with pytest.raises(ValueError, match='the model returned torques of shape'):
        plan_feedforward(WrongShape(), t, theta, theta)

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

"""Closed-loop stiffness of the arm under PD and the largest stable Runge-Kutta-Gill step."""

import numpy as np
import pytest
from rkgnn_ros.core.sim.parameters import ArmParameters
from rkgnn_ros.core.sim.plant import PDController, PlanarArm
from rkgnn_ros.core.sim.stability import max_stable_rkg_step
from rkgnn_ros.core.sim.trajectories import paper_reference
from scipy.integrate import solve_ivp


def closed_loop(arm, ctl, reference):
    n = arm.n_joints

    def f(t, x):
        ref, ref_dot = reference.evaluate(t)
        return arm.dynamics(x, ctl.torque(x[:n], x[n:], ref, ref_dot))
    return f


def rk4_rollout(f, h, duration, x0):
    """Integrate with classical RK4 (Gill's stability polynomial); None once |x| > 1e3."""
    x, t = x0.copy(), 0.0
    for _ in range(int(round(duration / h))):
        k1 = f(t, x)
        k2 = f(t + h / 2, x + h / 2 * k1)
        k3 = f(t + h / 2, x + h / 2 * k2)
        k4 = f(t + h, x + h * k3)
        x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        t += h
        if not np.all(np.abs(x) < 1e3):
            return None
    return x


@pytest.mark.parametrize('mass_model, frictionless, band', [
    ('point', True, (330.0, 440.0)),     # ~385 1/s
    ('rod', True, (1250.0, 1650.0)),     # ~1436 1/s
    ('point', False, (500.0, 650.0)),    # ~576 1/s: the tanh Coulomb term adds damping
    ('rod', False, (1850.0, 2350.0)),    # ~2109 1/s
])
def test_closed_loop_stiffness_of_the_paper_arm(mass_model, frictionless, band):
    params = ArmParameters.paper(mass_model)
    arm = PlanarArm(params.without_friction() if frictionless else params)
    ctl = PDController.paper()
    hanging = np.array([-np.pi / 2, 0.0, 0.0])
    stiffness = arm.closed_loop_stiffness(hanging, np.zeros(3), ctl.kp, ctl.kd)
    assert band[0] < stiffness < band[1]
    lam = arm.closed_loop_eigenvalues(hanging, np.zeros(3), ctl.kp, ctl.kd)
    assert np.all(lam.real < 0.0)      # the hanging pose is stable under the paper's PD
    # batched over states
    states = np.tile(hanging, (4, 1))
    np.testing.assert_allclose(
        arm.closed_loop_stiffness(states, np.zeros((4, 3)), ctl.kp, ctl.kd), stiffness)


@pytest.mark.parametrize('mass_model, band', [('point', (2.0e-3, 3.5e-3)),
                                              ('rod', (0.5e-3, 1.0e-3))])
def test_stable_rkg_step_is_stable_and_a_100hz_step_is_not(mass_model, band):
    arm = PlanarArm.paper(mass_model)
    ctl = PDController.paper()
    reference = paper_reference()
    h = max_stable_rkg_step(arm, ctl.kp, ctl.kd, reference, 20.0, samples=100)
    assert band[0] < h < band[1]
    theta_d, theta_d_dot = reference.evaluate(0.0)
    x0 = np.concatenate([theta_d, theta_d_dot])
    f = closed_loop(arm, ctl, reference)
    exact = solve_ivp(f, (0.0, 1.0), x0, method='LSODA', rtol=1e-10, atol=1e-10).y[:, -1]
    dt = 0.01
    substeps = int(np.ceil(dt / h))
    stable = rk4_rollout(f, dt / substeps, 1.0, x0)
    assert stable is not None and np.max(np.abs(stable - exact)) < 1e-4
    # one RKG step per 100 Hz sample is beyond the stability limit: blow-up or garbage
    unstable = rk4_rollout(f, dt, 1.0, x0)
    assert unstable is None or np.max(np.abs(unstable - exact)) > 1.0

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

"""Case 1 online: the servo law learned when the data determine it, the search's data."""

import numpy as np
import pytest
from rkgnn_ros.core.fitting.case_one import arm_model, fit_law, search_segments
from rkgnn_ros.core.fitting.controller import closed_loop
from rkgnn_ros.core.fitting.identify import Evolution
from rkgnn_ros.core.model.network import NetworkSpec
from rkgnn_ros.core.sim.plant import PlanarArm
from rkgnn_ros.core.sim.sensors import SensorModel
from rkgnn_ros.core.sim.servo import Servo
from rkgnn_ros.core.sim.simulate import simulate
from rkgnn_ros.core.sim.trajectories import paper_reference

KP = np.array([32.84, 42.05, 42.31])
KD = np.array([42.44, 0.19, 4.86])
ARM = PlanarArm.paper()


def run(servo, seconds, noise=None):
    return simulate(ARM, servo, paper_reference(3), seconds, rate=100.0,
                    noise=noise or SensorModel.exact(), rng=3)


@pytest.fixture(scope='module')
def pid_data():
    return run(Servo(KP, KD, ki=[20.0, 20.0, 20.0]), 12.0)


def test_a_pure_pd_is_learned_without_an_integral_and_a_pid_with_one(pid_data):
    law = fit_law([run(Servo(KP, KD), 6.0)])
    assert 'PID' not in law.describe() and np.all(law.ki == 0.0)
    np.testing.assert_allclose(law.kp, KP, rtol=1e-3)
    assert np.all(np.abs(law.kd - KD) <= 1e-3 * KP)
    # nor θ-terms: they would fit this torque too, and be wrong at another pose
    assert law.theta_weights.size == 0
    assert np.all(np.abs(law.bias) < 1e-3 * KP)
    law = fit_law([pid_data])
    assert law.describe().startswith('PID')
    np.testing.assert_allclose(law.ki, 20.0, rtol=1e-3)
    np.testing.assert_allclose(law.kp, KP, rtol=1e-3)


def test_gains_are_given_only_once_the_data_determine_them():
    # encoder noise 1e-4 rad, θ̇ differenced: 3 s fit almost any gains with the 78 θ-terms,
    # and the newest half disagrees; 16 s give them to 1 % (seed 3; 0.4 % measured)
    noisy = run(Servo(KP, KD, gravity='measured', arm=ARM), 16.0,
                SensorModel.differenced(1e-4))
    assert fit_law([noisy.slice(0, 301)]) is None
    law = fit_law([noisy])
    np.testing.assert_allclose(law.kp, KP, rtol=0.01)
    assert np.all(np.abs(law.kd - KD) <= 0.01 * (KD + 0.1 * KP))


def test_the_shifted_commands_carry_everything_but_the_pd_part(pid_data):
    law = fit_law([pid_data])
    seg, = search_segments([pid_data], law)
    # what the closed-loop search's case-2 kernel computes, Kp (θd' − θ) + Kd (θ̇d − θ̇),
    # plus the θ-terms on θ left to the model's gravity, is the whole law along the data
    e = pid_data.theta_d - pid_data.theta
    integral = np.zeros_like(e)
    integral[1:] = np.cumsum(0.5 * (e[1:] + e[:-1]), axis=0) * pid_data.dt
    measured = law._theta_terms(pid_data.theta, None) if law.theta_input == 'measured' \
        else 0.0
    pd_part = law.kp * (seg.theta_d - pid_data.theta) + law.kd * (
        pid_data.theta_d_dot - pid_data.theta_dot) + measured
    full = law.torque(pid_data.theta, pid_data.theta_dot, pid_data.theta_d,
                      pid_data.theta_d_dot, law.ki * integral)
    np.testing.assert_allclose(pd_part, full, atol=1e-9 * np.abs(full).max())
    # and that is the measured torque (the fit's residual)
    assert np.sqrt(np.mean((full - pid_data.tau) ** 2)) < 1e-3 * np.abs(pid_data.tau).max()


def test_the_arm_model_gets_the_servos_gravity_terms_back():
    data = run(Servo(KP, KD, gravity='measured', arm=ARM), 10.0)
    law = fit_law([data])
    assert law.theta_input == 'measured' and law.theta_weights.size > 0   # the compensation
    arm = Evolution(NetworkSpec.recommended(3, 'torque'), [data], seed=0).best_model()
    closed = closed_loop(arm, law, theta_samples=data.theta).model   # G − W φ(θ)
    back = arm_model(closed, law, data.theta)
    assert back.case == 'torque'
    added = back.gravity_terms(data.theta) - closed.gravity_terms(data.theta)
    target = law._theta_terms(data.theta, None)
    fold = np.array(back.info['controller_fold_error'])
    # the gravity output now holds the projection the fold error describes: what it misses
    # of the servo's terms is that share of their spread, and less than their spread
    spread = np.std(target, axis=0)
    missed = np.sqrt(np.mean((added - target - np.mean(added - target, axis=0)) ** 2, axis=0))
    np.testing.assert_allclose(missed, fold * spread, rtol=1e-6)
    assert np.all(fold < 1.0)

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

"""What a driver publishes: encoder noise, differenced or filtered velocity, missing fields."""

import math

import numpy as np
import pytest
from rkgnn_ros.core.sim.plant import PDController, PlanarArm
from rkgnn_ros.core.sim.sensors import SensorModel
from rkgnn_ros.core.sim.simulate import simulate
from rkgnn_ros.core.sim.trajectories import paper_reference

DT = 0.01


@pytest.fixture(scope='module')
def truth():
    """5 s of the paper's arm at 100 Hz, exact."""
    return simulate(PlanarArm.paper(), PDController.paper(), paper_reference(3), 5.0)


def test_exact_sensors_publish_the_truth(truth):
    theta, theta_dot, tau = SensorModel.exact().apply(truth.theta, truth.theta_dot, truth.tau,
                                                      DT, np.random.default_rng(0))
    np.testing.assert_array_equal(theta, truth.theta)
    np.testing.assert_array_equal(theta_dot, truth.theta_dot)
    np.testing.assert_array_equal(tau, truth.tau)


def test_differenced_velocity_is_the_backward_difference_of_the_noisy_positions(truth):
    model = SensorModel.differenced(1e-4)
    theta, theta_dot, _ = model.apply(truth.theta, truth.theta_dot, truth.tau, DT,
                                      np.random.default_rng(1))
    np.testing.assert_array_equal(theta_dot[0], 0.0)         # no previous position
    np.testing.assert_allclose(theta_dot[1:], np.diff(theta, axis=0) / DT, rtol=1e-12)
    noise = theta_dot[1:] - np.diff(truth.theta, axis=0) / DT
    # white θ noise of 1e-4 rad: sqrt(2) 1e-4 / 0.01 = 0.0141 rad/s (500 samples: ±7 %)
    np.testing.assert_allclose(np.std(noise, axis=0), math.sqrt(2) * 1e-4 / DT, rtol=0.15)


def test_filtered_velocity_is_a_first_order_low_pass_of_the_differences(truth):
    model = SensorModel(theta_std=1e-4, velocity='filtered', velocity_cutoff=10.0)
    rng_seed = 2
    theta, theta_dot, _ = model.apply(truth.theta, truth.theta_dot, truth.tau, DT,
                                      np.random.default_rng(rng_seed))
    alpha = 1.0 - math.exp(-2.0 * math.pi * 10.0 * DT)
    expected = np.zeros_like(theta)
    for k in range(1, theta.shape[0]):
        expected[k] = expected[k - 1] + alpha * ((theta[k] - theta[k - 1]) / DT - expected[k - 1])
    np.testing.assert_allclose(theta_dot, expected, rtol=1e-12, atol=1e-15)
    # less noise: the filter of the noise alone against the raw differenced noise
    exact = SensorModel(velocity='filtered', velocity_cutoff=10.0)
    _, clean, _ = exact.apply(truth.theta, truth.theta_dot, truth.tau, DT)
    noise = theta_dot[1:] - clean[1:]
    raw = np.diff(theta - truth.theta, axis=0) / DT
    assert np.all(np.std(noise, axis=0) < 0.5 * np.std(raw, axis=0))
    # paid for with lag: 1 / (2π f_c) + dt / 2 = 21 ms, i.e. two samples here
    lag = [np.sqrt(np.mean((clean[50 + s:] - truth.theta_dot[50:truth.n_samples - s]) ** 2))
           for s in range(6)]
    assert int(np.argmin(lag)) == 2, lag


def test_a_driver_without_velocity_or_effort_publishes_nan(truth):
    model = SensorModel(theta_std=1e-4, velocity='none', effort=False)
    theta, theta_dot, tau = model.apply(truth.theta, truth.theta_dot, truth.tau, DT,
                                        np.random.default_rng(3))
    assert np.all(np.isnan(theta_dot)) and np.all(np.isnan(tau))
    assert np.all(np.isfinite(theta))
    data = simulate(PlanarArm.paper(), PDController.paper(), paper_reference(3), 1.0,
                    noise=model, rng=3)
    assert data.tau is None and np.all(data.theta_dot == 0.0)


def test_stream_equals_batch_and_noise_changes_at_once_without_shifting_the_draws(truth):
    model = SensorModel(theta_std=1e-4, velocity='filtered')
    batch = model.apply(truth.theta, truth.theta_dot, truth.tau, DT, np.random.default_rng(4))
    stream = model.stream(DT, np.random.default_rng(4))
    quiet = SensorModel(velocity='filtered').stream(DT, np.random.default_rng(4))
    for k in range(truth.n_samples):
        values = stream.measure(truth.theta[k], truth.theta_dot[k], truth.tau[k])
        for arr, value in zip(batch, values):
            np.testing.assert_array_equal(arr[k], value)
        if k == 100:
            quiet.set_noise(theta_std=1e-4)
        late = quiet.measure(truth.theta[k], truth.theta_dot[k], truth.tau[k])
        if k > 100:         # same draws from the same seed: the same θ from then on
            np.testing.assert_array_equal(late[0], values[0])
    with pytest.raises(ValueError, match='theta_std'):
        stream.set_noise(theta_std=-1.0)


@pytest.mark.parametrize('kwargs, match', [
    ({'theta_std': -1.0}, 'theta_std'),
    ({'velocity': 'tacho'}, 'velocity'),
    ({'velocity': 'difference', 'theta_dot_std': 0.1}, 'theta_dot_std'),
    ({'velocity_cutoff': 0.0}, 'velocity_cutoff'),
])
def test_invalid_sensor_models_are_refused(kwargs, match):
    with pytest.raises(ValueError, match=match):
        SensorModel(**kwargs)

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

"""The accurate simulator: tracking, noise, digital control, open-loop replay, errors."""

import numpy as np
import pytest
from rkgnn_ros.core.data import Dataset
from rkgnn_ros.core.sim.parameters import ArmParameters
from rkgnn_ros.core.sim.plant import PDController, PlanarArm
from rkgnn_ros.core.sim.simulate import (
    NoiseModel, simulate, simulate_open_loop, SimulationError)
from rkgnn_ros.core.sim.trajectories import paper_reference


@pytest.fixture(scope='module')
def arm():
    return PlanarArm.paper()


@pytest.fixture(scope='module')
def controller():
    return PDController.paper()


@pytest.fixture(scope='module')
def reference():
    return paper_reference()


@pytest.fixture(scope='module')
def clean(arm, controller, reference):
    return simulate(arm, controller, reference, 10.0)


def test_pd_tracks_the_paper_reference(clean, reference):
    assert isinstance(clean, Dataset)
    assert clean.n_samples == 1001 and clean.n_joints == 3
    assert clean.dt == pytest.approx(0.01)
    assert clean.joint_names == ('joint1', 'joint2', 'joint3')
    error = clean.theta - clean.theta_d
    # bounded, but not tiny: the paper's PD has no gravity compensation
    assert np.max(np.abs(error)) < 0.4
    assert np.max(np.abs(clean.theta_dot - clean.theta_d_dot)) < 1.5
    assert np.sqrt(np.mean(error ** 2)) < 0.15
    theta_d, theta_d_dot = reference.evaluate(clean.t)
    np.testing.assert_array_equal(clean.theta_d, theta_d)
    np.testing.assert_array_equal(clean.theta_d_dot, theta_d_dot)


def test_recorded_torque_is_the_applied_pd_torque(clean, controller):
    np.testing.assert_allclose(
        clean.tau, controller.torque(clean.theta, clean.theta_dot, clean.theta_d,
                                     clean.theta_d_dot), rtol=1e-12, atol=1e-12)


def test_the_recorded_states_satisfy_the_dynamics(clean, arm):
    # θ̈ from the dynamics, integrated by the trapezoid rule, gives the recorded θ̇
    theta_ddot = arm.forward_dynamics(clean.theta, clean.theta_dot, clean.tau)
    predicted = clean.theta_dot[:-1] + 0.5 * clean.dt * (theta_ddot[1:] + theta_ddot[:-1])
    # (after the first samples: starting on the reference excites the fast mode)
    np.testing.assert_allclose(predicted[3:], clean.theta_dot[4:], atol=5e-3)


def test_solvers_agree(arm, controller, reference):
    lsoda = simulate(arm, controller, reference, 2.0)
    dop853 = simulate(arm, controller, reference, 2.0, method='DOP853')
    np.testing.assert_allclose(lsoda.state, dop853.state, atol=1e-6)


def test_x0_defaults_to_the_reference_start(arm, controller, reference):
    ds = simulate(arm, controller, reference, 0.5, t0=2.5, rate=50.0)
    theta_d, theta_d_dot = reference.evaluate(2.5)
    assert ds.t[0] == 2.5 and ds.n_samples == 26
    np.testing.assert_array_equal(ds.theta[0], theta_d)
    np.testing.assert_array_equal(ds.theta_dot[0], theta_d_dot)
    x0 = np.concatenate([theta_d + 0.1, np.zeros(3)])
    other = simulate(arm, controller, reference, 0.5, t0=2.5, rate=50.0, x0=x0)
    np.testing.assert_array_equal(other.state[0], x0)
    assert not np.allclose(other.theta[-1], ds.theta[-1], atol=1e-4)


def test_noise_statistics_and_reproducibility(arm, controller, reference, clean):
    noise = NoiseModel(theta_std=1e-3, theta_dot_std=2e-2, tau_std=0.05)
    a = simulate(arm, controller, reference, 10.0, noise=noise, rng=np.random.default_rng(5))
    b = simulate(arm, controller, reference, 10.0, noise=noise, rng=np.random.default_rng(5))
    c = simulate(arm, controller, reference, 10.0, noise=noise, rng=6)
    np.testing.assert_array_equal(a.state, b.state)
    np.testing.assert_array_equal(a.tau, b.tau)
    assert not np.array_equal(a.theta, c.theta)
    # the noise is on the records only: the noise-free run is the same plant trajectory
    for name, std in (('theta', 1e-3), ('theta_dot', 2e-2), ('tau', 0.05)):
        residual = getattr(a, name) - getattr(clean, name)
        assert np.std(residual) == pytest.approx(std, rel=0.05)
        assert abs(np.mean(residual)) < 4 * std / np.sqrt(residual.size)
    np.testing.assert_array_equal(a.theta_d, clean.theta_d)


def test_velocity_from_finite_differences(arm, controller, reference, clean):
    noise = NoiseModel(theta_std=1e-4, velocity_from_differences=True)
    ds = simulate(arm, controller, reference, 10.0, noise=noise, rng=1)
    residual = (ds.theta_dot - clean.theta_dot)[1:-1]
    # central differences of white noise: std = σ / (√2 dt), plus a tiny truncation error
    assert np.std(residual) == pytest.approx(1e-4 / (np.sqrt(2) * 0.01), rel=0.06)
    np.testing.assert_allclose(ds.theta_dot, np.gradient(ds.theta, 0.01, axis=0))


def test_realistic_noise():
    noise = NoiseModel.realistic()
    assert (noise.theta_std, noise.theta_dot_std, noise.tau_std) == (1e-4, 1e-3, 0.0)
    with pytest.raises(ValueError, match='theta_std'):
        NoiseModel(theta_std=-1.0)
    with pytest.raises(ValueError, match='theta_dot_std'):
        NoiseModel(theta_dot_std=1.0, velocity_from_differences=True)


def test_open_loop_replay_reproduces_the_digital_closed_loop(arm, controller, reference):
    # the paper's gains need a fast digital loop (100 Hz chatters): control = sample = 500 Hz
    closed = simulate(arm, controller, reference, 2.0, rate=500.0, control_rate=500.0)
    np.testing.assert_allclose(
        closed.tau, controller.torque(closed.theta, closed.theta_dot, closed.theta_d,
                                      closed.theta_d_dot), rtol=1e-12, atol=1e-12)
    replay = simulate_open_loop(arm, closed.tau, closed.t, closed.state[0])
    np.testing.assert_allclose(replay.state, closed.state, atol=1e-6)
    np.testing.assert_array_equal(replay.tau, closed.tau)
    assert replay.theta_d is None
    # and the digital loop at 500 Hz is close to the continuous one
    continuous = simulate(arm, controller, reference, 2.0, rate=500.0)
    np.testing.assert_allclose(closed.theta, continuous.theta, atol=5e-3)


def test_digital_controller_holds_its_torque(arm, controller, reference):
    slow = simulate(arm, controller, reference, 1.0, rate=100.0, control_rate=400.0)
    # samples fall on every fourth tick; the torque there is computed from the state
    np.testing.assert_allclose(
        slow.tau, controller.torque(slow.theta, slow.theta_dot, slow.theta_d,
                                    slow.theta_d_dot), rtol=1e-12, atol=1e-12)
    coarse = simulate(arm, controller, reference, 1.0, rate=500.0, control_rate=250.0)
    np.testing.assert_array_equal(coarse.tau[1::2], coarse.tau[0:-1:2])
    assert not np.array_equal(coarse.tau[2::2], coarse.tau[1:-1:2])


@pytest.mark.parametrize('mass_model', ('point', 'rod'))
def test_unstable_digital_controller_raises(controller, reference, mass_model):
    # the paper's gains are too stiff for a 100 Hz zero-order-hold PD
    with pytest.raises(SimulationError, match='diverged'):
        simulate(PlanarArm.paper(mass_model), controller, reference, 2.0, control_rate=100.0)


def test_unstable_continuous_loop_raises(arm, reference):
    pushing = PDController([-200.0, -200.0, -200.0], [0.0, 0.0, 0.0])
    with pytest.raises(SimulationError, match='diverged'):
        simulate(arm, pushing, reference, 5.0)


def test_open_loop_against_a_closed_form():
    # one link, no gravity, no friction: J θ̈ = τ(t)
    mass, length = 2.0, 0.5
    arm = PlanarArm(ArmParameters([mass], [length], gravity=0.0))
    inertia = mass * length ** 2
    t = np.linspace(0.0, 1.0, 11)
    tau = (0.3 * t)[:, None]
    x0 = np.array([0.2, -0.1])
    ramp = simulate_open_loop(arm, tau, t, x0, hold=False)
    expected = 0.2 - 0.1 * t + 0.3 * t ** 3 / (6 * inertia)
    np.testing.assert_allclose(ramp.theta[:, 0], expected, atol=1e-9)
    held = simulate_open_loop(arm, tau, t, x0, hold=True)
    # zero-order hold: the velocity gains τ_k dt / J over each interval
    expected_dot = -0.1 + np.concatenate([[0.0], np.cumsum(tau[:-1, 0]) * 0.1]) / inertia
    np.testing.assert_allclose(held.theta_dot[:, 0], expected_dot, atol=1e-9)


@pytest.mark.parametrize('kwargs, match', [
    ({'duration': 0.0}, 'duration'),
    ({'rate': -1.0}, 'rate'),
    ({'x0': np.zeros(3)}, 'x0'),
    ({'method': 'Euler'}, 'method'),
    ({'control_rate': 0.0}, 'control_rate'),
])
def test_simulate_validates_its_arguments(arm, controller, reference, kwargs, match):
    args = {'duration': 1.0, **kwargs}
    with pytest.raises(ValueError, match=match):
        simulate(arm, controller, reference, **args)


def test_mismatched_joint_counts_are_rejected(arm, controller):
    with pytest.raises(ValueError, match='reference'):
        simulate(arm, controller, paper_reference(2), 1.0)
    with pytest.raises(ValueError, match='tau_samples'):
        simulate_open_loop(arm, np.zeros((5, 2)), np.arange(5.0), np.zeros(6))
    with pytest.raises(ValueError, match='uniformly'):
        simulate_open_loop(arm, np.zeros((3, 3)), [0.0, 1.0, 3.0], np.zeros(6))

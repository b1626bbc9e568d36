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

"""The identified model: rollouts (compiled, against numpy RKG), terms, gains, validation."""

from model_helpers import (arm2_run, KD, KD2, KP, KP2, make_model, N, REFERENCE, SCALES,
                           simulate_model, torque_signal)
import numpy as np
import pytest
from rkgnn_ros.core.integration.rkg import rkg_integrate
from rkgnn_ros.core.model.model import RKGNNModel
from rkgnn_ros.core.model.network import BatchedNetwork
from rkgnn_ros.core.model.scales import Scales
from rkgnn_ros.core.model.spec import NetworkSpec


@pytest.fixture(scope='module')
def arm2_data():
    return arm2_run()


def numpy_rollout(model, t, substeps):
    """RKG rollout with the numpy BatchedNetwork (no compiled code), shape (N, 2n)."""
    net = BatchedNetwork(model.spec, model.spec.decode(model.genome, model.scales),
                         model.scales, model.kp, model.kd)
    qd, qd_dot = REFERENCE.evaluate(t)
    x0 = np.concatenate([qd[0], qd_dot[0]])
    if model.case == 'torque':
        tau = torque_signal(t)  # first-order hold, as the model's torque_interpolation

        def inputs(time):
            return np.array([np.interp(time, t, tau[:, j]) for j in range(N)])
    else:
        def inputs(time):
            return np.concatenate(REFERENCE.evaluate(time))
    return rkg_integrate(lambda x, u: net.rhs(x[None], u)[0], t, x0, substeps, inputs)


@pytest.mark.parametrize('velocity', ['learned', 'christoffel'])
@pytest.mark.parametrize('inertia', ['penalty', 'cholesky'])
@pytest.mark.parametrize('case', ['torque', 'pd_gains', 'unknown'])
def test_simulate_equals_a_numpy_rkg_rollout(case, inertia, velocity):
    model = make_model(case, inertia, velocity, torque_interpolation='linear')
    t = np.arange(41) * 0.01
    fast = simulate_model(model, t)
    assert fast.shape == (41, 2 * N)
    assert np.all(np.isfinite(fast))
    reference = numpy_rollout(model, t, model.substeps)
    scale = np.max(np.abs(reference), axis=0)
    np.testing.assert_allclose(fast, reference, rtol=0.0, atol=1e-10 * scale.max())


def test_simulate_keeps_the_step_width_on_a_coarser_grid():
    model = make_model('unknown', substeps=3)  # h = 0.01 / 3
    t = np.arange(21) * 0.02  # 6 substeps per interval keep h
    np.testing.assert_allclose(simulate_model(model, t), numpy_rollout(model, t, 6),
                               rtol=0.0, atol=1e-12)
    # an explicit count overrides it
    qd, qd_dot = REFERENCE.evaluate(t)
    two = model.simulate(np.concatenate([qd[0], qd_dot[0]]), t, reference=REFERENCE,
                         substeps=2)
    np.testing.assert_allclose(two, numpy_rollout(model, t, 2), rtol=0.0, atol=1e-12)


def test_predict_rolls_out_from_the_first_state(arm2_data):
    data = arm2_data.slice(0, 101)
    spec = NetworkSpec(2, 'pd_gains', bias=True)
    scales = Scales.from_datasets([data], 'pd_gains', KP2, KD2)
    model = RKGNNModel(spec, scales, spec.initial_genome(), kp=KP2, kd=KD2)
    pred = model.predict(data)
    assert pred.shape == (101, 4)
    np.testing.assert_array_equal(pred[0], data.state[0])
    np.testing.assert_array_equal(
        pred, model.simulate(data.state[0], data.t, theta_d=data.theta_d,
                             theta_d_dot=data.theta_d_dot))


def test_simulate_validates_its_inputs():
    model = make_model('torque')
    t = np.arange(11) * 0.01
    with pytest.raises(ValueError, match='t must be increasing'):
        model.simulate(np.zeros(2 * N), t[::-1], tau=torque_signal(t))
    with pytest.raises(ValueError, match='x0 contains NaN'):
        model.simulate(np.full(2 * N, np.nan), t, tau=torque_signal(t))
    with pytest.raises(ValueError, match='x0 must have 6 values'):
        model.simulate(np.zeros(N), t, tau=torque_signal(t))
    with pytest.raises(ValueError, match='needs measured torque'):
        model.simulate(np.zeros(2 * N), t)


# ----- the identified terms

def test_implied_gains_in_cases_1_and_2():
    assert make_model('torque').implied_gains() is None
    model = make_model('pd_gains')
    kp, kd = model.implied_gains()
    np.testing.assert_array_equal(kp, KP)
    np.testing.assert_array_equal(kd, KD)
    kp[:] = 0.0  # a copy: the model keeps its gains
    np.testing.assert_array_equal(model.implied_gains()[0], KP)


def test_implied_gains_in_case_3_by_hand():
    n = 2
    scales = Scales(theta_center=[0.0, 0.0], theta_spread=[0.3, 0.3], velocity=[1.0, 1.0],
                    acceleration=[1.0, 1.0], torque=[2.0, 1.0], error=[0.1, 0.2],
                    error_rate=[0.5, 0.25])
    spec = NetworkSpec(n, 'unknown', torque_units=2, torque_linear=True)
    g = spec.initial_genome()
    lin = np.array([[1.5, 0.5], [2.0, 4.0]])  # rows: P, D (normalised)
    nets = {'p_net': np.array([[[0.5, -1.0], [0.2, 0.0]],      # centres
                               [[0.0, 0.3], [-0.2, 0.1]],      # widths
                               [[1.0, 2.0], [-0.5, 0.25]]]),   # weights
            'd_net': np.array([[[-0.3, 0.7], [0.0, 1.1]],
                               [[0.1, 0.0], [0.0, -0.4]],
                               [[0.5, -1.5], [2.0, 1.0]]])}
    for b in spec.blocks():
        if b.name == 'pd_linear':
            g[b.start:b.stop] = lin.ravel()
        elif b.name in nets:
            g[b.start:b.stop] = nets[b.name].ravel()
    model = RKGNNModel(spec, scales, g)
    kp, kd = model.implied_gains()

    def slope(net, scale_in):
        # d/de Σ_k w_k exp(-(e - c_k)² / s_k²) at e = 0, in physical units
        c = scale_in[:, None] * net[0]
        iw = np.exp(-2.0 * net[1]) / scale_in[:, None] ** 2
        w = scales.torque[:, None] * net[2]
        return np.sum(w * 2.0 * c * iw * np.exp(-c ** 2 * iw), axis=1)

    expected_kp = scales.torque / scales.error * lin[0] + slope(nets['p_net'], scales.error)
    expected_kd = (scales.torque / scales.error_rate * lin[1]
                   + slope(nets['d_net'], scales.error_rate))
    np.testing.assert_allclose(kp, expected_kp, rtol=1e-7)
    np.testing.assert_allclose(kd, expected_kd, rtol=1e-7)
    # the RBF part matters here: the linear gains alone are not the answer
    assert np.all(np.abs(kp - scales.torque / scales.error * lin[0]) > 1.0)


@pytest.mark.parametrize('velocity', ['learned', 'christoffel'])
@pytest.mark.parametrize('inertia', ['penalty', 'cholesky'])
def test_inverse_dynamics_inverts_forward_dynamics_with_torque(inertia, velocity):
    model = make_model('torque', inertia, velocity, sigma=0.2)
    rng = np.random.default_rng(1)
    theta = SCALES.theta_center + 0.3 * rng.standard_normal((7, N))
    theta_dot, tau = rng.standard_normal((2, 7, N))
    acc = model.forward_dynamics(theta, theta_dot, tau)
    assert acc.shape == (7, N)
    np.testing.assert_allclose(model.inverse_dynamics(theta, theta_dot, acc), tau,
                               rtol=1e-9, atol=1e-10)
    # one state: shapes (n,)
    one = model.forward_dynamics(theta[2], theta_dot[2], tau[2])
    assert one.shape == (N,)
    np.testing.assert_allclose(one, acc[2], rtol=1e-12)
    np.testing.assert_allclose(model.inverse_dynamics(theta[2], theta_dot[2], one), tau[2],
                               rtol=1e-9, atol=1e-10)


@pytest.mark.parametrize('case', ['pd_gains', 'unknown'])
def test_inverse_dynamics_inverts_forward_dynamics_with_a_controller(case):
    model = make_model(case, 'penalty', sigma=0.2)
    rng = np.random.default_rng(2)
    theta = SCALES.theta_center + 0.3 * rng.standard_normal((5, N))
    theta_dot = rng.standard_normal((5, N))
    theta_d = theta + 0.1 * rng.standard_normal((5, N))
    theta_d_dot = theta_dot + 0.5 * rng.standard_normal((5, N))
    acc = model.forward_dynamics(theta, theta_dot, theta_d=theta_d, theta_d_dot=theta_d_dot)
    tau = model.controller_torque(theta, theta_dot, theta_d, theta_d_dot)
    np.testing.assert_allclose(model.inverse_dynamics(theta, theta_dot, acc), tau,
                               rtol=1e-9, atol=1e-10)
    if case == 'pd_gains':
        np.testing.assert_allclose(tau, KP * (theta_d - theta) + KD * (theta_d_dot - theta_dot),
                                   rtol=1e-14)


def test_terms_shapes_and_refusals():
    model = make_model('pd_gains')
    theta = np.zeros((4, N)) + SCALES.theta_center
    assert model.mass_matrix(theta).shape == (4, N, N)
    assert model.mass_matrix(theta[0]).shape == (N, N)
    terms = model.terms(theta, theta, theta, theta)
    assert set(terms) == {'M', 'V', 'G', 'F', 'tau'}
    assert all(terms[k].shape == (4, N) for k in ('V', 'G', 'F', 'tau'))
    with pytest.raises(ValueError, match='needs theta_d and theta_d_dot'):
        model.terms(theta, theta)
    with pytest.raises(ValueError, match='must have 3 columns'):
        model.mass_matrix(np.zeros(2))
    with pytest.raises(ValueError, match='no controller model'):
        make_model('torque').controller_torque(theta, theta, theta, theta)


@pytest.mark.parametrize('case', ['torque', 'pd_gains', 'unknown'])
def test_term_accessors_in_every_case(case):
    """
    Check velocity_terms, gravity_terms and friction_terms agree with terms() in all cases.

    Regression test (fixed in 3a690c8) for cases 2 and 3: the three accessors passed a zero
    input of n values (``np.zeros(self.n_joints)``) to ``BatchedNetwork.terms``, whose torque
    network then needs [θd, θ̇d] (2n values), so they raised "operands could not be
    broadcast together with shapes (0,) (1,3)".
    """
    model = make_model(case)
    rng = np.random.default_rng(3)
    theta = SCALES.theta_center + 0.3 * rng.standard_normal((4, N))
    theta_dot = rng.standard_normal((4, N))
    desired = {} if case == 'torque' else {'theta_d': theta, 'theta_d_dot': theta_dot}
    terms = model.terms(theta, theta_dot, **desired)
    np.testing.assert_allclose(model.velocity_terms(theta, theta_dot), terms['V'], rtol=1e-14)
    np.testing.assert_allclose(model.gravity_terms(theta), terms['G'], rtol=1e-14)
    np.testing.assert_allclose(model.friction_terms(theta_dot), terms['F'], rtol=1e-14)
    assert model.gravity_terms(theta[0]).shape == (N,)
    assert model.friction_terms(theta_dot[0]).shape == (N,)
    np.testing.assert_array_equal(model.friction_terms(np.zeros(N)), np.zeros(N))


@pytest.mark.parametrize('kwargs, message', [
    ({'genome': np.zeros(5)}, 'genome must have'),
    ({'joint_names': ('a', 'b')}, '2 joint names for a 3-joint model'),
    ({'joint_names': ('a', 'b', 'a')}, 'duplicate joint names'),
    ({'kp': None}, "case 'pd_gains' needs kp and kd"),
    ({'kd': [1.0, 2.0]}, 'kd must have 3 values'),
    ({'dt': 0.0}, 'dt must be positive'),
    ({'substeps': 0}, 'substeps must be >= 1'),
    ({'torque_interpolation': 'spline'}, "torque_interpolation must be 'hold' or 'linear'"),
])
def test_model_constructor_validation(kwargs, message):
    spec = NetworkSpec.paper(N, 'pd_gains')
    args = {'genome': spec.initial_genome(), 'kp': KP, 'kd': KD}
    args.update(kwargs)
    with pytest.raises(ValueError, match=message):
        RKGNNModel(spec, SCALES, **args)

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

"""The arm controller's law fitted from measured torque, to predict case 1 in closed loop."""

from dataclasses import replace
import math

import numpy as np
import pytest
from rkgnn_ros.core.fitting.controller import (closed_loop, closed_loop_model, fit_controller,
                                               fit_pd_law)
from rkgnn_ros.core.fitting.controller_laws import ControllerLaw, PDLaw, RBFFeatures, TrigFeatures
from rkgnn_ros.core.model.model import RKGNNModel
from rkgnn_ros.core.model.scales import Scales
from rkgnn_ros.core.model.spec import NetworkSpec
from rkgnn_ros.core.sim.plant import PDController, PlanarArm
from rkgnn_ros.core.sim.sensors import SensorModel
from rkgnn_ros.core.sim.servo import Servo
from rkgnn_ros.core.sim.simulate import NoiseModel, simulate
from rkgnn_ros.core.sim.trajectories import paper_reference, SumOfSines
from rkgnn_ros.streams.buffer import StreamBuffer

N = 3
SCALES = Scales(theta_center=[-1.5, 0.0, 0.0], theta_spread=[0.3, 0.3, 0.3],
                velocity=[1.0, 1.0, 1.0], acceleration=[5.0, 5.0, 5.0], torque=[3.0, 2.0, 1.0],
                error=[0.1, 0.1, 0.1], error_rate=[0.5, 0.5, 0.5])


@pytest.fixture(scope='module')
def pd_run():
    """10 s at 100 Hz of the paper's arm under the paper's PD."""
    return simulate(PlanarArm.paper(), PDController.paper(), paper_reference(N), 10.0,
                    rate=100.0)


def _fit(data, tau=None):
    return fit_pd_law(data.theta, data.theta_dot, data.tau if tau is None else tau,
                      data.theta_d, data.theta_d_dot)


def test_fit_recovers_the_paper_gains_exactly(pd_run):
    law = _fit(pd_run)
    pd = PDController.paper()
    np.testing.assert_allclose(law.kp, np.diag(pd.kp), rtol=1e-9)
    np.testing.assert_allclose(law.kd, np.diag(pd.kd), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(law.bias, 0.0, atol=1e-9)
    assert np.all(law.fit_ratio < 1e-9)
    assert law.samples == pd_run.n_samples
    assert law.usable()
    np.testing.assert_allclose(
        law.torque(pd_run.theta, pd_run.theta_dot, pd_run.theta_d, pd_run.theta_d_dot),
        pd_run.tau, atol=1e-9)


def test_constant_torque_is_fitted_and_folded_into_the_desired_position(pd_run):
    bias = np.array([2.0, -1.0, 0.5])
    law = _fit(pd_run, tau=pd_run.tau + bias)
    np.testing.assert_allclose(law.bias, bias, atol=1e-9)
    e = pd_run.theta_d - pd_run.theta
    # Kp (θd + c/Kp − θ) + Kd ė = Kp e + Kd ė + c
    shifted = law.kp * (e + law.shift()) + law.kd * (pd_run.theta_d_dot - pd_run.theta_dot)
    np.testing.assert_allclose(shifted, pd_run.tau + bias, atol=1e-9)


def test_gains_survive_encoder_noise():
    data = simulate(PlanarArm.paper(), PDController.paper(), paper_reference(N), 10.0,
                    rate=100.0, noise=NoiseModel.realistic(), rng=3)
    law = _fit(data)
    pd = PDController.paper()
    np.testing.assert_allclose(law.kp, np.diag(pd.kp), rtol=0.05)
    assert np.all(np.abs(law.kd - np.diag(pd.kd)) < 0.05 * np.diag(pd.kd) + 0.5)
    assert law.usable()


def test_a_torque_that_is_not_a_pd_law_is_not_usable(pd_run):
    t = pd_run.t[:, None]
    tau = 5.0 * np.sin(2 * np.pi * np.array([0.37, 0.91, 1.3]) * t)
    law = _fit(pd_run, tau=tau)
    assert law is not None and not law.usable()
    assert np.all(law.fit_ratio > 0.5)


def test_too_few_or_degenerate_samples_give_none(pd_run):
    d = pd_run
    assert fit_pd_law(d.theta[:10], d.theta_dot[:10], d.tau[:10], d.theta_d[:10],
                      d.theta_d_dot[:10]) is None
    # the error never varies: gains are not identifiable
    same = np.ones((100, N))
    assert fit_pd_law(same, same, same, same, same) is None
    # non-finite rows are left out, not propagated
    theta = d.theta.copy()
    theta[::7] = np.nan
    law = fit_pd_law(theta, d.theta_dot, d.tau, d.theta_d, d.theta_d_dot)
    assert law.samples == d.n_samples - len(range(0, d.n_samples, 7))
    np.testing.assert_allclose(law.kp, np.diag(PDController.paper().kp), rtol=1e-9)
    with pytest.raises(ValueError, match='same shape'):
        fit_pd_law(d.theta, d.theta_dot[:5], d.tau, d.theta_d, d.theta_d_dot)


def _torque_model(seed=0):
    spec = NetworkSpec(N, 'torque', inertia='cholesky', velocity='christoffel', bias=True,
                       inertia_floor=0.05)
    genome = spec.initial_genome() + 0.05 * np.random.default_rng(seed).standard_normal(
        spec.genome_size)
    return RKGNNModel(spec, SCALES, genome, dt=0.001, substeps=1)


def test_closed_loop_model_is_the_torque_model_driven_by_the_law():
    model = _torque_model()
    law = PDLaw(kp=np.array([30.0, 20.0, 10.0]), kd=np.array([3.0, 2.0, 1.0]),
                bias=np.array([1.0, -0.5, 0.2]), fit_ratio=np.zeros(N), samples=100)
    closed = closed_loop_model(model, law)
    assert closed.case == 'pd_gains' and closed.joint_names == model.joint_names
    np.testing.assert_array_equal(closed.genome, model.genome)
    t = np.arange(1001) * 0.001
    reference = SumOfSines.random(N, np.random.default_rng(2), amplitude=0.3,
                                  offsets=np.array([-1.5, 0.0, 0.0]))
    qd, qd_dot = reference.evaluate(t)
    x0 = np.concatenate([qd[0], qd_dot[0]])
    states = closed.simulate(x0, t, theta_d=qd + law.shift(), theta_d_dot=qd_dot)
    assert np.isfinite(states).all()
    tau = law.torque(states[:, :N], states[:, N:], qd, qd_dot)
    replay = model.simulate(x0, t, tau=tau)
    scale = np.ptp(states[:, :N], axis=0)
    assert np.max(np.abs(replay[:, :N] - states[:, :N]) / scale) < 1e-3


def test_closed_loop_model_refuses_other_cases_and_sizes():
    model = _torque_model()
    law = PDLaw(np.ones(2), np.ones(2), np.zeros(2), np.zeros(2), 10)
    with pytest.raises(ValueError, match='joints'):
        closed_loop_model(model, law)
    law3 = PDLaw(np.ones(N), np.ones(N), np.zeros(N), np.zeros(N), 10)
    pd_model = closed_loop_model(model, law3)
    with pytest.raises(ValueError, match="case 'torque'"):
        closed_loop_model(pd_model, law3)


def test_buffer_pairs_states_with_commands_for_the_fit(pd_run):
    d = pd_run
    buffer = StreamBuffer(('a', 'b', 'c'), 0.01, 20.0, 0.1, need_tau=True,
                          need_desired=False)
    assert buffer.controller_samples() is None
    t0 = 1000.0
    for k in range(d.n_samples):
        buffer.add_state(t0 + d.t[k], d.theta[k], d.theta_dot[k], d.tau[k])
    assert buffer.controller_samples() is None  # no command yet
    for k in range(200, d.n_samples):  # commands only from 2 s on
        buffer.add_command(t0 + d.t[k], d.theta_d[k], d.theta_d_dot[k])
    pairs = buffer.controller_samples()
    assert pairs['theta'].shape == (d.n_samples - 200 + 1, N)  # one step of tolerance
    np.testing.assert_allclose(pairs['theta_d'][1:], d.theta_d[200:], atol=1e-12)
    np.testing.assert_allclose(pairs['tau'][1:], d.tau[200:], atol=1e-12)
    law = fit_pd_law(**pairs)  # the first state is paired with the nearest command held
    np.testing.assert_allclose(law.kp, np.diag(PDController.paper().kp), rtol=1e-3)
    no_tau = StreamBuffer(('a', 'b', 'c'), 0.01, 20.0, 0.1, need_tau=False,
                          need_desired=True)
    assert no_tau.controller_samples() is None


def test_snapshot_pairs_commands_on_request_only(pd_run):
    d = pd_run
    buffer = StreamBuffer(('a', 'b', 'c'), 0.01, 20.0, 0.1, need_tau=True,
                          need_desired=False)
    t0 = 1000.0
    for k in range(d.n_samples):
        buffer.add_state(t0 + d.t[k], d.theta[k], d.theta_dot[k], d.tau[k])
        if k >= 300:
            buffer.add_command(t0 + d.t[k], d.theta_d[k], d.theta_d_dot[k])
    plain = list(buffer.snapshot())
    assert len(plain) == 1 and plain[0].theta_d is None and plain[0].n_samples == d.n_samples
    paired = list(buffer.snapshot(pair_commands=True))
    assert len(paired) == 1
    seg = paired[0]
    assert seg.n_samples == d.n_samples - 300 + 1  # from one step before the first command
    np.testing.assert_allclose(seg.theta_d[1:], d.theta_d[300:], atol=1e-9)
    np.testing.assert_allclose(seg.tau[1:], d.tau[300:], atol=1e-9)


# -- the general law: fit_controller, closed_loop -------------------------------------------

ARM = PlanarArm.paper()
KP = np.diag(PDController.paper().kp)
KD = np.diag(PDController.paper().kd)
SERVOS = {
    'pd': Servo(KP, KD),
    'pd_gravity': Servo(KP, KD, gravity='measured', arm=ARM),
    'pd_gravity_desired': Servo(KP, KD, gravity='desired', arm=ARM),
    'pid': Servo(KP, KD, ki=[20.0, 20.0, 20.0]),
}
SENSORS = {'exact': SensorModel.exact(), 'differenced': SensorModel.differenced(1e-4)}


@pytest.fixture(scope='module')
def servo_runs():
    """20 s of the paper's arm per servo and sensor chain (fixed seed)."""
    return {(s, m): simulate(ARM, servo, paper_reference(N), 20.0, noise=SENSORS[m], rng=7)
            for s, servo in SERVOS.items() for m in SENSORS}


@pytest.mark.parametrize('servo', sorted(SERVOS))
@pytest.mark.parametrize('sensors', sorted(SENSORS))
def test_fit_controller_recovers_every_servo_with_or_without_encoder_noise(
        servo_runs, servo, sensors):
    data = servo_runs[servo, sensors]
    law = fit_controller(data, features=TrigFeatures(N), integral=servo == 'pid')
    true = SERVOS[servo]
    # exact data: the filtered equation is the servo's own (to the kernel's accuracy);
    # noise: h' * θ carries 7e-4 rad/s, 1-3 % of the filtered error rate
    rtol = 1e-3 if sensors == 'exact' else 0.03
    np.testing.assert_allclose(law.kp, true.kp, rtol=rtol)
    # Kd and Ki relative to themselves or, when small (0.19, 0), to 0.1 s × Kp
    for fitted, gain in ((law.kd, true.kd), (law.ki, true.ki)):
        assert np.all(np.abs(fitted - gain) <= rtol * (gain + 0.1 * true.kp)), (fitted, gain)
    if servo.startswith('pd_gravity'):
        assert law.theta_input == ('measured' if servo == 'pd_gravity' else 'desired')
    assert law.usable() and np.all(law.fit_ratio < (1e-4 if sensors == 'exact' else 0.02))
    # the law's torque on the true states is the servo's (the integral is held: not PID)
    if servo != 'pid':
        exact = servo_runs[servo, 'exact']
        tau = law.torque(exact.theta, exact.theta_dot, exact.theta_d, exact.theta_d_dot)
        assert np.sqrt(np.mean((tau - exact.tau) ** 2)) < rtol * np.sqrt(np.mean(exact.tau ** 2))


def test_plain_least_squares_is_biased_by_differenced_velocity_and_the_filter_is_not(
        servo_runs):
    data = servo_runs['pd', 'differenced']
    plain = fit_pd_law(data.theta, data.theta_dot, data.tau, data.theta_d, data.theta_d_dot)
    law = fit_controller(data)
    assert plain.kd[2] < 0.85 * KD[2]                     # errors in variables: shrunk
    assert abs(law.kd[2] - KD[2]) < 0.02 * KD[2]
    # the measured (differenced) velocity, filtered on both sides, is far less biased too
    filtered = fit_controller(data, measured_velocity=True)
    assert abs(filtered.kd[2] - KD[2]) < abs(plain.kd[2] - KD[2])


def test_fit_needs_no_velocity_and_takes_commands_from_any_source(servo_runs):
    data = servo_runs['pd', 'exact']
    blind = replace(data, theta_dot=np.zeros_like(data.theta))   # a driver without velocity
    law = fit_controller(blind)
    np.testing.assert_allclose(law.kp, KP, rtol=1e-4)
    np.testing.assert_allclose(law.kd, KD, rtol=1e-4, atol=1e-4)
    # the plan sampled at the state times is the same arrays as joint_commands
    theta_d, theta_d_dot = paper_reference(N).evaluate(data.t)
    planned = replace(blind, theta_d=theta_d, theta_d_dot=theta_d_dot)
    np.testing.assert_allclose(fit_controller(planned).kp, law.kp, rtol=1e-12)
    with pytest.raises(ValueError, match='tau, theta_d and theta_d_dot'):
        fit_controller(replace(data, theta_d=None))


def test_saturated_samples_are_left_out_and_the_limit_is_kept():
    limit = np.array([12.0, 7.0, 1.8])
    data = simulate(ARM, Servo(KP, KD, tau_limit=limit), paper_reference(N), 20.0)
    assert np.all(np.isclose(np.abs(data.tau), limit).sum(axis=0) >= 3)
    law = fit_controller(data)
    np.testing.assert_allclose(law.tau_limit, limit, rtol=1e-9)
    np.testing.assert_allclose(law.kp, KP, rtol=1e-3)
    assert np.all(np.abs(law.torque(data.theta, data.theta_dot, data.theta_d + 1.0,
                                    data.theta_d_dot)) <= limit)


def test_too_little_or_degenerate_data_gives_none(servo_runs):
    data = servo_runs['pd', 'exact']
    assert fit_controller(data.slice(0, 40)) is None         # shorter than the filter
    still = replace(data, theta=data.theta_d.copy(), theta_dot=data.theta_d_dot.copy())
    assert fit_controller(still) is None                     # the error never varied


def _model_for(data, seed=0):
    spec = NetworkSpec(N, 'torque', theta_units=4, inertia='cholesky', velocity='christoffel',
                       bias=True, inertia_floor=0.05)
    scales = Scales.from_datasets([data], 'torque')
    genome = spec.initial_genome(np.random.default_rng(seed))
    genome += 0.05 * np.random.default_rng(seed + 1).standard_normal(spec.genome_size)
    return RKGNNModel(spec, scales, genome, dt=0.01, substeps=4)


def test_closed_loop_folds_the_laws_terms_into_gravity_and_the_command():
    data = simulate(ARM, Servo(KP, KD), paper_reference(N), 5.0)
    model = _model_for(data)
    units = RBFFeatures.from_model(model)
    law = ControllerLaw(kp=KP, kd=KD, ki=np.zeros(N), bias=np.array([0.5, -0.2, 0.1]),
                        integral_term=np.array([0.1, 0.1, -0.1]), feedforward=np.zeros(N),
                        theta_weights=np.array([[2.0, -1.0, 0.5, 0.0], [0.0, 1.0, 0.0, 0.3],
                                                [0.1, 0.0, 0.0, 0.0]]),
                        theta_input='measured', features=units, fit_ratio=np.zeros(N),
                        samples=data.n_samples)
    loop = closed_loop(model, law)
    assert loop.model.case == 'pd_gains' and np.all(loop.fold_error == 0.0)
    t = data.t[:201]
    states = loop.simulate(data.state[0], t, data.theta_d[:201], data.theta_d_dot[:201])
    assert np.isfinite(states).all()
    # the same motion: the arm model driven by the law's torque along it
    tau = law.torque(states[:, :N], states[:, N:], data.theta_d[:201], data.theta_d_dot[:201])
    replay = model.simulate(data.state[0], t, tau=tau)
    assert np.max(np.abs(replay[:, :N] - states[:, :N])) < 1e-3 * np.max(np.ptp(states[:, :N], 0))


def test_closed_loop_projects_a_foreign_basis_along_the_data(servo_runs):
    data = servo_runs['pd_gravity', 'exact']
    model = _model_for(data)
    law = fit_controller(data, features=TrigFeatures(N), theta_input='measured')
    with pytest.raises(ValueError, match='theta_samples'):
        closed_loop(model, law)
    loop = closed_loop(model, law, theta_samples=data.theta)
    assert loop.fold_error.shape == (N,) and np.all(loop.fold_error >= 0.0)
    # the folded gravity is the law's θ-terms projected on the units (+ the command offset)
    g_before = model.gravity_terms(data.theta)
    g_after = RKGNNModel(replace(loop.model.spec, case='torque'), model.scales,
                         loop.model.genome).gravity_terms(data.theta)
    folded = g_before - g_after + law.kp * loop.offset
    terms = law._theta_terms(data.theta, None)
    residual = np.sqrt(np.mean((folded - terms) ** 2, axis=0))
    spread = np.std(terms, axis=0)
    np.testing.assert_allclose(residual / spread, loop.fold_error, rtol=1e-6, atol=1e-9)
    assert np.all(loop.fold_error < 1.0)


def test_a_law_on_the_desired_position_folds_into_the_command(servo_runs):
    data = servo_runs['pd_gravity_desired', 'exact']
    law = fit_controller(data, features=TrigFeatures(N), theta_input='desired')
    shifted = data.theta_d + law.shift(data.theta_d, data.theta_d_dot)
    # Kp (θd' − θ) + Kd ė is the whole law
    via_shift = law.kp * (shifted - data.theta) + law.kd * (data.theta_d_dot - data.theta_dot)
    np.testing.assert_allclose(via_shift, law.torque(data.theta, data.theta_dot, data.theta_d,
                                                     data.theta_d_dot), atol=1e-9)
    loop = closed_loop(_model_for(data), law)
    np.testing.assert_array_equal(loop.model.genome, _model_for(data).genome)


def test_closed_loop_integrates_the_integral_term_instead_of_holding_it():
    data = simulate(ARM, Servo(KP, KD, ki=[20.0, 20.0, 20.0]), paper_reference(N), 3.0)
    model = _model_for(data)
    law = ControllerLaw(kp=KP, kd=KD, ki=np.full(N, 20.0), bias=np.zeros(N),
                        integral_term=np.array([1.0, -0.5, 0.2]), feedforward=np.zeros(N),
                        theta_weights=np.zeros((N, 0)), theta_input='measured', features=None,
                        fit_ratio=np.zeros(N), samples=data.n_samples)
    loop = closed_loop(model, law)
    t = data.t[:201]                                   # 2 s
    qd, qd_dot = data.theta_d[:201], data.theta_d_dot[:201]
    x0 = data.state[0]
    # the exact loop, [θ, θ̇, ∫e] by classical RK4 at 1 ms, the arm model's forward dynamics

    def rate(time, y):
        ref, ref_dot = paper_reference(N).evaluate(time)
        tau = law.torque(y[:N], y[N:2 * N], ref, ref_dot, law.integral_term + 20.0 * y[2 * N:])
        acc = model.forward_dynamics(y[:N], y[N:2 * N], tau=tau)
        return np.concatenate([y[N:2 * N], acc, ref - y[:N]])

    y, h = np.concatenate([x0, np.zeros(N)]), 0.001
    for k in range(2000):
        s = k * h
        k1 = rate(s, y)
        k2 = rate(s + h / 2, y + h / 2 * k1)
        k3 = rate(s + h / 2, y + h / 2 * k2)
        k4 = rate(s + h, y + h * k3)
        y = y + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    held = loop.simulate(x0, t, qd, qd_dot, iterations=0)[-1, :N]
    iterated = loop.simulate(x0, t, qd, qd_dot)[-1, :N]
    held_error = np.linalg.norm(held - y[:N])
    # seen: 0.028 rad held, 3.6e-4 after 3 iterations, 9e-6 after 4
    assert held_error > 1e-2                            # holding it is visibly wrong
    assert np.linalg.norm(iterated - y[:N]) < 0.05 * held_error


def test_data_sampled_coarser_than_the_filter_are_filtered_at_one_sample():
    # model_step 0.1 s (the node's range allows it) is coarser than the default filter
    # (0.03 s): the narrowest filter the samples allow is used instead of raising
    data = simulate(ARM, SERVOS['pd'], paper_reference(N), 20.0, rate=10.0)
    law = fit_controller(data)
    assert law.filter_sigma == pytest.approx(data.dt)
    # exact data at 10 Hz: the kernel's accuracy at that sampling, 0.1 % (seen: 0.06 %)
    np.testing.assert_allclose(law.kp, KP, rtol=1e-3)
    np.testing.assert_allclose(law.kd, KD, rtol=1e-3, atol=1e-3)


@pytest.mark.parametrize('n, max_factors', [(1, 1), (3, 3), (6, 3), (7, 2)])
def test_trig_features_are_the_products_of_cosines_and_sines(n, max_factors):
    features = TrigFeatures(n, max_factors)
    # every product of at most max_factors factors, one cos or sin per joint, no constant
    count = sum(math.comb(n, k) * 2 ** k for k in range(1, min(n, max_factors) + 1))
    assert features.size == count
    theta = np.random.default_rng(n).normal(scale=3.0, size=(4, 5, n))
    phi = features(theta)
    assert phi.shape == (4, 5, count)
    for f, term in enumerate(features.terms):
        expected = np.ones((4, 5))
        for joint, kind in term:
            expected = expected * (np.sin if kind else np.cos)(theta[..., joint])
        assert np.array_equal(phi[..., f], expected)
    assert np.array_equal(features(theta[1, 2]), phi[1, 2])  # one configuration alike

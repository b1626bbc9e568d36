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

"""The linear inverse-dynamics fit in the trigonometric basis (core/fitting/linear.py)."""

import numpy as np
import pytest
from rkgnn_ros.core.fitting.linear import (LinearDynamics, Samples, samples_from_datasets,
                                           torque_nrmse)
from rkgnn_ros.core.model.trig import TrigBasis
from rkgnn_ros.core.model.trig_certificate import certify_inertia
from rkgnn_ros.core.model.trig_dynamics import Layout, regressor
from rkgnn_ros.core.sim.plant import PDController, PlanarArm
from rkgnn_ros.core.sim.simulate import NoiseModel, simulate, simulate_open_loop
from rkgnn_ros.core.sim.trajectories import hanging_pose, paper_reference, SumOfSines
from spatial_arm import SpatialArm

ARM = PlanarArm.paper()
PD = PDController.paper()
KP, KD = np.diag(PD.kp), np.diag(PD.kd)


def run(reference, duration, noise=None, seed=0):
    """Simulate the paper's arm under its PD; 1 s of start-up transient is dropped."""
    data = simulate(ARM, PD, reference, duration + 1.0, rate=100.0, t0=-1.0, noise=noise,
                    rng=seed)
    return data.slice(100, data.n_samples)


def other_pose_reference():
    pose = hanging_pose(3) + np.array([0.6, -0.5, 0.6])
    return SumOfSines.random(3, np.random.default_rng(5), n_terms=4, amplitude=0.4,
                             min_frequency_hz=0.15, max_frequency_hz=0.7, offsets=pose)


@pytest.fixture(scope='module')
def training():
    return run(paper_reference(3), 12.0)


@pytest.fixture(scope='module')
def heldout():
    return run(other_pose_reference(), 6.0, seed=1)


@pytest.fixture(scope='module')
def planar_fit(training):
    return LinearDynamics(TrigBasis(3, planar=True)).fit(training, 'torque')


def random_coefficients(basis, rng):
    lay = Layout.of(basis)
    coef = 0.1 * rng.standard_normal(lay.size)
    coef[lay.viscous] = np.abs(coef[lay.viscous])
    coef[lay.coulomb] = np.abs(coef[lay.coulomb])
    return coef


# -- the regressor ------------------------------------------------------------------------

@pytest.mark.parametrize('settings', [{'mass_degree': 2}, {'planar': True},
                                      {'planar': True, 'tied': True}])
def test_regressor_times_coefficients_is_the_models_inverse_dynamics(settings):
    rng = np.random.default_rng(1)
    basis = TrigBasis(3, **settings)
    coef = random_coefficients(basis, rng)
    model = LinearDynamics.from_coefficients(basis, coef)
    theta, qd, qdd = (rng.uniform(-3, 3, (25, 3)), rng.normal(0, 2, (25, 3)),
                      rng.normal(0, 5, (25, 3)))
    y = regressor(basis, theta, qd, qdd, 0.05)
    np.testing.assert_allclose(y @ coef, model.inverse_dynamics(theta, qd, qdd), atol=1e-12)
    # the case-3 columns: the PD torque with a minus sign
    err, derr = rng.normal(size=(25, 3)), rng.normal(size=(25, 3))
    y3 = regressor(basis, theta, qd, qdd, 0.05, err, derr)
    gains = np.concatenate([coef, KP, KD])
    np.testing.assert_allclose(y3 @ gains, y @ coef - KP * err - KD * derr, atol=1e-12)


def test_velocity_terms_are_the_christoffel_terms_of_m():
    rng = np.random.default_rng(2)
    basis = TrigBasis(3, mass_degree=2)
    model = LinearDynamics.from_coefficients(basis, random_coefficients(basis, rng))
    theta, qd = rng.uniform(-3, 3, 3), rng.normal(0, 2, 3)
    step = 1e-6
    dm = np.stack([(model.raw_mass_matrix(theta + step * e)
                    - model.raw_mass_matrix(theta - step * e)) / (2 * step)
                   for e in np.eye(3)], axis=-1)                      # (i, j, k) = ∂_k M_ij
    v = np.einsum('ijk,j,k->i', dm, qd, qd) - 0.5 * np.einsum('jki,j,k->i', dm, qd, qd)
    np.testing.assert_allclose(model.velocity_terms(theta, qd), v, atol=1e-7)
    # with V from M, θ̇ᵀ(Ṁ - 2C)θ̇ = 0: the power of V is ½ θ̇ᵀ Ṁ θ̇
    m_dot = dm @ qd
    assert abs(qd @ model.velocity_terms(theta, qd) - 0.5 * qd @ m_dot @ qd) < 1e-7


def test_gravity_is_the_gradient_of_the_potential():
    rng = np.random.default_rng(3)
    basis = TrigBasis(3)
    model = LinearDynamics.from_coefficients(basis, random_coefficients(basis, rng))
    theta = rng.uniform(-3, 3, 3)
    step = 1e-6
    grad = [(model.potential(theta + step * e) - model.potential(theta - step * e)) / (2 * step)
            for e in np.eye(3)]
    np.testing.assert_allclose(model.gravity_terms(theta), grad, atol=1e-8)


# -- exact recovery -----------------------------------------------------------------------

@pytest.mark.parametrize('tied', [False, True])
def test_exact_planar_data_give_the_arm_on_the_whole_torus(training, tied):
    acc = ARM.forward_dynamics(training.theta, training.theta_dot, training.tau)
    samples = Samples(training.theta, training.theta_dot, acc, training.tau)
    model = LinearDynamics(TrigBasis(3, planar=True, tied=tied))
    model.fit_samples(samples, 'torque')
    theta = np.random.default_rng(4).uniform(-np.pi, np.pi, (2000, 3))
    truth = ARM.mass_matrix(theta)
    assert np.abs(model.mass_matrix(theta) - truth).max() < 1e-5 * np.abs(truth).max()
    gravity = ARM.gravity_terms(theta)
    assert np.abs(model.gravity_terms(theta) - gravity).max() < 1e-5 * np.abs(gravity).max()
    np.testing.assert_allclose(model.viscous_, ARM.params.viscous, rtol=1e-4)
    np.testing.assert_allclose(model.coulomb_, ARM.params.coulomb, rtol=1e-4)


def test_a_spatial_arm_is_recovered_far_from_its_data():
    arm = SpatialArm.elbow()
    rng = np.random.default_rng(5)
    count = 600
    theta = rng.uniform(-1.0, 1.0, (count, 3))               # a third of each joint's turn
    qd, qdd = rng.normal(0, 1.5, (count, 3)), rng.normal(0, 4, (count, 3))
    tau = arm.inverse_dynamics(theta, qd, qdd)
    model = LinearDynamics(TrigBasis(3, mass_degree=2), max_cells=0)
    model.fit_samples(Samples(theta, qd, qdd, tau), 'torque')
    far = rng.uniform(-np.pi, np.pi, (500, 3))
    truth = arm.mass_matrix(far)
    assert np.abs(model.mass_matrix(far) - truth).max() < 1e-4 * np.abs(truth).max()
    gravity = arm.gravity_terms(far)
    assert np.abs(model.gravity_terms(far) - gravity).max() < 1e-4 * np.abs(gravity).max()


# -- the fit on simulated runs ------------------------------------------------------------

def test_heldout_torque_and_rollouts_around_another_pose(planar_fit, heldout):
    model = planar_fit
    acc = samples_from_datasets(heldout, 'torque', window=model.window_).theta_ddot
    truth = torque_nrmse(ARM.inverse_dynamics(heldout.theta, heldout.theta_dot, acc),
                         heldout.tau)
    error = torque_nrmse(model.inverse_dynamics(heldout.theta, heldout.theta_dot, acc),
                         heldout.tau)
    assert error < 0.003 and error < truth + 0.002
    rollout = model.simulate(heldout.state[0], heldout.t, tau=heldout.tau)
    reference = simulate_open_loop(ARM, heldout.tau, heldout.t, heldout.state[0], hold=False)
    scale = np.std(heldout.theta, axis=0)
    assert np.all(np.sqrt(np.mean((rollout[:, :3] - reference.theta) ** 2, 0)) < 0.01 * scale)


def test_the_ridge_weight_is_chosen_on_held_out_samples(training):
    # a torque with no structure: the training fit would always prefer the weakest ridge,
    # the held-out samples prefer the strongest
    rng = np.random.default_rng(6)
    noise_only = training.__class__(t=training.t, theta=training.theta,
                                    theta_dot=training.theta_dot,
                                    tau=rng.normal(size=training.tau.shape))
    ridges = (1e-10, 1e-6, 1e-2, 1.0)
    model = LinearDynamics(TrigBasis(3, planar=True), ridges=ridges, certify=False)
    model.fit(noise_only, 'torque')
    assert [r for r, _ in model.validation_] == list(ridges)
    assert model.ridge_ == 1.0
    clean = LinearDynamics(TrigBasis(3, planar=True), ridges=ridges, certify=False)
    assert clean.fit(training, 'torque').ridge_ == 1e-10


def test_friction_is_never_negative(training):
    # a torque with a negative viscous term: unconstrained least squares would follow it
    acc = ARM.forward_dynamics(training.theta, training.theta_dot, training.tau)
    tau = training.tau - 2.0 * ARM.params.viscous * training.theta_dot   # viscous -(0.5, 0.3, 0.1)
    model = LinearDynamics(TrigBasis(3, planar=True), certify=False)
    model.fit_samples(Samples(training.theta, training.theta_dot, acc, tau), 'torque')
    assert np.all(model.viscous_ >= 0.0) and np.all(model.coulomb_ >= 0.0)
    np.testing.assert_allclose(model.viscous_, 0.0, atol=1e-9)
    free = np.linalg.lstsq(
        regressor(model.basis, training.theta, training.theta_dot, acc, 0.05).reshape(
            -1, model.layout_.size), tau.reshape(-1), rcond=None)[0]
    np.testing.assert_allclose(free[model.layout_.viscous], [-0.5, -0.3, -0.1], atol=1e-6)


def test_noisy_encoders_choose_a_wider_derivative_window(training):
    noisy = run(paper_reference(3), 12.0, noise=NoiseModel.realistic(), seed=3)
    clean = LinearDynamics(TrigBasis(3, planar=True), certify=False).fit(training, 'torque')
    rough = LinearDynamics(TrigBasis(3, planar=True), certify=False).fit(noisy, 'torque')
    assert clean.window_ == 7
    assert rough.window_ >= 21


def test_case_2_keeps_the_known_gains_and_predicts_in_closed_loop(training, heldout):
    model = LinearDynamics(TrigBasis(3, planar=True)).fit(training, 'pd_gains', KP, KD)
    np.testing.assert_array_equal(model.kp_, KP)
    reference = other_pose_reference()
    rollout = model.simulate(heldout.state[0], heldout.t, reference=reference)
    scale = np.std(heldout.theta, axis=0)
    assert np.all(np.sqrt(np.mean((rollout[:, :3] - heldout.theta) ** 2, 0)) < 0.01 * scale)


def test_case_3_identifies_the_normalised_model(training, heldout):
    model = LinearDynamics(TrigBasis(3, planar=True), gain_normalisation=1.0)
    model.fit(training, 'unknown')
    assert model.kp_.mean() == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(model.kp_, KP / KP.mean(), rtol=1e-4)
    np.testing.assert_allclose(model.kd_, KD / KP.mean(), rtol=1e-3, atol=1e-4)
    # the scale is the one thing not identified: one known number restores the torques
    physical = model.scaled(KP.mean())
    np.testing.assert_allclose(physical.kp_, KP, rtol=1e-4)
    acc = samples_from_datasets(heldout, 'torque', window=7).theta_ddot
    assert torque_nrmse(physical.inverse_dynamics(heldout.theta, heldout.theta_dot, acc),
                        heldout.tau) < 0.003
    # and the motion it predicts does not depend on it
    reference = other_pose_reference()
    a = model.simulate(heldout.state[0], heldout.t[:200], reference=reference)
    b = physical.simulate(heldout.state[0], heldout.t[:200], reference=reference)
    np.testing.assert_allclose(a, b, atol=1e-9)


def test_refuses_before_fit_and_without_what_the_case_needs(training):
    model = LinearDynamics(3)
    with pytest.raises(RuntimeError, match='not fitted'):
        model.mass_matrix(np.zeros(3))
    with pytest.raises(ValueError, match='needs measured torque'):
        model.fit(training.__class__(t=training.t, theta=training.theta,
                                     theta_dot=training.theta_dot), 'torque')
    with pytest.raises(ValueError, match='kp and kd'):
        model.fit(training, 'pd_gains')
    with pytest.raises(ValueError, match='case must be'):
        model.fit(training, 'psychic')


# -- M positive definite on the whole range -----------------------------------------------

def test_planar_fit_is_certified_positive_on_the_torus(planar_fit):
    cert = planar_fit.certificate_
    assert cert.certified and cert.lower_bound >= planar_fit.min_eigenvalue_ > 0.0
    theta = np.random.default_rng(7).uniform(-np.pi, np.pi, (20000, 3))
    s = planar_fit.inertia_scale_
    lam = np.linalg.eigvalsh(planar_fit.raw_mass_matrix(theta) * np.outer(s, s))[:, 0]
    assert lam.min() >= cert.lower_bound              # the bound is a bound
    assert lam.min() <= cert.smallest_seen + 1e-12


def test_a_poorly_excited_generic_basis_stays_positive_far_from_its_data():
    # ±0.3 rad about the hanging pose with encoder noise: the degree-2 basis (112
    # coefficients) is free far away, and its unconstrained M is indefinite there
    narrow = SumOfSines.random(3, np.random.default_rng(2), n_terms=3, amplitude=0.3,
                               min_frequency_hz=0.2, max_frequency_hz=0.8)
    data = run(narrow, 8.0, noise=NoiseModel.realistic())
    free = LinearDynamics(TrigBasis(3, mass_degree=2), certify=False, window=31)
    free.fit(data, 'torque')
    model = LinearDynamics(TrigBasis(3, mass_degree=2), window=31, max_cells=2000)
    model.fit(data, 'torque')
    theta = np.random.default_rng(8).uniform(-np.pi, np.pi, (5000, 3))
    s = model.inertia_scale_
    assert np.linalg.eigvalsh(free.raw_mass_matrix(theta))[:, 0].min() < 0.0
    lam = np.linalg.eigvalsh(model.mass_matrix(theta) * np.outer(s, s))[:, 0]
    assert lam.min() >= model.min_eigenvalue_ * (1 - 1e-9)
    # the constrained refit makes the guard a rare event (it is measured, not assumed)
    raw = np.linalg.eigvalsh(model.raw_mass_matrix(theta) * np.outer(s, s))[:, 0]
    assert model.cuts_ > 0
    assert np.mean(raw < model.min_eigenvalue_) < np.mean(
        np.linalg.eigvalsh(free.raw_mass_matrix(theta) * np.outer(s, s))[:, 0]
        < model.min_eigenvalue_)
    # and the fit to the data is not given up for it
    acc = samples_from_datasets(data, 'torque', window=31).theta_ddot
    assert torque_nrmse(model.inverse_dynamics(data.theta, data.theta_dot, acc),
                        data.tau) < 0.05


def test_the_certificate_finds_an_indefinite_mass_matrix():
    basis = TrigBasis(2, planar=True)
    lay = Layout.of(basis)
    coef = np.zeros(lay.size)
    # M = [[1 + 0.9 cos θ2·k, 0], [0, 1]] with k > 1 is indefinite near θ2 = π
    start = 0
    for (a, b), ix in zip(basis.mass_entries, basis.mass_index):
        names = basis.names()
        for pos, f in enumerate(ix):
            if a == b and names[f] == '1':
                coef[start + pos] = 1.0
            if (a, b) == (0, 0) and names[f] == 'cos(θ2)':
                coef[start + pos] = 1.5
        start += ix.size
    cert = certify_inertia(basis, coef[lay.mass], 0.01)
    assert not cert.certified and cert.lower_bound < 0.0
    assert cert.violations.shape[0] > 0 and cert.smallest_seen < 0.0
    assert abs(abs(cert.worst_theta[1]) - np.pi) < 0.5
    # while a positive one is certified, with a bound below the true minimum (0.5 - 0)
    coef_ok = coef.copy()
    coef_ok[coef == 1.5] = 0.5
    cert = certify_inertia(basis, coef_ok[lay.mass], 0.1)
    assert cert.certified and 0.1 <= cert.lower_bound <= 0.5 + 1e-12

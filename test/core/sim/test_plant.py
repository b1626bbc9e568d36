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

"""The planar arm: closed forms, Lagrangian identities, energy, regressor; its PD servo."""

import numpy as np
from plant_helpers import random_arm, random_states
import pytest
from rkgnn_ros.core.sim.parameters import ArmParameters, MASS_MODELS
from rkgnn_ros.core.sim.plant import PDController, PlanarArm
from scipy.integrate import solve_ivp

SIZES = (1, 2, 3, 5)


@pytest.fixture
def rng():
    return np.random.default_rng(20260521)


# -- parameters ---------------------------------------------------------------------------

def test_paper_parameters():
    p = ArmParameters.paper()
    np.testing.assert_array_equal(p.masses, [6.0, 4.0, 3.0])
    np.testing.assert_array_equal(p.lengths, [0.2, 0.3, 0.1])
    assert p.mass_model == 'point' and p.gravity == 9.81 and p.n_joints == 3
    np.testing.assert_array_equal(p.viscous, [0.5, 0.3, 0.1])
    np.testing.assert_array_equal(p.coulomb, [0.3, 0.2, 0.1])
    np.testing.assert_array_equal(p.com_distances, p.lengths)
    rod = ArmParameters.paper('rod')
    np.testing.assert_allclose(rod.com_distances, 0.5 * rod.lengths)
    np.testing.assert_allclose(rod.joint_inertias, rod.masses * rod.lengths ** 2 / 3.0)


@pytest.mark.parametrize('kwargs, match', [
    ({'masses': [1.0, -1.0], 'lengths': [0.1, 0.2]}, 'masses'),
    ({'masses': [1.0, 1.0], 'lengths': [0.1, 0.0]}, 'lengths'),
    ({'masses': [1.0, 1.0], 'lengths': [0.1]}, 'lengths'),
    ({'masses': [], 'lengths': []}, 'masses'),
    ({'masses': [1.0, np.nan], 'lengths': [0.1, 0.2]}, 'masses'),
    ({'masses': [1.0], 'lengths': [0.1], 'mass_model': 'shell'}, 'mass_model'),
    ({'masses': [1.0], 'lengths': [0.1], 'viscous': [-0.1]}, 'viscous'),
    ({'masses': [1.0], 'lengths': [0.1], 'coulomb': [0.1, 0.2]}, 'coulomb'),
    ({'masses': [1.0], 'lengths': [0.1], 'coulomb_velocity': 0.0}, 'coulomb_velocity'),
    ({'masses': [1.0], 'lengths': [0.1], 'gravity': np.inf}, 'gravity'),
])
def test_parameters_are_validated(kwargs, match):
    with pytest.raises(ValueError, match=match):
        ArmParameters(**kwargs)


def test_wrong_state_shape_is_rejected():
    arm = PlanarArm.paper()
    with pytest.raises(ValueError, match='theta'):
        arm.mass_matrix(np.zeros(2))
    with pytest.raises(ValueError, match='tau'):
        arm.forward_dynamics(np.zeros(3), np.zeros(3), np.zeros(4))


# -- closed forms -------------------------------------------------------------------------

@pytest.mark.parametrize('mass_model', MASS_MODELS)
@pytest.mark.parametrize('n', SIZES)
def test_mass_matrix_symmetric_positive_definite(n, mass_model, rng):
    arm = random_arm(n, mass_model, rng)
    theta = rng.uniform(-np.pi, np.pi, (200, n))
    m = arm.mass_matrix(theta)
    assert m.shape == (200, n, n)
    np.testing.assert_allclose(m, np.swapaxes(m, -1, -2), atol=1e-14)
    assert np.all(np.linalg.eigvalsh(m) > 0.0)


@pytest.mark.parametrize('mass_model', MASS_MODELS)
def test_one_link_closed_form(mass_model, rng):
    m, length, g = 2.5, 0.4, 9.81
    arm = PlanarArm(ArmParameters([m], [length], mass_model, gravity=g))
    c, inertia = (length, 0.0) if mass_model == 'point' else (length / 2, m * length ** 2 / 12)
    theta, theta_dot, _ = random_states(1, rng)
    np.testing.assert_allclose(arm.mass_matrix(theta)[:, 0, 0], m * c ** 2 + inertia)
    np.testing.assert_allclose(arm.velocity_terms(theta, theta_dot), 0.0, atol=1e-15)
    np.testing.assert_allclose(arm.gravity_terms(theta)[:, 0], m * g * c * np.cos(theta[:, 0]))


@pytest.mark.parametrize('mass_model', MASS_MODELS)
def test_two_link_textbook_closed_form(mass_model, rng):
    m1, m2, l1, l2, g = 3.0, 2.0, 0.4, 0.3, 9.81
    arm = PlanarArm(ArmParameters([m1, m2], [l1, l2], mass_model, gravity=g))
    if mass_model == 'point':
        c1, c2, i1, i2 = l1, l2, 0.0, 0.0
    else:
        c1, c2, i1, i2 = l1 / 2, l2 / 2, m1 * l1 ** 2 / 12, m2 * l2 ** 2 / 12
    theta, theta_dot, _ = random_states(2, rng)
    q1, q2 = theta.T
    w1, w2 = theta_dot.T
    m11 = m1 * c1 ** 2 + i1 + m2 * (l1 ** 2 + c2 ** 2 + 2 * l1 * c2 * np.cos(q2)) + i2
    m12 = m2 * (c2 ** 2 + l1 * c2 * np.cos(q2)) + i2
    m22 = m2 * c2 ** 2 + i2 + 0 * q2
    expected_m = np.stack([np.stack([m11, m12], -1), np.stack([m12, m22], -1)], -2)
    hh = m2 * l1 * c2 * np.sin(q2)
    expected_v = np.stack([-hh * (2 * w1 * w2 + w2 ** 2), hh * w1 ** 2], -1)
    g2 = m2 * g * c2 * np.cos(q1 + q2)
    expected_g = np.stack([(m1 * c1 + m2 * l1) * g * np.cos(q1) + g2, g2], -1)
    np.testing.assert_allclose(arm.mass_matrix(theta), expected_m, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(arm.velocity_terms(theta, theta_dot), expected_v,
                               rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(arm.gravity_terms(theta), expected_g, rtol=1e-13, atol=1e-13)


# -- Lagrangian identities ----------------------------------------------------------------

def mass_matrix_gradient(arm, theta, eps=1e-6):
    """Return ∂M/∂θ_k by central differences, shape (n, n, n) with k first."""
    n = theta.size
    out = np.empty((n, n, n))
    for k in range(n):
        step = np.zeros(n)
        step[k] = eps
        out[k] = (arm.mass_matrix(theta + step) - arm.mass_matrix(theta - step)) / (2 * eps)
    return out


@pytest.mark.parametrize('mass_model', MASS_MODELS)
@pytest.mark.parametrize('n', (2, 3, 5))
def test_velocity_terms_match_lagrangian_finite_differences(n, mass_model, rng):
    # V = Ṁ θ̇ - ½ ∂/∂θ (θ̇ᵀ M θ̇), with ∂M/∂θ from finite differences
    arm = random_arm(n, mass_model, rng)
    for theta, theta_dot in zip(*random_states(n, rng, count=10)[:2]):
        dm = mass_matrix_gradient(arm, theta)
        m_dot = np.einsum('kij,k->ij', dm, theta_dot)
        expected = m_dot @ theta_dot - 0.5 * np.einsum('kij,i,j->k', dm, theta_dot, theta_dot)
        v = arm.velocity_terms(theta, theta_dot)
        np.testing.assert_allclose(v, expected, rtol=1e-6, atol=1e-7 * np.abs(expected).max())
        # the power balance behind skew symmetry: θ̇ᵀ V = ½ θ̇ᵀ Ṁ θ̇
        assert theta_dot @ v == pytest.approx(0.5 * theta_dot @ m_dot @ theta_dot, rel=1e-6)


@pytest.mark.parametrize('mass_model', MASS_MODELS)
def test_gravity_is_gradient_of_potential_energy(mass_model, rng):
    arm = random_arm(3, mass_model, rng)
    theta = rng.uniform(-np.pi, np.pi, 3)
    zero = np.zeros(3)
    eps = 1e-6
    grad = np.array([(arm.energy(theta + eps * e, zero) - arm.energy(theta - eps * e, zero))
                     / (2 * eps) for e in np.eye(3)])
    np.testing.assert_allclose(arm.gravity_terms(theta), grad, rtol=1e-7, atol=1e-8)


@pytest.mark.parametrize('mass_model', MASS_MODELS)
@pytest.mark.parametrize('n', SIZES)
def test_forward_inverts_inverse_dynamics(n, mass_model, rng):
    arm = random_arm(n, mass_model, rng)
    theta, theta_dot, theta_ddot = random_states(n, rng)
    tau = arm.inverse_dynamics(theta, theta_dot, theta_ddot)
    m = arm.mass_matrix(theta)
    np.testing.assert_allclose(
        tau, np.einsum('...ij,...j->...i', m, theta_ddot) + arm.velocity_terms(theta, theta_dot)
        + arm.gravity_terms(theta) + arm.friction_terms(theta_dot), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(arm.forward_dynamics(theta, theta_dot, tau), theta_ddot,
                               rtol=1e-9, atol=1e-9)
    # the compiled single-state kernel against the batched numpy reference
    single = np.array([arm.forward_dynamics(*s) for s in zip(theta, theta_dot, tau)])
    np.testing.assert_allclose(single, arm.forward_dynamics(theta, theta_dot, tau),
                               rtol=1e-12, atol=1e-12)
    x = np.concatenate([theta, theta_dot], axis=-1)
    np.testing.assert_allclose(arm.dynamics(x, tau)[:, n:], theta_ddot, rtol=1e-9, atol=1e-9)


def test_kernel_constants_are_copies():
    arm = PlanarArm.paper()
    before = arm.forward_dynamics(np.zeros(3), np.zeros(3), np.zeros(3))
    constants = arm.kernel_constants()
    constants.d[:] = 0.0
    constants.gh[:] = 0.0
    np.testing.assert_array_equal(arm.forward_dynamics(np.zeros(3), np.zeros(3), np.zeros(3)),
                                  before)
    assert np.all(arm.kernel_constants().gh != 0.0)


def test_friction_terms():
    arm = PlanarArm.paper()
    p = arm.params
    w = np.array([0.0, 0.05, -10.0])
    np.testing.assert_allclose(
        arm.friction_terms(w), p.viscous * w + p.coulomb * np.tanh(w / 0.05))
    assert arm.friction_terms(np.zeros(3)) == pytest.approx(np.zeros(3))


# -- energy -------------------------------------------------------------------------------

def passive_rollout(arm, x0, duration, count=400):
    n = arm.n_joints
    zero = np.zeros(n)
    t = np.linspace(0.0, duration, count)
    sol = solve_ivp(lambda s, x: arm.dynamics(x, zero), (0.0, duration), x0, method='DOP853',
                    rtol=1e-12, atol=1e-12, t_eval=t)
    assert sol.success
    return arm.energy(sol.y[:n].T, sol.y[n:].T)


@pytest.mark.parametrize('mass_model', MASS_MODELS)
def test_energy_conserved_without_friction_and_control(mass_model):
    arm = PlanarArm(ArmParameters.paper(mass_model).without_friction())
    x0 = np.array([0.3, -0.8, 1.2, 0.5, -1.0, 2.0])
    energy = passive_rollout(arm, x0, 3.0)
    swing = np.ptp(arm.gravity_terms(np.zeros(3)))  # scale of the energy exchanged
    assert np.max(np.abs(energy - energy[0])) < 1e-8 * max(abs(energy[0]), swing)


@pytest.mark.parametrize('mass_model', MASS_MODELS)
def test_energy_decreases_monotonically_with_friction(mass_model):
    arm = PlanarArm.paper(mass_model)
    energy = passive_rollout(arm, np.array([0.3, -0.8, 1.2, 0.5, -1.0, 2.0]), 3.0)
    assert np.all(np.diff(energy) <= 1e-10)
    assert energy[-1] < energy[0] - 1.0


# -- regressor ----------------------------------------------------------------------------

@pytest.mark.parametrize('mass_model', MASS_MODELS)
@pytest.mark.parametrize('n', SIZES)
def test_regressor_reproduces_inverse_dynamics(n, mass_model, rng):
    arm = random_arm(n, mass_model, rng)
    theta, theta_dot, theta_ddot = random_states(n, rng)
    tau = arm.inverse_dynamics(theta, theta_dot, theta_ddot)
    y = arm.regressor(theta, theta_dot, theta_ddot)
    assert y.shape == (theta.shape[0], n, 5 * n)
    assert arm.parameter_vector().shape == (5 * n,) and len(arm.parameter_names()) == 5 * n
    np.testing.assert_allclose(y @ arm.parameter_vector(), tau, rtol=1e-12, atol=1e-12)
    y_base = arm.base_regressor(theta, theta_dot, theta_ddot)
    np.testing.assert_allclose(y_base @ arm.base_parameter_vector(), tau,
                               rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize('mass_model', MASS_MODELS)
@pytest.mark.parametrize('n', (2, 3, 5))
def test_least_squares_identification_on_random_states(n, mass_model, rng):
    arm = random_arm(n, mass_model, rng)
    theta, theta_dot, theta_ddot = random_states(n, rng, count=200)
    tau = arm.inverse_dynamics(theta, theta_dot, theta_ddot)
    y = arm.regressor(theta, theta_dot, theta_ddot).reshape(-1, 5 * n)
    # rank deficient: the masses are combinations of the other columns
    assert np.linalg.matrix_rank(y) == 4 * n
    p_hat, *_ = np.linalg.lstsq(y, tau.ravel(), rcond=None)
    np.testing.assert_allclose(y @ p_hat, tau.ravel(), rtol=1e-9, atol=1e-9)
    # the minimum-norm estimate differs from p only in the null space: it predicts new states
    fresh = random_states(n, rng, count=50)
    np.testing.assert_allclose(arm.regressor(*fresh) @ p_hat, arm.inverse_dynamics(*fresh),
                               rtol=1e-8, atol=1e-8)
    # the base parameters are recovered exactly
    y_base = arm.base_regressor(theta, theta_dot, theta_ddot).reshape(-1, 4 * n)
    assert np.linalg.matrix_rank(y_base) == 4 * n
    b_hat, *_ = np.linalg.lstsq(y_base, tau.ravel(), rcond=None)
    np.testing.assert_allclose(b_hat, arm.base_parameter_vector(), rtol=1e-8, atol=1e-10)


def test_without_gravity_the_first_moment_of_link_one_is_unidentifiable(rng):
    arm = random_arm(3, 'rod', rng, gravity=0.0)
    y_base = arm.base_regressor(*random_states(3, rng))
    np.testing.assert_array_equal(y_base[..., 0], 0.0)
    assert np.linalg.matrix_rank(y_base.reshape(-1, 12)) == 11


def test_pd_controller():
    ctl = PDController.paper()
    np.testing.assert_array_equal(np.diag(ctl.kp), [32.84, 42.05, 42.31])
    np.testing.assert_array_equal(np.diag(ctl.kd), [42.44, 0.19, 4.86])
    theta = np.array([[0.1, 0.2, 0.3], [0.0, 0.0, 0.0]])
    tau = ctl.torque(theta, np.ones((2, 3)), np.zeros(3), np.zeros(3))
    np.testing.assert_allclose(tau[0], -np.diag(ctl.kp) * theta[0] - np.diag(ctl.kd))
    assert tau.shape == (2, 3)
    limited = PDController(np.diag(ctl.kp), np.diag(ctl.kd), tau_limit=[1.0, 2.0, 3.0])
    out = limited.torque(np.zeros(3), np.zeros(3), np.array([1.0, -1.0, 0.01]), np.zeros(3))
    np.testing.assert_allclose(out, [1.0, -2.0, 0.4231])
    with pytest.raises(ValueError, match='kd'):
        PDController([1.0, 2.0], [1.0, 2.0, 3.0])

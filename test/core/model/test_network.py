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
The function network N_f evaluated in numpy: inertia modes, terms, by-hand systems.

Plain pytest, no middleware. Hand-built genomes with unit scales stand for systems whose
accelerations are known in closed form.
"""

import math

from model_helpers import set_block, unit_scales
import numpy as np
import pytest
from rkgnn_ros.core.model.network import BatchedNetwork, pair_products
from rkgnn_ros.core.model.spec import NetworkSpec

CASES = ('torque', 'pd_gains', 'unknown')


# ----- BatchedNetwork

def random_network(spec, pop=40, seed=0, scale=1.0, kp=None, kd=None, scales=None):
    scales = scales if scales is not None else unit_scales(spec.n_joints)
    rng = np.random.default_rng(seed)
    genomes = spec.initial_genome() + scale * rng.standard_normal((pop, spec.genome_size))
    return BatchedNetwork(spec, spec.decode(genomes, scales), scales, kp, kd)


@pytest.mark.parametrize('n', [1, 2, 3, 5])
def test_cholesky_mode_gives_symmetric_positive_definite_inertia(n):
    scales = unit_scales(n, torque=np.linspace(1.0, 3.0, n), acceleration=np.full(n, 4.0))
    spec = NetworkSpec(n, inertia='cholesky', bias=True)
    net = random_network(spec, pop=200, seed=n, scale=1.0, scales=scales)
    rng = np.random.default_rng(10 + n)
    theta = rng.uniform(-2.0, 2.0, (200, n))
    mass = net.mass_matrix(theta)
    assert mass.shape == (200, n, n)
    np.testing.assert_allclose(mass, np.swapaxes(mass, 1, 2), rtol=1e-13, atol=1e-13)
    eig = np.linalg.eigvalsh(mass)
    # M = L Lᵀ + diag(ε) with ε = 1e-3 × inertia scale
    assert np.all(eig >= 0.999 * np.min(spec.inertia_epsilon(scales)))
    assert np.all(net.min_minor(theta) > 0.0)


def test_cholesky_mass_matrix_by_hand():
    spec = NetworkSpec(2, inertia='cholesky', theta_units=0, bias=True)
    scales = unit_scales(2)
    g = np.zeros(spec.genome_size)
    lower = [1.5, -0.5, 2.0]  # L[0,0], L[1,0], L[1,1]: the packed lower triangle, by rows
    set_block(spec, g, 'theta_bias', lower + [0.0] * (spec.n_outputs - 3))
    net = BatchedNetwork(spec, spec.decode(g, scales), scales)
    big_l = np.array([[1.5, 0.0], [-0.5, 2.0]])
    expected = big_l @ big_l.T + 1e-3 * np.eye(2)  # default inertia_floor 1e-3
    np.testing.assert_allclose(net.mass_matrix(np.zeros((1, 2)))[0], expected, rtol=1e-15)
    spec = NetworkSpec(2, inertia='cholesky', theta_units=0, bias=True, inertia_floor=0.25)
    net = BatchedNetwork(spec, spec.decode(g, unit_scales(2, torque=[2.0, 3.0])),
                         unit_scales(2, torque=[2.0, 3.0]))
    expected = 2.0 * (big_l @ big_l.T) + np.diag([0.5, 0.75])  # L's row i scales as sqrt(ms_i)
    expected[1, 1] = 3.0 * (0.25 + 4.0) + 0.75
    expected[0, 1] = expected[1, 0] = np.sqrt(2.0 * 3.0) * (1.5 * -0.5)
    np.testing.assert_allclose(net.mass_matrix(np.zeros((1, 2)))[0], expected, rtol=1e-14)


@pytest.mark.parametrize('n', [2, 3, 4])
def test_penalty_mode_is_symmetric_and_may_be_indefinite(n):
    spec = NetworkSpec.paper(n)
    net = random_network(spec, pop=100, seed=n, scale=1.0)
    theta = np.random.default_rng(n).uniform(-1.0, 1.0, (100, n))
    mass = net.mass_matrix(theta)
    np.testing.assert_array_equal(mass, np.swapaxes(mass, 1, 2))
    minors = net.min_minor(theta)
    assert np.any(minors < 0.0) and np.any(minors > 0.0)  # hence the penalty
    # leading principal minors (with unit scales the normalised M is M itself)
    by_hand = np.min([np.linalg.det(mass[:, :k, :k]) for k in range(1, n + 1)], axis=0)
    np.testing.assert_allclose(minors, by_hand, rtol=1e-12, atol=1e-12)


def test_min_minor_is_normalised_by_the_inertia_scale():
    spec = NetworkSpec(2, theta_units=0, bias=True)
    scales = unit_scales(2, torque=[4.0, 1.0], acceleration=[1.0, 4.0])  # inertia 4, 1/4
    g = np.zeros(spec.genome_size)
    set_block(spec, g, 'theta_bias', [1.0, 2.0, 1.0] + [0.0] * (spec.n_outputs - 3))
    net = BatchedNetwork(spec, spec.decode(g, scales), scales)
    mass = net.mass_matrix(np.zeros((1, 2)))[0]
    np.testing.assert_allclose(mass, [[4.0, 2.0], [2.0, 0.25]])  # genome × sqrt(ms_i ms_j)
    # normalised M = [[1, 2], [2, 1]]: minors 1 and -3
    np.testing.assert_allclose(net.min_minor(np.zeros((1, 2))), [-3.0])


@pytest.mark.parametrize('case', CASES)
@pytest.mark.parametrize('inertia', ['penalty', 'cholesky'])
def test_rhs_shapes(case, inertia):
    n, pop = 3, 6
    spec = NetworkSpec(n, case, inertia=inertia, bias=True, torque_linear=True)
    net = random_network(spec, pop=pop, scale=0.1, kp=np.ones(n), kd=np.ones(n))
    x = np.random.default_rng(1).standard_normal((pop, 2 * n))
    inputs = ([np.ones(n), np.ones((pop, n))] if case == 'torque'
              else [np.ones(2 * n), np.ones((pop, 2 * n))])
    for u in inputs:
        out = net.rhs(x, u)
        assert out.shape == (pop, 2 * n)
        np.testing.assert_array_equal(out[:, :n], x[:, n:])  # dθ/dt = θ̇
        assert np.all(np.isfinite(out))
        terms = net.terms(x, u)
        assert terms['M'].shape == (pop, n, n)
        for key in ('V', 'G', 'F', 'tau'):
            assert terms[key].shape == (pop, n)


def test_pd_gains_case_needs_the_gains():
    spec = NetworkSpec.paper(2, 'pd_gains')
    with pytest.raises(ValueError, match="case 'pd_gains' needs kp and kd"):
        BatchedNetwork(spec, spec.decode(spec.initial_genome(), unit_scales(2)),
                       unit_scales(2), kp=[1.0, 1.0])


def test_pair_products_ordering():
    td = np.array([2.0, 3.0, 5.0])
    np.testing.assert_array_equal(pair_products(td), [6.0, 10.0, 15.0])  # 12, 13, 23
    td4 = np.array([2.0, 3.0, 5.0, 7.0])
    np.testing.assert_array_equal(pair_products(td4), [6.0, 10.0, 14.0, 15.0, 21.0, 35.0])
    assert pair_products(np.array([4.0])).shape == (0,)
    batch = np.arange(24.0).reshape(2, 4, 3)
    out = pair_products(batch)
    assert out.shape == (2, 4, 3)
    np.testing.assert_array_equal(out[1, 2], pair_products(batch[1, 2]))


def test_velocity_terms_use_the_paper_ordering():
    """Check B's column p multiplies the p-th pair product of eq. (5), C's column j θ̇_j²."""
    n = 3
    spec = NetworkSpec(n, theta_units=0, bias=True, friction=False)
    scales = unit_scales(n)
    sl = spec.output_slices()
    td = np.array([[2.0, 3.0, 5.0]])
    x = np.hstack([np.zeros((1, n)), td])
    pairs = [(0, 1), (0, 2), (1, 2)]
    for i in range(n):
        for p, (j, k) in enumerate(pairs):
            g = np.zeros(spec.genome_size)
            bias = np.zeros(spec.n_outputs)
            bias[sl['coriolis'].start + i * 3 + p] = 1.0
            set_block(spec, g, 'theta_bias', bias)
            net = BatchedNetwork(spec, spec.decode(g, scales), scales)
            v = net.terms(x, np.zeros(n))['V'][0]
            expected = np.zeros(n)
            expected[i] = td[0, j] * td[0, k]
            np.testing.assert_array_equal(v, expected)
        for j in range(n):
            g = np.zeros(spec.genome_size)
            bias = np.zeros(spec.n_outputs)
            bias[sl['centrifugal'].start + i * n + j] = 1.0
            set_block(spec, g, 'theta_bias', bias)
            net = BatchedNetwork(spec, spec.decode(g, scales), scales)
            v = net.terms(x, np.zeros(n))['V'][0]
            expected = np.zeros(n)
            expected[i] = td[0, j] ** 2
            np.testing.assert_array_equal(v, expected)


def test_pendulum_by_hand():
    """
    Check a one-joint pendulum set by hand reproduces its closed-form acceleration.

    m θ̈ = τ - c θ̇² - (g0 + g1 exp(-(θ - c0)² / s²)) - f_v θ̇ - f_c tanh(θ̇ / v_c): constant
    inertia from the bias, gravity from the bias plus one RBF unit.
    """
    spec = NetworkSpec(1, theta_units=1, bias=True)
    scales = unit_scales(1)
    m, c, g0, g1, c0, width, fv, fc = 0.7, 0.3, 1.5, -2.0, 0.4, 0.25, 0.8, 0.6
    g = np.zeros(spec.genome_size)
    set_block(spec, g, 'theta_centres', [[c0]])
    set_block(spec, g, 'theta_widths', [width])           # 1/s² = exp(-2 w)
    set_block(spec, g, 'theta_weights', [[0.0], [0.0], [g1]])  # outputs: M, C, G
    set_block(spec, g, 'theta_bias', [m, c, g0])
    set_block(spec, g, 'friction', [[fv / 0.1], [fc / 0.1]])  # decoded as 0.1 |g|
    net = BatchedNetwork(spec, spec.decode(g, scales), scales)
    rng = np.random.default_rng(4)
    theta, theta_dot, tau = rng.uniform(-2.0, 2.0, (3, 50, 1))
    x = np.hstack([theta, theta_dot])
    gravity = g0 + g1 * np.exp(-(theta - c0) ** 2 * math.exp(-2.0 * width))
    friction = fv * theta_dot + fc * np.tanh(theta_dot / spec.coulomb_velocity)
    expected = (tau - c * theta_dot ** 2 - gravity - friction) / m
    out = net.rhs(x, tau)
    np.testing.assert_allclose(out[:, 1:], expected, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(out[:, :1], theta_dot)
    np.testing.assert_allclose(net.terms(x, tau)['G'], gravity, rtol=1e-14)


def test_two_joint_system_with_constant_inertia_by_hand():
    spec = NetworkSpec(2, theta_units=0, bias=True, friction=False)
    scales = unit_scales(2)
    sl = spec.output_slices()
    bias = np.zeros(spec.n_outputs)
    bias[sl['inertia']] = [2.0, 0.5, 1.0]  # packed upper triangle M00, M01, M11
    bias[sl['coriolis']] = [0.2, -0.3]      # B (2 × 1)
    bias[sl['centrifugal']] = [0.0, 0.1, -0.1, 0.0]  # C (2 × 2), row-major
    bias[sl['gravity']] = [4.0, 1.0]
    g = np.zeros(spec.genome_size)
    set_block(spec, g, 'theta_bias', bias)
    net = BatchedNetwork(spec, spec.decode(g, scales), scales)
    rng = np.random.default_rng(7)
    x = rng.standard_normal((20, 4))
    tau = rng.standard_normal((20, 2))
    td = x[:, 2:]
    mass = np.array([[2.0, 0.5], [0.5, 1.0]])
    v = (np.outer(td[:, 0] * td[:, 1], [0.2, -0.3])
         + td[:, ::-1] ** 2 * np.array([0.1, -0.1]))
    expected = np.linalg.solve(mass, (tau - v - np.array([4.0, 1.0])).T).T
    np.testing.assert_allclose(net.rhs(x, tau)[:, 2:], expected, rtol=1e-12, atol=1e-13)


def test_torque_network_by_hand():
    n = 2
    spec = NetworkSpec(n, 'unknown', theta_units=0, torque_units=2, bias=True,
                       torque_linear=True, friction=False)
    scales = unit_scales(n)
    g = np.zeros(spec.genome_size)
    centres = np.array([[-0.5, 0.5], [0.2, 0.0]])
    widths = np.array([[0.0, 0.3], [-0.2, 0.1]])
    weights = np.array([[1.0, -2.0], [0.5, 0.25]])
    set_block(spec, g, 'p_net', [centres, widths, weights])
    set_block(spec, g, 'd_net', [-centres, widths, 2.0 * weights])
    set_block(spec, g, 'pd_linear', [[3.0, 4.0], [0.5, 0.25]])
    net = BatchedNetwork(spec, spec.decode(g, scales), scales)
    rng = np.random.default_rng(3)
    x = rng.standard_normal((10, 2 * n))
    u = rng.standard_normal(2 * n)
    err = u[:n] - x[:, :n]
    derr = u[n:] - x[:, n:]

    def rbf(e, c, w, a):
        return np.sum(a * np.exp(-(e[:, :, None] - c) ** 2 * np.exp(-2.0 * w)), axis=-1)

    expected = (np.array([3.0, 4.0]) * err + np.array([0.5, 0.25]) * derr
                + rbf(err, centres, widths, weights) + rbf(derr, -centres, widths, 2 * weights))
    np.testing.assert_allclose(net.torque(x, u), expected, rtol=1e-13)


def test_one_model_over_many_states_equals_one_state_per_model():
    spec = NetworkSpec(3, bias=True)
    scales = unit_scales(3)
    g = spec.initial_genome() + 0.3 * np.random.default_rng(2).standard_normal(spec.genome_size)
    one = BatchedNetwork(spec, spec.decode(g, scales), scales)
    copies = BatchedNetwork(spec, spec.decode(np.tile(g, (8, 1)), scales), scales)
    theta = np.random.default_rng(3).standard_normal((8, 3))
    np.testing.assert_allclose(one.theta_outputs(theta), copies.theta_outputs(theta),
                               rtol=1e-13, atol=1e-14)
    np.testing.assert_allclose(one.mass_matrix(theta), copies.mass_matrix(theta),
                               rtol=1e-13, atol=1e-14)


def test_singular_inertia_gives_nan_not_an_exception():
    spec = NetworkSpec.paper(2)
    scales = unit_scales(2)
    genomes = np.vstack([np.zeros(spec.genome_size), spec.initial_genome()])  # M = 0, M > 0
    net = BatchedNetwork(spec, spec.decode(genomes, scales), scales)
    x = np.zeros((2, 4))
    out = net.rhs(x, np.ones(2))
    assert np.all(np.isnan(out[0, 2:]))
    assert np.all(np.isfinite(out[1]))
    alone = BatchedNetwork(spec, spec.decode(genomes[1], scales), scales).rhs(x[1:], np.ones(2))
    np.testing.assert_array_equal(out[1], alone[0])


def finite_difference_velocity_terms(net, x, step=1e-6):
    """V = Ṁθ̇ - ½ ∂(θ̇ᵀMθ̇)/∂θ by central differences of ``net.mass_matrix``, x (P, 2n)."""
    n = x.shape[1] // 2
    theta, theta_dot = x[:, :n], x[:, n:]
    dmass = np.empty((x.shape[0], n, n, n))  # [p, k, i, j] = ∂M_ij/∂θ_k
    for k in range(n):
        e = np.zeros(n)
        e[k] = step
        dmass[:, k] = (net.mass_matrix(theta + e) - net.mass_matrix(theta - e)) / (2 * step)
    m_dot = np.einsum('pkij,pk->pij', dmass, theta_dot)
    grad = np.einsum('pi,pkij,pj->pk', theta_dot, dmass, theta_dot)
    return np.einsum('pij,pj->pi', m_dot, theta_dot) - 0.5 * grad, m_dot


@pytest.mark.parametrize('basis', ['rbf', 'poly', 'poly+rbf'])
@pytest.mark.parametrize('inertia', ['penalty', 'cholesky'])
@pytest.mark.parametrize('n', [1, 2, 3])
def test_christoffel_velocity_terms(inertia, n, basis):
    spec = NetworkSpec(n, inertia=inertia, velocity='christoffel', bias=True, basis=basis)
    net = random_network(spec, pop=12, seed=5, scale=0.5)
    rng = np.random.default_rng(6)
    x = rng.uniform(-1.0, 1.0, (12, 2 * n))
    v = net.terms(x, np.zeros(n))['V']
    v_fd, m_dot = finite_difference_velocity_terms(net, x)
    np.testing.assert_allclose(v, v_fd, rtol=1e-6, atol=1e-8)
    # energy consistency: θ̇ᵀV = ½ θ̇ᵀṀθ̇, so d/dt ½θ̇ᵀMθ̇ = θ̇ᵀ(τ - G - F)
    power = np.einsum('pi,pi->p', x[:, n:], v)
    half = 0.5 * np.einsum('pi,pij,pj->p', x[:, n:], m_dot, x[:, n:])
    np.testing.assert_allclose(power, half, rtol=1e-6, atol=1e-8)
    dmass = net.mass_derivatives(x[:, :n])
    assert dmass.shape == (12, n, n, n)
    np.testing.assert_allclose(dmass, np.swapaxes(dmass, 2, 3), rtol=1e-12, atol=1e-14)


def test_christoffel_velocity_terms_of_one_model_over_many_states():
    spec = NetworkSpec(3, inertia='cholesky', velocity='christoffel', bias=True)
    scales = unit_scales(3)
    g = spec.initial_genome() + 0.3 * np.random.default_rng(8).standard_normal(spec.genome_size)
    one = BatchedNetwork(spec, spec.decode(g, scales), scales)
    copies = BatchedNetwork(spec, spec.decode(np.tile(g, (6, 1)), scales), scales)
    x = np.random.default_rng(9).standard_normal((6, 6))
    np.testing.assert_allclose(one.terms(x, np.zeros(3))['V'], copies.terms(x, np.zeros(3))['V'],
                               rtol=1e-12, atol=1e-13)

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

"""The equation-error warm start: θ̈ estimate, the least-squares design, the case-3 gauge."""

from model_helpers import block, KD, KP, N, SCALES
import numpy as np
import pytest
from rkgnn_ros.core.data import Dataset
from rkgnn_ros.core.fitting.warmstart import (_design, estimate_acceleration, least_squares_genome,
                                              LINEAR_BLOCKS)
from rkgnn_ros.core.model.network import BatchedNetwork
from rkgnn_ros.core.model.spec import NetworkSpec

CASES = ('torque', 'pd_gains', 'unknown')
INERTIA = ('penalty', 'cholesky')


def polynomial_segments(rng, count=6, duration=1.0, rate=50.0):
    """Segments whose θ̇ is a cubic in t (the Savitzky-Golay derivative is then exact)."""
    t = np.arange(int(round(duration * rate)) + 1) / rate
    out = []
    for _ in range(count):
        c = rng.standard_normal((4, N))
        theta0 = SCALES.theta_center + 0.3 * rng.standard_normal(N)
        theta_dot = sum(c[p] * t[:, None] ** p for p in range(4))
        theta = theta0 + sum(c[p] * t[:, None] ** (p + 1) / (p + 1) for p in range(4))
        acc = sum(p * c[p] * t[:, None] ** (p - 1) for p in range(1, 4))
        out.append((t, theta, theta_dot, acc))
    return out


def random_linear_genome(spec, seed):
    rng = np.random.default_rng(seed)
    g = spec.initial_genome(rng=rng)
    index = linear_index(spec)
    g[index] = rng.standard_normal(index.size)
    f = block(spec, 'friction')
    g[f.start:f.stop] = np.abs(g[f.start:f.stop]) + 0.1
    return g


def linear_index(spec):
    return np.concatenate([np.arange(b.start, b.stop) for b in spec.blocks()
                           if b.name in LINEAR_BLOCKS])


def inverse_dynamics(net, theta, theta_dot, acc):
    """M θ̈ + V + G + F of the network, shape (T, n)."""
    u = np.zeros(N if net.spec.case == 'torque' else 2 * N)  # τ is not part of it
    terms = net.terms(np.hstack([theta, theta_dot]), u)
    return (np.einsum('pij,pj->pi', terms['M'], acc) + terms['V'] + terms['G'] + terms['F'])


def test_savitzky_golay_acceleration_is_exact_for_cubic_velocities():
    (t, _, theta_dot, acc), = polynomial_segments(np.random.default_rng(0), count=1)
    np.testing.assert_allclose(estimate_acceleration(theta_dot, t[1] - t[0]), acc,
                               rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize('case', ['torque', 'pd_gains'])
def test_least_squares_recovers_the_linear_elements(case):
    spec = NetworkSpec.paper(N, case)
    g = random_linear_genome(spec, seed=3)
    net = BatchedNetwork(spec, spec.decode(g, SCALES), SCALES, KP, KD)
    datasets = []
    for t, theta, theta_dot, acc in polynomial_segments(np.random.default_rng(4)):
        tau = inverse_dynamics(net, theta, theta_dot, acc)
        if case == 'torque':
            datasets.append(Dataset(t, theta, theta_dot, tau=tau))
        else:  # τ = Kp (θd - θ) with θ̇d = θ̇
            datasets.append(Dataset(t, theta, theta_dot, theta_d=theta + tau / KP,
                                    theta_d_dot=theta_dot))
    start = g.copy()
    index = linear_index(spec)
    start[index] = spec.initial_genome()[index]  # keep centres and widths, forget weights
    out = least_squares_genome(spec, datasets, SCALES, genome=start, kp=KP, kd=KD, ridge=0.0)
    np.testing.assert_allclose(out[index], g[index], rtol=0.0, atol=1e-6)
    np.testing.assert_array_equal(np.delete(out, index), np.delete(g, index))


def test_least_squares_design_reproduces_the_network_residual():
    """Check A @ (linear elements) = M θ̈ + V + G + F - τ_network at random states, case 3."""
    spec = NetworkSpec(N, 'unknown', bias=True, torque_linear=True)
    g = random_linear_genome(spec, seed=5)
    for name in ('p_net', 'd_net'):
        b = block(spec, name)
        net_block = g[b.start:b.stop].reshape(b.shape)
        net_block[2] = np.random.default_rng(6).standard_normal(net_block[2].shape)
        g[b.start:b.stop] = net_block.ravel()
    params = spec.decode(g, SCALES)
    net = BatchedNetwork(spec, params, SCALES)
    rng = np.random.default_rng(7)
    theta = SCALES.theta_center + 0.3 * rng.standard_normal((40, N))
    theta_dot, acc = rng.standard_normal((2, 40, N))
    err = 0.1 * rng.standard_normal((40, N))
    derr = 0.5 * rng.standard_normal((40, N))
    a, index = _design(spec, SCALES, params, theta, theta_dot, acc, err, derr)
    assert a.shape == (40 * N, index.size) and np.unique(index).size == index.size
    x = np.hstack([theta, theta_dot])
    u = np.hstack([theta + err, theta_dot + derr])
    residual = inverse_dynamics(net, theta, theta_dot, acc) - np.vstack(
        [net.torque(x[i:i + 1], u[i]) for i in range(40)])
    np.testing.assert_allclose(a @ g[index], residual.reshape(-1), rtol=1e-10, atol=1e-10)


def test_least_squares_keeps_friction_non_negative():
    """Data with negative damping: the unconstrained solution would want negative friction."""
    spec = NetworkSpec.paper(N, 'torque')
    g = random_linear_genome(spec, seed=8)
    net = BatchedNetwork(spec, spec.decode(g, SCALES), SCALES)
    datasets = []
    for t, theta, theta_dot, acc in polynomial_segments(np.random.default_rng(9)):
        tau = inverse_dynamics(net, theta, theta_dot, acc) - 5.0 * theta_dot * SCALES.torque
        datasets.append(Dataset(t, theta, theta_dot, tau=tau))
    out = least_squares_genome(spec, datasets, SCALES, genome=g)
    f = block(spec, 'friction')
    friction = out[f.start:f.stop].reshape(f.shape)
    assert np.all(friction >= 0.0)
    assert np.any(friction[0] == 0.0)  # the viscous bound is active


def test_least_squares_gauge_in_case_3():
    """
    Check case 3 gives the true solution up to scale, the scale fixed by mean M_ii / ms_i = 1.

    Regression test for the gauge (fixed in 3a690c8): ``warmstart._fix_gauge`` took
    ``np.diagonal(net.mass_matrix(th[None]))[0]``, the diagonal of the (1, n) leading
    axes, i.e. ``[M_00]`` only, so the level was mean(M_00) × mean(1 / ms_i) instead of
    mean(M_ii / ms_i).
    """
    spec = NetworkSpec(N, 'unknown', torque_units=0, torque_linear=True)
    g = random_linear_genome(spec, seed=10)
    p = block(spec, 'pd_linear')
    g[p.start:p.stop] = np.abs(g[p.start:p.stop]) + 0.5
    net = BatchedNetwork(spec, spec.decode(g, SCALES), SCALES)
    params = spec.decode(g, SCALES)
    kp, kd = params.kp[0], params.kd[0]
    datasets = []
    rng = np.random.default_rng(11)
    for t, theta, theta_dot, acc in polynomial_segments(rng):
        tau = inverse_dynamics(net, theta, theta_dot, acc)
        derr = 0.3 * rng.standard_normal(theta.shape)
        err = (tau - kd * derr) / kp
        datasets.append(Dataset(t, theta, theta_dot, theta_d=theta + err,
                                theta_d_dot=theta_dot + derr))
    out = least_squares_genome(spec, datasets, SCALES, genome=g)
    index = linear_index(spec)
    ratio = out[index] @ g[index] / (g[index] @ g[index])
    np.testing.assert_allclose(out[index], ratio * g[index], rtol=0.0, atol=1e-6)
    fitted = BatchedNetwork(spec, spec.decode(out, SCALES), SCALES)
    theta = np.vstack([d.theta for d in datasets])
    diag = np.diagonal(fitted.mass_matrix(theta), axis1=1, axis2=2)
    step = max(1, theta.shape[0] // 200)
    np.testing.assert_allclose(np.mean(diag[::step] / SCALES.inertia), 1.0, rtol=1e-9)


def test_least_squares_refuses_cholesky_inertia():
    spec = NetworkSpec(N, 'torque', inertia='cholesky')
    data = polynomial_segments(np.random.default_rng(0), count=1)
    with pytest.raises(ValueError, match="needs inertia='penalty'"):
        least_squares_genome(spec, data, SCALES)

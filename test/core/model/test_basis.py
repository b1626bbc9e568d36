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
The bases of the θ outputs as plug-ins: registry, features, gradients, kernels against numpy.

Every registered basis and a sum of them, through the compiled cost and rollouts and the
numpy reference, held equal.

The polynomial basis is the second plug-in (no genome parameters, a fixed code table, as
a trigonometric one would be): it exercises the kernels' dispatch to bases they do not
inline, and sums of bases.
"""

import os
import zlib

from model_helpers import unit_scales
import numpy as np
import pytest
from rkgnn_ros.core.data import Dataset
from rkgnn_ros.core.fitting.fitness import FitnessProblem
from rkgnn_ros.core.model import kernels
from rkgnn_ros.core.model.basis import base, imq, poly, rbf, registry, trig
from rkgnn_ros.core.model.network import BatchedNetwork, feature_gradients, features
from rkgnn_ros.core.model.spec import NetworkSpec
from rkgnn_ros.core.sim.trajectories import paper_reference

BASES = ('rbf', 'poly', 'poly+rbf', 'rbf+poly', 'trig', 'trig3d', 'trig+rbf', 'imq', 'imq+rbf')
SCALES = unit_scales(3, theta_spread=[0.4, 0.5, 0.6], torque=[3.0, 2.0, 1.0],
                     acceleration=[5.0, 5.0, 5.0])


def test_registry_names_and_sums():
    assert set(registry.BASES) == {'rbf', 'poly', 'trig', 'trig3d', 'imq'}
    assert [b.name for b in registry.lookup('poly+rbf')] == ['poly', 'rbf']
    assert len({b.kind for b in registry.BASES.values()}) == len(registry.BASES)
    assert all(isinstance(b, base.Basis) for b in registry.BASES.values())
    for bad in ('rbf+rbf', 'fourier', '', 'rbf+'):
        with pytest.raises(ValueError, match='basis'):
            registry.lookup(bad)
    with pytest.raises(ValueError, match='basis'):
        NetworkSpec(3, basis='fourier')


def test_the_paper_layout_is_the_rbf_basis():
    for case, size in (('torque', 99), ('pd_gains', 99), ('unknown', 153)):
        spec = NetworkSpec.paper(3, case)
        assert spec.basis == 'rbf' and spec.genome_size == size
    names = [b.name for b in NetworkSpec.paper(3).blocks()]
    assert names[:3] == ['theta_centres', 'theta_widths', 'theta_weights']


def test_a_basis_without_parameters_adds_no_genome_block():
    spec = NetworkSpec(3, basis='poly', bias=True)
    n_poly = 3 + 6                                        # degree 1 and 2 in 3 angles
    assert spec.n_features == n_poly
    assert [b.name for b in spec.blocks()][0] == 'theta_weights'
    both = NetworkSpec(3, basis='poly+rbf', theta_units=2, bias=True)
    assert both.n_features == n_poly + 2
    assert both.genome_size == spec.genome_size + 2 * (3 + 1) + 2 * spec.n_outputs
    codes = registry.table(both)[-1]
    assert codes.shape == (n_poly + 2, 3) and np.all(codes[n_poly:] == 0)
    np.testing.assert_array_equal(codes[:n_poly].sum(axis=1), [1] * 3 + [2] * 6)


def genomes(spec, pop=5, seed=0, scale=0.3):
    rng = np.random.default_rng(seed)
    return spec.initial_genome() + scale * rng.standard_normal((pop, spec.genome_size))


@pytest.mark.parametrize('basis', BASES)
def test_gradients_are_the_derivatives_of_the_features(basis):
    spec = NetworkSpec(3, basis=basis, bias=True)
    params = spec.decode(genomes(spec), SCALES)
    theta = np.random.default_rng(1).uniform(-1.0, 1.0, (5, 3))
    phi = features(spec, params, theta)
    grad = feature_gradients(spec, params, theta, phi)
    assert phi.shape == (5, spec.n_features) and grad.shape == (5, spec.n_features, 3)
    step = 1e-6
    for k in range(3):
        e = np.zeros(3)
        e[k] = step
        fd = (features(spec, params, theta + e) - features(spec, params, theta - e)) / (2 * step)
        np.testing.assert_allclose(grad[..., k], fd, rtol=1e-6, atol=1e-8)


def test_the_polynomial_features_are_the_monomials_of_the_normalised_angles():
    spec = NetworkSpec(2, basis='poly', bias=True)
    scales = unit_scales(2, theta_center=[0.5, -1.0], theta_spread=[2.0, 4.0])
    params = spec.decode(spec.initial_genome(), scales)
    theta = np.array([[1.5, 1.0]])
    z1, z2 = (1.5 - 0.5) / 2.0, (1.0 + 1.0) / 4.0
    np.testing.assert_allclose(features(spec, params, theta)[0],
                               [z1, z2, z1 * z1, z1 * z2, z2 * z2], rtol=1e-15)


def test_the_inverse_multiquadric_units_reach_beyond_the_gaussian_ones():
    """φ = 1/sqrt(1 + |θ - c|²/s²): 1 at the centre, 1/sqrt(5) two widths out (Gaussian e^-4)."""
    spec = NetworkSpec(2, basis='imq+rbf', theta_units=1, bias=True)
    scales = unit_scales(2, theta_center=[0.5, -1.0], theta_spread=[3.0, 4.0])
    genome = spec.initial_genome()
    layout = {b.name: b for b in spec.blocks()}
    for name in ('imq_centres', 'theta_centres'):
        genome[layout[name].start:layout[name].stop] = 0.0
    params = spec.decode(genome, scales)
    assert registry.lookup('imq')[0].kind == imq.KIND
    width = 5.0                                  # |spread| with zero width genes
    theta = np.array([[0.5, -1.0], [0.5 + 2 * width, -1.0], [0.5, -1.0 + 20 * width]])
    phi = features(spec, params, theta)
    np.testing.assert_allclose(phi[:, 0], [1.0, 1 / np.sqrt(5.0), 1 / np.sqrt(401.0)],
                               rtol=1e-14)
    np.testing.assert_allclose(phi[:, 1], [1.0, np.exp(-4.0), np.exp(-400.0)], rtol=1e-14)


@pytest.mark.parametrize('name, n, size', [('trig', 3, 12), ('trig', 6, 42), ('trig3d', 3, 42),
                                           ('trig3d', 6, 858)])
def test_the_trigonometric_features_are_the_arm_tables_without_the_constant(name, n, size):
    spec = NetworkSpec(n, basis=name, bias=True)
    table = registry.BASES[name].table(n)
    assert spec.n_features == size == table.n_features - 1
    params = spec.decode(spec.initial_genome(), unit_scales(n))
    theta = np.random.default_rng(4).uniform(-np.pi, np.pi, (7, n))
    np.testing.assert_allclose(features(spec, params, theta), table.values(theta)[:, 1:],
                               rtol=0, atol=1e-14)


def test_a_trig_network_holds_the_planar_arm_mass_matrix_everywhere():
    """Least squares on 40 configurations in a small box gives M on the whole torus."""
    from rkgnn_ros.core.sim.plant import PlanarArm
    arm = PlanarArm.paper('rod')
    spec = NetworkSpec(3, 'torque', inertia='penalty', bias=True, basis='trig')
    params = spec.decode(spec.initial_genome(), unit_scales(3))
    rng = np.random.default_rng(5)
    near = rng.uniform(-0.3, 0.3, (40, 3))
    far = rng.uniform(-np.pi, np.pi, (200, 3))
    design = np.column_stack([features(spec, params, near), np.ones(len(near))])
    truth = arm.mass_matrix(near)
    coef = np.linalg.lstsq(design, truth.reshape(len(near), -1), rcond=None)[0]
    far_design = np.column_stack([features(spec, params, far), np.ones(len(far))])
    predicted = (far_design @ coef).reshape(-1, 3, 3)
    np.testing.assert_allclose(predicted, arm.mass_matrix(far), rtol=0, atol=1e-9)


@pytest.fixture(scope='module')
def data():
    """Two segments of smooth motion with torque and a desired trajectory."""
    t = np.arange(61) / 100.0
    qd, qd_dot = paper_reference(3).evaluate(t)
    tau = np.column_stack([np.sin(2 * np.pi * (0.7 + 0.3 * i) * t + i) for i in range(3)])
    d = Dataset(t, qd + 0.02 * np.sin(5 * t)[:, None], qd_dot + 0.1 * np.cos(5 * t)[:, None],
                tau=tau, theta_d=qd, theta_d_dot=qd_dot)
    return [d.slice(0, 30), d.slice(30, 61)]


@pytest.mark.parametrize('basis', BASES)
@pytest.mark.parametrize('inertia, velocity', [('penalty', 'learned'),
                                               ('cholesky', 'christoffel'),
                                               ('penalty', 'christoffel')])
@pytest.mark.parametrize('case', ['torque', 'unknown'])
def test_compiled_kernels_equal_the_numpy_reference_for_every_basis(data, basis, inertia,
                                                                    velocity, case):
    spec = NetworkSpec(3, case, inertia=inertia, velocity=velocity, bias=True, basis=basis,
                       theta_units=2, torque_units=2, torque_linear=True)
    problem = FitnessProblem(spec, data, substeps=2, shooting=7, torque_interpolation='linear')
    assert problem.constants.inlined == (basis == 'rbf')
    pop = genomes(spec, pop=4, scale=0.05)
    costs = problem.cost(pop)
    assert np.all(np.isfinite(costs))
    np.testing.assert_allclose(costs, problem.cost_numpy(pop), rtol=1e-10, atol=0.0)
    rollouts = problem.rollouts(pop)
    for seg, d in enumerate(data):
        start = problem.seg_start[seg]
        numpy_rows, _ = problem.rollout_numpy(pop, seg)
        np.testing.assert_allclose(rollouts[:, start:start + d.n_samples], numpy_rows,
                                   rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize('basis', ['poly', 'poly+rbf', 'trig+rbf', 'imq+rbf'])
def test_the_model_of_another_basis_rolls_out_and_saves(basis, tmp_path):
    from rkgnn_ros.core.model.model import RKGNNModel
    spec = NetworkSpec(3, 'torque', inertia='cholesky', velocity='christoffel', bias=True,
                       basis=basis, theta_units=2)
    model = RKGNNModel(spec, SCALES, genomes(spec, pop=1, scale=0.05)[0], substeps=4)
    t = np.arange(41) / 100.0
    states = model.simulate(np.zeros(6), t, tau=np.ones((41, 3)))
    net = BatchedNetwork(spec, model._params, SCALES)
    assert np.all(np.isfinite(states))
    # one RKG step of the numpy network from the first state
    from rkgnn_ros.core.integration.rkg import rkg_step
    x = states[:1]
    for _ in range(4):
        x = rkg_step(net.rhs, x, 0.0025, np.ones(3), np.ones(3), np.ones(3))
    np.testing.assert_allclose(states[1], x[0], rtol=1e-10, atol=1e-12)
    model.save(tmp_path / 'model.yaml')
    loaded = RKGNNModel.load(tmp_path / 'model.yaml')
    assert loaded.spec.basis == basis
    np.testing.assert_array_equal(loaded.simulate(np.zeros(6), t, tau=np.ones((41, 3))), states)


def test_christoffel_velocity_conserves_kinetic_energy_with_a_penalty_inertia():
    """M from the polynomial basis, no G, F or τ: ½θ̇ᵀMθ̇ is a constant of the motion."""
    from rkgnn_ros.core.model.model import RKGNNModel
    spec = NetworkSpec(2, 'torque', inertia='penalty', velocity='christoffel', bias=True,
                       basis='poly', friction=False)
    scales = unit_scales(2)
    g = spec.initial_genome()
    weights = next(b for b in spec.blocks() if b.name == 'theta_weights')
    w = np.zeros(weights.shape)
    w[spec.output_slices()['inertia']] = 0.05 * np.random.default_rng(3).standard_normal(
        (3, spec.n_features))
    g[weights.start:weights.stop] = w.ravel()
    model = RKGNNModel(spec, scales, g, substeps=20)
    t = np.arange(201) / 100.0
    x = model.simulate(np.array([0.2, -0.1, 0.6, -0.4]), t, tau=np.zeros((201, 2)))
    mass = model.mass_matrix(x[:, :2])
    lowest = np.linalg.eigvalsh(mass)[:, 0]
    assert np.all(lowest > 0.5)                              # positive definite on the path
    assert np.ptp(lowest) > 0.1                              # and far from constant on it
    energy = 0.5 * np.einsum('ti,tij,tj->t', x[:, 2:], mass, x[:, 2:])
    assert np.max(np.abs(energy - energy[0])) < 1e-9 * energy[0]


def test_the_kernels_know_the_fingerprint_of_what_they_inline():
    crc = 0
    assert registry.MODULES == (rbf, poly, trig, imq)
    for module in (base, *registry.MODULES, registry):
        with open(module.__file__, 'rb') as f:
            crc = zlib.crc32(f.read(), crc)
    assert registry.source_fingerprint() == crc
    assert kernels._compiled_fingerprint() == kernels._FINGERPRINT   # refreshed at import
    assert not kernels.ensure_current()
    assert os.path.basename(registry.__file__) == 'registry.py'

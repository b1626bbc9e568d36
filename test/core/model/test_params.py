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

"""Decoding genomes into the named records the kernels take, and the kernels' constants."""

import math

from model_helpers import set_block, unit_scales
import numpy as np
import pytest
from rkgnn_ros.core.model.params import NetworkParams
from rkgnn_ros.core.model.scales import Scales
from rkgnn_ros.core.model.spec import NetworkSpec

CASES = ('torque', 'pd_gains', 'unknown')


@pytest.mark.parametrize('case', CASES)
def test_decode_shapes(case):
    n, k, kt, pop = 3, 4, 2, 5
    spec = NetworkSpec(n, case, theta_units=k, torque_units=kt, bias=True,
                       torque_linear=True)
    scales = unit_scales(n)
    genomes = np.random.default_rng(0).standard_normal((pop, spec.genome_size))
    p = spec.decode(genomes, scales)
    kt_used = kt if case == 'unknown' else 0
    expected = {
        'features': (pop, k, n + 1), 'weights': (pop, spec.n_outputs, k),
        'bias': (pop, spec.n_outputs), 'viscous': (pop, n), 'coulomb': (pop, n),
        'p_centres': (pop, n, kt_used), 'p_inv_width2': (pop, n, kt_used),
        'p_weights': (pop, n, kt_used), 'd_centres': (pop, n, kt_used),
        'd_inv_width2': (pop, n, kt_used), 'd_weights': (pop, n, kt_used),
        'kp': (pop, n), 'kd': (pop, n)}
    assert isinstance(p, NetworkParams)
    assert {key: value.shape for key, value in p._asdict().items()} == expected
    assert all(value.flags.c_contiguous for value in p)
    # one genome decodes to a population of one; take() picks models out of a population
    single = spec.decode(genomes[2], scales)
    picked = p.take([2])
    for key in expected:
        np.testing.assert_array_equal(getattr(single, key)[0], getattr(p, key)[2])
        np.testing.assert_array_equal(getattr(picked, key), getattr(single, key))


def test_decode_maps_the_normalised_genome_to_physical_units():
    n = 2
    scales = Scales(theta_center=[-1.0, 0.5], theta_spread=[0.3, 0.4], velocity=[2.0, 4.0],
                    acceleration=[5.0, 10.0], torque=[3.0, 1.0], error=[0.1, 0.2],
                    error_rate=[0.5, 0.25])
    spec = NetworkSpec(n, 'unknown', theta_units=1, torque_units=1, torque_linear=True)
    g = np.zeros(spec.genome_size)
    set_block(spec, g, 'theta_centres', [[1.0, -2.0]])
    set_block(spec, g, 'theta_widths', [0.5])
    set_block(spec, g, 'friction', [[-1.0, 2.0], [3.0, -4.0]])
    set_block(spec, g, 'p_net', [[[0.5], [1.0]], [[0.0], [0.0]], [[2.0], [-1.0]]])
    set_block(spec, g, 'pd_linear', [[1.0, 2.0], [3.0, 4.0]])
    p = spec.decode(g, scales)
    # the RBF unit decodes to [centre, 1/width²]
    np.testing.assert_allclose(p.features[0, :, :n], [[-1.0 + 0.3, 0.5 - 0.8]])
    np.testing.assert_allclose(p.features[0, :, n], [math.exp(-1.0) / 0.25])  # |spread|² = .25
    # friction is |g| times its scale: never negative damping
    np.testing.assert_allclose(p.viscous[0], [0.1 * 3.0 / 2.0 * 1.0, 0.1 * 1.0 / 4.0 * 2.0])
    np.testing.assert_allclose(p.coulomb[0], [0.1 * 3.0 * 3.0, 0.1 * 1.0 * 4.0])
    np.testing.assert_allclose(p.p_centres[0, :, 0], [0.05, 0.2])
    np.testing.assert_allclose(p.p_weights[0, :, 0], [6.0, -1.0])
    np.testing.assert_allclose(p.kp[0], [3.0 / 0.1 * 1.0, 1.0 / 0.2 * 2.0])
    np.testing.assert_allclose(p.kd[0], [3.0 / 0.5 * 3.0, 1.0 / 0.25 * 4.0])


def test_extreme_width_genes_decode_to_finite_widths_without_warnings():
    # an ES with a large step can sample width genes far out: exp(-2 g) must not overflow,
    # and a unit at its own centre must not give inf * 0
    import warnings
    from rkgnn_ros.core.model.basis.rbf import LOG_WIDTH_LIMIT
    spec = NetworkSpec(2, 'unknown', theta_units=2, torque_units=1, torque_linear=True)
    g = np.zeros(spec.genome_size)
    set_block(spec, g, 'theta_widths', [-1e4, 1e4])
    set_block(spec, g, 'p_net', [[[0.0], [0.0]], [[-1e4], [1e4]], [[1.0], [1.0]]])
    scales = unit_scales(2)
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        p = spec.decode(g, scales)
    assert np.all(np.isfinite(p.features)) and np.all(np.isfinite(p.p_inv_width2))
    assert p.features[0, 0, 2] == pytest.approx(math.exp(2 * LOG_WIDTH_LIMIT) /
                                                np.sum(scales.theta_spread ** 2))
    assert 0.0 < p.features[0, 1, 2] < 1e-40                 # a flat unit, not a zero width
    assert 0.0 < p.p_inv_width2[0, 0, 0] and np.isfinite(p.p_inv_width2[0, 1, 0])


def test_decode_rejects_a_wrong_length():
    spec = NetworkSpec.paper(3)
    with pytest.raises(ValueError, match=r'shape \(P, 99\)'):
        spec.decode(np.zeros(98), unit_scales(3))
    with pytest.raises(ValueError, match=r'shape \(P, 99\)'):
        spec.decode(np.zeros((2, 2, 99)), unit_scales(3))


def test_constants_describe_the_structure_and_the_known_gains():
    spec = NetworkSpec(3, 'pd_gains', inertia='cholesky', velocity='christoffel', bias=True,
                       basis='poly+rbf')
    scales = unit_scales(3, acceleration=[2.0, 4.0, 8.0])
    c = spec.constants(scales, kp=[1.0, 2.0, 3.0], kd=[4.0, 5.0, 6.0])
    assert (c.case_id, c.chol, c.christ) == (1, True, True)
    n_poly = spec.bases[0].size(spec)
    assert c.kinds.tolist() == [spec.bases[0].kind] * n_poly + [spec.bases[1].kind] * 3
    assert c.starts.tolist() == [0, n_poly, n_poly + 3] and not c.inlined
    assert c.codes.shape == (n_poly + 3, 3) and c.codes.dtype == np.int64
    np.testing.assert_array_equal(c.kp_known, [1.0, 2.0, 3.0])
    np.testing.assert_allclose(c.inv_sqrt_ms, 1.0 / np.sqrt(1.0 / np.array([2.0, 4.0, 8.0])))
    np.testing.assert_allclose(c.eps, spec.inertia_epsilon(scales))
    none = NetworkSpec(3).constants(scales)
    np.testing.assert_array_equal(none.kp_known, np.zeros(3))

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
The structure of N_f: genome layout and sizes (the paper's 99 and 153), validation, files.

Plain pytest, no middleware.
"""

import math

from hypothesis import given, settings
from hypothesis import strategies as st
from model_helpers import unit_scales
import numpy as np
import pytest
from rkgnn_ros.core.model.spec import check_genome, genome_report, NetworkSpec

CASES = ('torque', 'pd_gains', 'unknown')


def expected_size(n, case='torque', k=3, kt=3, bias=False, friction=True, linear=False,
                  velocity='learned'):
    """Genome length from first principles (see the network.py docstring)."""
    n_out = n * (n + 1) // 2 + n  # M's triangle and G
    if velocity == 'learned':
        n_out += n * (n * (n - 1) // 2) + n * n  # B and C
    size = k * (n + 1 + n_out)  # per θ unit: n centre coordinates, a width, the weights
    size += n_out if bias else 0
    size += 2 * n if friction else 0
    if case == 'unknown':
        size += 2 * 3 * n * kt  # P and D nets: (centre, width, weight) per joint and unit
        size += 2 * n if linear else 0
    return size


# ----- genome layout

def test_paper_genome_sizes_match_the_paper():
    # section 4: "In the cases 1 and 2, 99 elements and in case 3, 153 elements"
    assert NetworkSpec.paper(3, 'torque').genome_size == 99
    assert NetworkSpec.paper(3, 'pd_gains').genome_size == 99
    assert NetworkSpec.paper(3, 'unknown').genome_size == 153
    assert NetworkSpec.paper().genome_size == 99


@pytest.mark.parametrize('n, case, size', [
    (1, 'torque', 3 * (1 + 1 + 3) + 2), (2, 'torque', 46), (2, 'pd_gains', 46),
    (2, 'unknown', 82), (5, 'torque', 313), (5, 'unknown', 403), (6, 'torque', 3 * 160 + 12)])
def test_paper_structure_size_for_general_n(n, case, size):
    spec = NetworkSpec.paper(n, case)
    assert spec.genome_size == size == expected_size(n, case)
    assert spec.n_outputs == n * (n + 1) // 2 + n * n * (n - 1) // 2 + n * n + n
    assert spec.n_pairs == n * (n - 1) // 2


@settings(max_examples=60, deadline=None)
@given(n=st.integers(1, 7), case=st.sampled_from(CASES), k=st.integers(0, 4),
       kt=st.integers(0, 3), bias=st.booleans(), friction=st.booleans(),
       linear=st.booleans(), inertia=st.sampled_from(('penalty', 'cholesky')),
       velocity=st.sampled_from(('learned', 'christoffel')))
def test_genome_size_formula(n, case, k, kt, bias, friction, linear, inertia, velocity):
    if k == 0 and not bias:
        bias = True
    if case == 'unknown' and kt == 0:
        linear = True
    spec = NetworkSpec(n, case, theta_units=k, torque_units=kt, inertia=inertia, bias=bias,
                       friction=friction, torque_linear=linear, velocity=velocity)
    assert spec.genome_size == expected_size(n, case, k, kt, bias, friction, linear, velocity)
    # the blocks tile the genome: contiguous, in order, no gaps, sizes = product of shapes
    blocks = spec.blocks()
    assert blocks[0].start == 0
    for before, after in zip(blocks, blocks[1:]):
        assert after.start == before.stop
    assert blocks[-1].stop == spec.genome_size
    assert all(b.size == math.prod(b.shape) for b in blocks)
    assert len({b.name for b in blocks}) == len(blocks)
    assert sum(size for _, _, size in genome_report(spec)) == spec.genome_size
    assert spec.initial_genome().shape == (spec.genome_size,)


def test_block_layout_of_the_full_structure():
    spec = NetworkSpec(3, 'unknown', theta_units=2, torque_units=4, bias=True,
                       torque_linear=True)
    layout = [(b.name, b.shape, b.start, b.stop) for b in spec.blocks()]
    n_out = 27
    starts = np.cumsum([0, 6, 2, n_out * 2, n_out, 6, 36, 36])
    assert layout == [
        ('theta_centres', (2, 3), starts[0], starts[1]),
        ('theta_widths', (2,), starts[1], starts[2]),
        ('theta_weights', (n_out, 2), starts[2], starts[3]),
        ('theta_bias', (n_out,), starts[3], starts[4]),
        ('friction', (2, 3), starts[4], starts[5]),
        ('p_net', (3, 3, 4), starts[5], starts[6]),
        ('d_net', (3, 3, 4), starts[6], starts[7]),
        ('pd_linear', (2, 3), starts[7], starts[7] + 6),
    ]
    assert spec.genome_size == starts[7] + 6


def test_output_slices_tile_the_output_vector():
    spec = NetworkSpec.paper(4)
    sl = spec.output_slices()
    assert (sl['inertia'].start, sl['inertia'].stop) == (0, 10)
    assert (sl['coriolis'].start, sl['coriolis'].stop) == (10, 10 + 4 * 6)
    assert (sl['centrifugal'].start, sl['centrifugal'].stop) == (34, 34 + 16)
    assert (sl['gravity'].start, sl['gravity'].stop) == (50, 54)
    assert spec.n_outputs == 54
    assert spec.output_scales(unit_scales(4)).shape == (54,)
    # V from M's Christoffel symbols: no B and C outputs
    spec = NetworkSpec(4, velocity='christoffel')
    sl = spec.output_slices()
    assert (sl['gravity'].start, sl['gravity'].stop) == (10, 14)
    assert sl['coriolis'].stop - sl['coriolis'].start == 0
    assert sl['centrifugal'].stop - sl['centrifugal'].start == 0
    assert spec.n_outputs == 14


def test_recommended_structure_is_smaller_than_the_papers():
    # 3 units, bias, V from M: 3 × (3 + 1 + 9) + 9 + 6 = 54 elements against 126 with B, C
    spec = NetworkSpec.recommended(3, 'torque')
    assert spec.genome_size == expected_size(3, bias=True, velocity=spec.velocity)
    assert spec.inertia == 'cholesky'


@pytest.mark.parametrize('kwargs, message', [
    ({'n_joints': 0}, 'n_joints must be an integer >= 1'),
    ({'n_joints': -2}, 'n_joints must be an integer >= 1'),
    ({'n_joints': 2.5}, 'n_joints must be an integer >= 1'),
    ({'n_joints': '3'}, 'n_joints must be an integer >= 1'),
    ({'n_joints': 3, 'case': 'torques'}, 'case must be one of'),
    ({'n_joints': 3, 'inertia': 'spd'}, 'inertia must be one of'),
    ({'n_joints': 3, 'theta_units': -1}, 'theta_units and torque_units must be >= 0'),
    ({'n_joints': 3, 'torque_units': -1}, 'theta_units and torque_units must be >= 0'),
    ({'n_joints': 3, 'theta_units': 0}, 'theta_units = 0 needs bias'),
    ({'n_joints': 3, 'case': 'unknown', 'torque_units': 0}, "case 'unknown' needs torque_units"),
    ({'n_joints': 3, 'coulomb_velocity': 0.0}, 'coulomb_velocity must be > 0'),
    ({'n_joints': 3, 'coulomb_velocity': float('nan')}, 'coulomb_velocity must be > 0'),
    ({'n_joints': 3, 'velocity': 'lagrange'}, 'velocity must be one of'),
    ({'n_joints': 3, 'inertia_floor': 0.0}, r'inertia_floor must be in \(0, 1\)'),
    ({'n_joints': 3, 'inertia_floor': 1.0}, r'inertia_floor must be in \(0, 1\)'),
])
def test_invalid_specs_are_rejected(kwargs, message):
    with pytest.raises(ValueError, match=message):
        NetworkSpec(**kwargs)


def test_valid_edge_specs_are_accepted():
    assert NetworkSpec(2, theta_units=0, bias=True).genome_size == 11 + 4
    assert NetworkSpec(2, 'unknown', torque_units=0, torque_linear=True).genome_size == 46 + 4


def test_spec_dict_round_trip_and_unknown_settings():
    spec = NetworkSpec(4, 'unknown', theta_units=2, torque_units=1, inertia='cholesky',
                       bias=True, torque_linear=True, coulomb_velocity=0.1)
    assert NetworkSpec.from_dict(spec.to_dict()) == spec
    d = spec.to_dict()
    d['hidden_layers'] = 2
    with pytest.raises(ValueError, match=r"unknown settings \['hidden_layers'\]"):
        NetworkSpec.from_dict(d)


def test_check_genome():
    spec = NetworkSpec.paper(2)
    g = spec.initial_genome()
    np.testing.assert_array_equal(check_genome(spec, list(g)), g)
    with pytest.raises(ValueError, match='genome has 45 elements, the network needs 46'):
        check_genome(spec, g[:-1])
    g[3] = np.nan
    with pytest.raises(ValueError, match='NaN or inf'):
        check_genome(spec, g)

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
The core computes what it computed before it was restructured (commit 6d3b752).

Costs, rollouts, model terms, equation-error residuals, the least-squares warm start and
the PD-tuning cost of fixed genomes on fixed data (``golden_core.py``), against the values
stored from that commit. The tolerance, 1e-10 relative, is the one the compiled kernels and
the numpy reference are held to; divergence (inf costs, NaN rollout rows) must match exactly.
"""

import json

import golden_core
import numpy as np
import pytest

RTOL = 1e-10


@pytest.fixture(scope='module')
def outputs():
    with open(golden_core.PATH, encoding='utf-8') as f:
        stored = json.load(f)
    return stored, golden_core.compute()


def assert_same(got, want, what):
    got = np.asarray(got, dtype=float)
    want = np.asarray(want, dtype=float)
    assert got.shape == want.shape, what
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want), err_msg=what)
    np.testing.assert_array_equal(np.isposinf(got), np.isposinf(want), err_msg=what)
    fin = np.isfinite(want)
    scale = np.max(np.abs(want[fin])) if np.any(fin) else 1.0
    np.testing.assert_allclose(got[fin], want[fin], rtol=RTOL, atol=RTOL * scale, err_msg=what)


@pytest.mark.parametrize('name', [name for name, _ in golden_core.specs()] + ['tracking'])
def test_outputs_equal_those_before_the_restructuring(outputs, name):
    stored, now = outputs
    assert set(now[name]) == set(stored[name])
    for key, want in stored[name].items():
        if isinstance(want, dict):
            assert set(now[name][key]) == set(want)
            for term, value in want.items():
                assert_same(now[name][key][term], value, f'{name}.{key}.{term}')
        else:
            assert_same(now[name][key], want, f'{name}.{key}')


def test_the_stored_costs_discriminate(outputs):
    stored, _ = outputs
    costs = np.array([stored[name]['cost_10'] for name, _ in golden_core.specs()])
    assert np.sum(np.isfinite(costs)) >= 20          # most configurations give finite costs
    assert np.unique(costs[np.isfinite(costs)]).size == np.sum(np.isfinite(costs))

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

"""The inputs at the RKG stage times: held and interpolated torque, Hermite reference."""

import numpy as np
import pytest
from rkgnn_ros.core.integration.inputs import hermite, stage_inputs, stage_times


def test_stage_inputs_of_measured_torque():
    t = np.arange(5) * 0.1
    tau = np.column_stack([t ** 2, -t])
    held = stage_inputs('torque', t, 2, tau=tau)
    assert held.shape == (4, 2, 3, 2)
    np.testing.assert_array_equal(held, np.broadcast_to(tau[:-1, None, None], held.shape))
    linear = stage_inputs('torque', t, 2, tau=tau, torque_interpolation='linear')
    times = stage_times(0.0, 0.1, 4, 2)  # (4, 2, 3): t, t + h/2, t + h of each substep
    expected = np.stack([np.interp(times, t, tau[:, j]) for j in range(2)], axis=-1)
    np.testing.assert_allclose(linear, expected, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(times[1, 1], [0.15, 0.175, 0.2])


def test_hermite_is_exact_for_cubics():
    t = np.linspace(0.0, 1.0, 11)
    coef = np.array([[0.5, -1.0], [2.0, 0.3], [-1.0, 1.5], [0.7, -0.2]])  # cubic per column

    def cubic(s):
        return sum(coef[p] * s[:, None] ** p for p in range(4))

    def slope(s):
        return sum(p * coef[p] * s[:, None] ** (p - 1) for p in range(1, 4))

    s = np.linspace(-0.05, 1.0, 97)
    inside = s >= 0.0
    out = hermite(t, cubic(t), slope(t), s)
    np.testing.assert_allclose(out[inside], cubic(s[inside]), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(out[~inside], cubic(t[:1]).repeat((~inside).sum(), axis=0))


@pytest.mark.parametrize('substeps', [1, 3, 8])
def test_stage_inputs_of_samples_are_hermite_at_the_stage_times(substeps):
    rng = np.random.default_rng(substeps)
    t = 0.37 + 0.01 * np.arange(41)
    theta_d, theta_d_dot = rng.standard_normal((41, 3)), rng.standard_normal((41, 3))
    u = stage_inputs('pd_gains', t, substeps, theta_d=theta_d, theta_d_dot=theta_d_dot)
    times = stage_times(t[0], 0.01, 40, substeps).reshape(-1)
    acc = np.gradient(theta_d_dot, 0.01, axis=0)
    want = np.concatenate([hermite(t, theta_d, theta_d_dot, times),
                           hermite(t, theta_d_dot, acc, times)], axis=-1)
    np.testing.assert_allclose(u.reshape(-1, 6), want, rtol=0, atol=1e-12)
    assert u.shape == (40, substeps, 3, 6) and u.flags['C_CONTIGUOUS']

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

"""The compiled single-state forward dynamics equals the plant's numpy forward dynamics."""

import numpy as np
from plant_helpers import random_arm, random_states
import pytest
from rkgnn_ros.core.sim.parameters import MASS_MODELS
from rkgnn_ros.core.sim.plant_kernels import (forward_dynamics_into, forward_dynamics_kernel,
                                              KernelConstants)

SIZES = (1, 2, 3, 5)


@pytest.fixture
def rng():
    return np.random.default_rng(20260521)


@pytest.mark.parametrize('mass_model', MASS_MODELS)
@pytest.mark.parametrize('n', SIZES)
def test_public_compiled_kernels_match_numpy(n, mass_model, rng):
    arm = random_arm(n, mass_model, rng)
    theta, theta_dot, theta_ddot = random_states(n, rng)
    tau = arm.inverse_dynamics(theta, theta_dot, theta_ddot)
    expected = arm.forward_dynamics(theta, theta_dot, tau)           # batched numpy path
    constants = arm.kernel_constants()
    assert isinstance(constants, KernelConstants)
    assert constants.d.shape == (n, n) and constants.gh.shape == (n,)
    assert isinstance(constants.coulomb_velocity, float)
    work, out = np.full((n + 3, n), np.nan), np.full(n, np.nan)
    for k in range(theta.shape[0]):
        np.testing.assert_allclose(
            forward_dynamics_kernel(theta[k], theta_dot[k], tau[k], *constants), expected[k],
            rtol=1e-12, atol=1e-12)
        forward_dynamics_into(theta[k], theta_dot[k], tau[k], *constants, work, out)
        np.testing.assert_allclose(out, expected[k], rtol=1e-12, atol=1e-12)

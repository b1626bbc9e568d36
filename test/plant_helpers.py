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

"""Helpers shared by the tests of the simulated plant: random arms and random states."""

import numpy as np
from rkgnn_ros.core.sim.parameters import ArmParameters
from rkgnn_ros.core.sim.plant import PlanarArm


def random_arm(n, mass_model, rng, friction=True, gravity=9.81):
    """Return an n-link arm with random masses, lengths and friction."""
    return PlanarArm(ArmParameters(
        masses=rng.uniform(0.5, 6.0, n), lengths=rng.uniform(0.1, 0.5, n),
        mass_model=mass_model, gravity=gravity,
        viscous=rng.uniform(0.0, 0.5, n) if friction else None,
        coulomb=rng.uniform(0.0, 0.3, n) if friction else None))


def random_states(n, rng, count=40):
    """Return random θ, θ̇, θ̈, each of shape (count, n)."""
    return (rng.uniform(-np.pi, np.pi, (count, n)), rng.normal(0.0, 2.0, (count, n)),
            rng.normal(0.0, 5.0, (count, n)))

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

"""The set-up precompile drives the online policy to a published, predicting model."""

import os
import sys

from repo_paths import REPO_ROOT

sys.path.insert(0, os.path.join(REPO_ROOT,
                                'tools'))

import precompile  # noqa: E402, I100  (tools/precompile.py, run by make build)
from rkgnn_ros.core.sim.plant import PDController, PlanarArm  # noqa: E402
from rkgnn_ros.core.sim.simulate import simulate  # noqa: E402
from rkgnn_ros.core.sim.trajectories import paper_reference  # noqa: E402


def test_the_precompile_reaches_a_published_model_in_every_case():
    data = simulate(PlanarArm.paper(), PDController.paper(), paper_reference(3), 4.0,
                    rate=100.0, joint_names=precompile.JOINTS)
    for case in ('torque', 'pd_gains', 'unknown'):
        assert precompile.run_case(data, case, {}) >= 2


def test_the_precompile_covers_the_default_network_and_the_trigonometric_dispatch():
    assert {} in precompile.NETWORKS
    assert any('trig' in network.get('basis', '') for network in precompile.NETWORKS)

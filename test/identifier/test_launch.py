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

"""The launch file is installed and well-formed (and builds its description if launch exists)."""

import ast
import os

import pytest
from repo_paths import REPO_ROOT

LAUNCH = os.path.join(REPO_ROOT, 'launch', 'identify_sim.launch.py')


def test_launch_file_starts_both_nodes_with_their_config():
    tree = ast.parse(open(LAUNCH, encoding='utf-8').read())
    calls = [n for n in ast.walk(tree) if isinstance(n, ast.Call)
             and getattr(n.func, 'id', None) == 'Node']
    executables = sorted(kw.value.value for c in calls for kw in c.keywords
                         if kw.arg == 'executable')
    assert executables == ['identifier', 'sim_arm']
    text = open(LAUNCH, encoding='utf-8').read()
    assert "'sim_arm.yaml'" in text and "'identifier.yaml'" in text
    for name in ('sim_arm.yaml', 'identifier.yaml'):
        assert os.path.exists(os.path.join(REPO_ROOT, 'config', name))


def test_launch_description_builds():
    launch = pytest.importorskip(
        'launch', reason='the launch package is not published on PyPI; with ROS 2 Jazzy '
        'installed this builds the launch description')
    pytest.importorskip('launch_ros')
    import importlib.util
    spec = importlib.util.spec_from_file_location('identify_sim', LAUNCH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert isinstance(module.generate_launch_description(), launch.LaunchDescription)

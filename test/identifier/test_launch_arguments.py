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

"""The launch file's namespace and use_sim_time arguments reach both nodes."""

import ast
import os

import pytest
from repo_paths import REPO_ROOT

LAUNCH = os.path.join(REPO_ROOT, 'launch', 'identify_sim.launch.py')


def _calls(name):
    tree = ast.parse(open(LAUNCH, encoding='utf-8').read())
    return [n for n in ast.walk(tree) if isinstance(n, ast.Call)
            and getattr(n.func, 'id', None) == name]


def test_namespace_and_use_sim_time_are_arguments_passed_to_both_nodes():
    declared = {c.args[0].value for c in _calls('DeclareLaunchArgument')}
    assert {'namespace', 'use_sim_time', 'sim'} <= declared
    for node in _calls('Node'):
        keywords = {kw.arg: ast.unparse(kw.value) for kw in node.keywords}
        assert keywords['namespace'] == 'namespace'
        assert 'sim_time' in keywords['parameters']
    assert "LaunchConfiguration('use_sim_time')" in open(LAUNCH, encoding='utf-8').read()


def test_the_description_declares_namespace_and_sim_time():
    reason = ('launch_ros is not published on PyPI; with ROS 2 Jazzy installed this builds '
              'the launch description')
    pytest.importorskip('launch', reason=reason)
    pytest.importorskip('launch_ros', reason=reason)
    import importlib.util
    from launch.actions import DeclareLaunchArgument
    spec = importlib.util.spec_from_file_location('identify_sim', LAUNCH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    description = module.generate_launch_description()
    declared = {a.name: a.default_value for a in description.entities
                if isinstance(a, DeclareLaunchArgument)}
    assert {'namespace', 'use_sim_time', 'sim'} <= set(declared)
    assert len([a for a in description.entities if type(a).__name__ == 'Node']) == 2

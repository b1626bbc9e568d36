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

"""bench/online_servos.py's figures from recorded streams, without running a cell."""

import importlib.util
import os
import sys

import numpy as np
import pytest
from repo_paths import REPO_ROOT

_BENCH = os.path.join(REPO_ROOT, 'bench')
_PATH = os.path.join(_BENCH, 'online_servos.py')
if _BENCH not in sys.path:
    sys.path.insert(0, _BENCH)  # its sibling bench/monitor.py
_SPEC = importlib.util.spec_from_file_location('online_servos', _PATH)
online_servos = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(online_servos)


def _recording(offset):
    """Return (snapshot, commands): an arm 0.1 s behind its plan, predictions ``offset`` off."""
    t = np.arange(0.0, 40.0, 0.01)
    amplitude = np.array([1.0, 0.8, 0.6])
    theta = amplitude * np.sin(t[:, None] - 0.1)
    theta_d = amplitude * np.sin(t[:, None])
    offs = np.arange(0.0, 2.001, 0.01)
    t0s = list(np.arange(1.0, 37.0, 0.1))
    thetas = [amplitude * np.sin(t0 + offs[:, None] - 0.1) + offset for t0 in t0s]
    snapshot = (t, theta, t0s, [offs] * len(t0s), thetas, [], None)
    return snapshot, (t, theta_d)


def test_the_worst_joint_ratio_sees_a_joint_the_average_hides():
    # exact on two joints, 0.06 rad off on the third: over the joints the published error
    # is below following the reference's; on the third joint it is above
    snapshot, commands = _recording(np.array([0.0, 0.0, 0.06]))
    cell = online_servos.score(snapshot, commands, 2.0, 40.0)
    assert cell['self_check_ratio'] < 1.0
    assert cell['self_check_worst_joint_ratio'] > 1.3
    worst = cell['self_check_worst_joint']
    assert worst['joint'] == 2
    assert worst['prediction'] / worst['follow_reference'] == pytest.approx(
        cell['self_check_worst_joint_ratio'])
    snapshot, commands = _recording(np.zeros(3))
    assert online_servos.score(snapshot, commands, 2.0, 40.0)[
        'self_check_worst_joint_ratio'] < 1e-9


def test_the_summary_takes_the_worst_cell_and_an_old_cell_counts_as_unknown():
    cell = {'prediction_nrmse_60s': 0.01, 'follow_reference_nrmse': 0.1,
            'self_check_ratio': 0.5, 'self_check_worst_joint_ratio': 0.9}
    results = {'pd': {'exact': {'1': cell, '3': dict(cell, self_check_worst_joint_ratio=1.3)}}}
    assert online_servos.summary(results) == pytest.approx((0.1, 0.5, 1.3))
    del results['pd']['exact']['3']['self_check_worst_joint_ratio']
    assert online_servos.summary(results)[2] == float('inf')

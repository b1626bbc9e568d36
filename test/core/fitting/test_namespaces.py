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
Three arms in one domain, each a sim_arm + identifier pair under its own namespace.

The installed executables, started as a user starts them (``-r __ns:=/armK`` with the
package's parameters files, whose ``/**/`` keys apply in any namespace). Each arm's joints
have names of their own, so a sample of another arm reaching an identifier would be
dropped as ``missing_joint`` (or, first, make its model another arm's): each model and each
model file must name its own arm's joints, and no identifier may count such a drop.
"""

import os
import random
import signal
import subprocess
import threading

from ament_index_python.packages import get_package_prefix, get_package_share_directory
from diagnostic_msgs.msg import DiagnosticArray
import pytest
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rkgnn_ros.core.fitting.identify import RKGNNModel
from ros_helpers import spinning_context, wait_for
from std_msgs.msg import String
import yaml

pytestmark = pytest.mark.ros

ARMS = ('arm1', 'arm2', 'arm3')
PATIENCE = 240.0


def joints(arm):
    return [f'{arm}_joint{i}' for i in (1, 2, 3)]


def _installed(name):
    return os.path.join(get_package_prefix('rkgnn_ros'), 'lib', 'rkgnn_ros', name)


def _config(name):
    return os.path.join(get_package_share_directory('rkgnn_ros'), 'config', name)


def _exit_code(process, log, timeout=60.0):
    """Return the exit code; a node still running after ``timeout`` dumps its stacks."""
    try:
        return process.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        process.send_signal(signal.SIGABRT)   # faulthandler: every thread's stack, then ends
        try:
            process.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            pass
        return f'still running {timeout:.0f} s after SIGINT ({log})'


def _tail(path, lines=60):
    with open(path, errors='replace') as f:
        return ''.join(f.readlines()[-lines:])


@pytest.fixture
def three_arms(tmp_path):
    domain = random.randint(100, 230)
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED='1')
    procs, logs = [], []
    try:
        for k, arm in enumerate(ARMS):
            masses = [6.0 - k, 4.0, 3.0 + 0.5 * k]   # three different arms
            for name, extra in (
                    ('sim_arm', ['-p', f'joint_names:={joints(arm)}', '-p',
                                 f'masses:={masses}']),
                    ('identifier', ['-p', 'min_window:=3.0', '-p',
                                    f"model_file:={tmp_path / f'{arm}.yaml'}"])):
                log = open(tmp_path / f'{arm}_{name}.log', 'w')
                logs.append(log)
                procs.append(subprocess.Popen(
                    [_installed(name), '--ros-args', '-r', f'__ns:=/{arm}',
                     '--params-file', _config(f'{name}.yaml')] + extra,
                    env=env, stdout=log, stderr=subprocess.STDOUT))
        yield domain, procs, tmp_path, [log.name for log in logs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for p in procs:
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        for log in logs:
            log.close()


def test_three_namespaced_arms_give_three_models_none_fed_by_another_arm(three_arms):
    domain, procs, folder, logs = three_arms
    models, drops = {}, {}
    lock = threading.Lock()

    def on_model(arm, msg):
        with lock:
            models[arm] = msg.data

    def on_diagnostics(msg):
        for status in msg.status:
            if not status.hardware_id.endswith('/identifier'):
                continue  # the identifier's other parts (its feed-forward) report too
            values = {kv.key: kv.value for kv in status.values}
            with lock:
                drops[status.hardware_id] = int(values.get('drops.missing_joint', 0))

    with spinning_context(domain) as (context, executor):
        probe = Node(f'probe_{random.getrandbits(32):08x}', context=context)
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        for arm in ARMS:
            probe.create_subscription(String, f'/{arm}/identifier/model',
                                      lambda m, arm=arm: on_model(arm, m), latched)
        probe.create_subscription(DiagnosticArray, '/diagnostics', on_diagnostics, 10)
        executor.add_node(probe)
        assert wait_for(lambda: len(models) == len(ARMS) and len(drops) == len(ARMS)
                        or any(p.poll() is not None for p in procs), PATIENCE), \
            f'models from {sorted(models)}, diagnostics from {sorted(drops)}'
        assert all(p.poll() is None for p in procs), 'a node exited early'
        with lock:
            received, counted = dict(models), dict(drops)
    for arm in ARMS:
        model = RKGNNModel.from_yaml(received[arm])
        assert list(model.joint_names) == joints(arm), arm
        assert counted[f'/{arm}/identifier'] == 0, (arm, counted)
    for p in procs:
        p.send_signal(signal.SIGINT)
    for p, log in zip(procs, logs):
        assert _exit_code(p, log) == 0, _tail(log)
    for arm in ARMS:   # each model file written by its own identifier only
        saved = yaml.safe_load((folder / f'{arm}.yaml').read_text())
        assert saved['joint_names'] == joints(arm)

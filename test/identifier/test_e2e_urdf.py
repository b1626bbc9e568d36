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
End to end on a URDF arm: the identifier takes sim_arm's robot_description and identifies.

The installed ``sim_arm`` simulates the UR5 of ``config/sim_arm_ur5.yaml`` and publishes its
``robot_description``; the installed ``identifier`` runs on its defaults (the description
from the topic, ``case: auto``). Checked over the real middleware: ``~/model`` carries a
rigid-body model of the arm's joints, ``/diagnostics`` says the description is in use, the
model's predictions reach ``~/prediction``, and ``~/save_urdf`` writes a URDF that the
rigid-body structure reads back with the same joints.
"""

import os
import random
import subprocess
import time

from ament_index_python.packages import get_package_prefix, get_package_share_directory
import pytest
import yaml

pytestmark = pytest.mark.ros

pytest.importorskip('pinocchio')


def _installed(name):
    return os.path.join(get_package_prefix('rkgnn_ros'), 'lib', 'rkgnn_ros', name)


@pytest.fixture
def urdf_pair(tmp_path):
    domain = random.randint(100, 230)
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED='1')
    config = os.path.join(get_package_share_directory('rkgnn_ros'), 'config')
    procs, logs = [], []
    for name, files, extra in (
            ('sim_arm', ['sim_arm.yaml', 'sim_arm_ur5.yaml'], []),
            ('identifier', ['identifier.yaml'],
             ['-p', f"identified_urdf_file:={tmp_path / 'identified.urdf'}"])):
        log = open(tmp_path / f'{name}.log', 'w')
        logs.append(log)
        cmd = [_installed(name), '--ros-args']
        for f in files:
            cmd += ['--params-file', os.path.join(config, f)]
        procs.append(subprocess.Popen(cmd + extra, env=env, stdout=log,
                                      stderr=subprocess.STDOUT))
    yield domain, procs, tmp_path
    for p in procs:
        if p.poll() is None:
            p.kill()
            p.wait()
    for log in logs:
        log.close()


def test_the_identifier_identifies_the_described_arm_and_writes_its_urdf(urdf_pair):
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from std_msgs.msg import String
    from std_srvs.srv import Trigger
    from trajectory_msgs.msg import JointTrajectory

    domain, procs, tmp_path = urdf_pair
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain)
    node = rclpy.create_node('e2e_urdf_listener', context=ctx)
    models, sources, statuses = [], set(), []
    node.create_subscription(String, 'identifier/model', models.append,
                             QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                                        durability=DurabilityPolicy.TRANSIENT_LOCAL))
    node.create_subscription(JointTrajectory, 'identifier/prediction',
                             lambda msg: sources.add(msg.header.frame_id.split(';')[0]), 10)

    def on_diagnostics(msg):
        for status in msg.status:
            for pair in status.values:
                if pair.key == 'robot_description':
                    statuses.append(pair.value)
    node.create_subscription(DiagnosticArray, '/diagnostics', on_diagnostics, 10)
    client = node.create_client(Trigger, 'identifier/save_urdf')
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    try:
        deadline = time.monotonic() + 150.0     # a fresh clone compiles its kernels first
        while time.monotonic() < deadline and not ('model' in sources and models):
            executor.spin_once(timeout_sec=0.1)
            for p in procs:
                assert p.poll() is None, open(tmp_path / 'identifier.log').read()[-3000:]
        model = yaml.safe_load(models[-1].data)
        assert model['kind'] == 'rigid_body', model.get('kind')
        assert model['joint_names'][0] == 'shoulder_pan_joint' and len(model['bodies']) == 6
        assert 'model' in sources, sources
        assert any(s.startswith('in use') for s in statuses), statuses[-3:]
        assert client.wait_for_service(timeout_sec=10.0)
        future = client.call_async(Trigger.Request())
        executor.spin_until_future_complete(future, timeout_sec=10.0)
        assert future.result().success, future.result().message
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
    from rkgnn_ros.core.rigid.structure import RigidStructure
    text = (tmp_path / 'identified.urdf').read_text()
    structure = RigidStructure(text, model['joint_names'])
    assert structure.n_joints == 6
    assert 'identified by rkgnn_ros' in text

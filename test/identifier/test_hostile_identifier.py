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
The identifier against what the third adversarial probe (issue 31) found.

- ``feedforward.forward_topic`` naming a topic the node uses with another type: the node
  refuses to start with one line naming the parameter, the topic and its type.
"""

import os
import random
import subprocess
import sys

import pytest
import rclpy
from rclpy.context import Context
from rclpy.parameter import Parameter
from repo_paths import REPO_ROOT
from rkgnn_ros.identification.parameters import ConfigurationError
from rkgnn_ros.identifier import IdentifierNode

pytestmark = pytest.mark.ros

ROOT = REPO_ROOT
DOMAIN_ID = int(os.environ.get('ROS_DOMAIN_ID') or random.SystemRandom().randint(150, 199))
JOINTS = ['j1', 'j2', 'j3']
PATIENCE = 60.0


@pytest.fixture
def context():
    """Yield a private rclpy Context, initialised, and shut it down afterwards."""
    ctx = Context()
    rclpy.init(context=ctx, domain_id=DOMAIN_ID)
    yield ctx
    rclpy.try_shutdown(context=ctx)


@pytest.mark.parametrize('topic, kind', [
    ('/diagnostics', 'diagnostic_msgs/msg/DiagnosticArray'),
    ('joint_states', 'sensor_msgs/msg/JointState'),
    ('~/model', 'std_msgs/msg/String'),
    ('/rosout', 'rcl_interfaces/msg/Log')])
def test_a_forward_topic_of_another_type_refuses_to_start(context, topic, kind):
    with pytest.raises(ConfigurationError) as raised:
        IdentifierNode(context=context, namespace=f'/hostile{os.getpid()}', parameter_overrides=[
            Parameter('joints', value=JOINTS),
            Parameter('feedforward.forward_topic', value=topic)])
    message = str(raised.value)
    assert 'feedforward.forward_topic' in message and kind in message, message


def test_a_forward_topic_of_the_same_type_is_taken(context):
    node = IdentifierNode(context=context, namespace=f'/hostile{os.getpid()}',
                          parameter_overrides=[
                              Parameter('joints', value=JOINTS),
                              Parameter('feedforward.forward_topic',
                                        value='/sim_arm/feedforward')])
    try:
        topics = {p.topic_name for p in node.publishers}
        assert '/sim_arm/feedforward' in topics
    finally:
        node.stop()
        node.destroy_node()


def test_the_process_says_why_in_one_line_and_exits_1():
    env = dict(os.environ, ROS_DOMAIN_ID=str(DOMAIN_ID),
               PYTHONPATH=os.pathsep.join(filter(None, [ROOT, os.environ.get('PYTHONPATH')])))
    proc = subprocess.run(
        [sys.executable, '-m', 'rkgnn_ros.identifier', '--ros-args', '-p',
         f'joints:={JOINTS}', '-p', 'feedforward.forward_topic:=/diagnostics'],
        env=env, capture_output=True, text=True, timeout=4 * PATIENCE)
    assert proc.returncode == 1, proc.stderr[-2000:]
    assert 'Traceback' not in proc.stderr, proc.stderr[-2000:]
    assert 'refusing to start' in proc.stderr and 'DiagnosticArray' in proc.stderr

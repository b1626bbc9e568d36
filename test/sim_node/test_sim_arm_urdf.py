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

"""sim_arm with a URDF arm: the configuration, the simulation, the node's topics, bad URDFs."""

import os
from pathlib import Path
import random
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip('pinocchio')

from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from repo_paths import REPO_ROOT  # noqa: E402
from rkgnn_ros.core.sim.arm_simulator import ArmSimulator  # noqa: E402
from rkgnn_ros.core.sim.servo import Servo  # noqa: E402
from rkgnn_ros.core.sim.simulate import simulate  # noqa: E402
from rkgnn_ros.core.sim.urdf_arm import UrdfArm  # noqa: E402
from rkgnn_ros.sim_arm import SimArm  # noqa: E402
from rkgnn_ros.sim_node.parameters import (build_config, ConfigurationError,  # noqa: E402
                                           PARAMETERS)
from ros_helpers import retire_node, spinning_context, wait_for  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import String  # noqa: E402
from urdf_helpers import planar_urdf  # noqa: E402

REPO = Path(REPO_ROOT)
DOMAIN_ID = int(os.environ.get('ROS_DOMAIN_ID') or random.SystemRandom().randint(150, 199))
PATIENCE = 60.0
UR5 = 'example-robot-data:ur_description/urdf/ur5_robot.urdf'
UR5_GAINS = {'kp': [400.0, 400.0, 200.0, 40.0, 40.0, 10.0],
             'kd': [40.0, 40.0, 20.0, 3.0, 3.0, 0.3],
             'viscous': [2.0, 2.0, 1.0, 0.3, 0.3, 0.1],
             'coulomb': [1.0, 1.0, 0.5, 0.2, 0.2, 0.05], 'integration_step': 0.002}
HOME = [0.0, -1.57, 1.57, -1.57, -1.57, 0.0]


def values(**overrides):
    """Return sim_arm's parameter values: the defaults with ``overrides`` (dots as __)."""
    out = {spec.name: spec.default for spec in PARAMETERS}
    out.update({name.replace('__', '.'): value for name, value in overrides.items()})
    return out


def test_a_robot_description_makes_sim_arm_simulate_the_urdf_arm():
    config, warnings = build_config(values(robot_description=UR5, urdf__home=HOME,
                                           **UR5_GAINS))
    assert isinstance(config.arm, UrdfArm)
    assert config.joint_names == ('shoulder_pan_joint', 'shoulder_lift_joint', 'elbow_joint',
                                  'wrist_1_joint', 'wrist_2_joint', 'wrist_3_joint')
    assert '<robot name="ur5"' in config.robot_description
    np.testing.assert_allclose(config.arm.viscous, UR5_GAINS['viscous'])
    theta_d, _ = config.reference.evaluate(np.linspace(0.0, 60.0, 601))
    # the paper's sines about the home pose
    np.testing.assert_allclose(theta_d.mean(axis=0), HOME, atol=0.1)
    assert not warnings
    planar, _ = build_config(values())
    assert planar.robot_description == ''
    assert planar.joint_names == ('joint1', 'joint2', 'joint3')


def test_locked_joints_and_a_reference_beyond_the_limits_are_taken_and_warned():
    xml = planar_urdf([2.0, 1.0, 0.5], [0.3, 0.2, 0.1])
    config, warnings = build_config(values(
        robot_description=xml, urdf__joints=['joint1', 'joint2'],
        urdf__locked_joints=['joint3'], urdf__locked_positions=[0.4], urdf__home=[-1.5, 2.8],
        kp=[50.0, 20.0], kd=[5.0, 2.0], viscous=[0.1, 0.1], coulomb=[0.0, 0.0]))
    assert config.joint_names == ('joint1', 'joint2')
    assert config.arm.locked == {'joint3': 0.4}
    assert any("leaves the URDF limits of ['joint2']" in w for w in warnings), warnings


@pytest.mark.parametrize('overrides, message', [
    ({'robot_description': '/no/such/arm.urdf'}, "cannot read '/no/such/arm.urdf'"),
    ({'robot_description': '<robot name="x"><link></robot>'}, 'not valid XML'),
    ({'robot_description': UR5, 'urdf.joints': ['elbow']}, "no joint named 'elbow'"),
    ({'robot_description': planar_urdf([1.0], [0.3], limits=False)},
     "'joint1' has no usable <limit lower upper>"),
    ({'robot_description': planar_urdf([1.0, 1.0], [0.3, 0.2], inertial=False)},
     'move no inertia'),
    ({'robot_description': UR5, 'urdf.locked_joints': ['elbow_joint'],
      'urdf.joints': ['shoulder_pan_joint'], 'urdf.locked_positions': []},
     'urdf.locked_positions has 0 values'),
    ({'robot_description': UR5, 'urdf.home': [0.0]}, 'urdf.home has 1 values'),
    ({'robot_description': UR5}, 'viscous has 3 values but the arm has 6 joints'),
])
def test_bad_urdf_settings_are_refused_naming_the_problem(overrides, message):
    given = values()
    given.update(overrides)
    with pytest.raises(ConfigurationError) as info:
        build_config(given)
    assert message in str(info.value)


def test_the_node_simulator_on_a_urdf_arm_follows_the_accurate_simulation():
    config, _ = build_config(values(robot_description=UR5, urdf__home=HOME, **UR5_GAINS))
    sim = ArmSimulator(config.arm, config.kp, config.kd, config.reference, 0.002,
                       compiled=False)
    states = []
    for k in range(1, 101):
        sim.advance(0.01 * k)
        states.append(sim.sample()[0])
    truth = simulate(config.arm, Servo(config.kp, config.kd), config.reference, 1.0)
    # fixed RK steps of 2 ms against the adaptive solver at rtol 1e-9
    assert np.max(np.abs(np.array(states) - truth.theta[1:])) < 1e-5


def test_the_node_publishes_the_urdf_and_its_joint_states():
    xml = planar_urdf([2.0, 1.0], [0.3, 0.2])
    with spinning_context(DOMAIN_ID) as (context, executor):
        probe = Node(f'probe_{random.getrandbits(32):08x}', context=context)
        received = {'states': [], 'description': []}
        probe.create_subscription(JointState, 'joint_states', received['states'].append,
                                  QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
        probe.create_subscription(
            String, 'robot_description', received['description'].append,
            QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.TRANSIENT_LOCAL))
        executor.add_node(probe)
        overrides = {'robot_description': xml, 'kp': [50.0, 20.0], 'kd': [5.0, 2.0],
                     'viscous': [0.1, 0.1], 'coulomb': [0.0, 0.0]}
        node = SimArm(context=context, parameter_overrides=[
            Parameter(name, value=value) for name, value in overrides.items()])
        executor.add_node(node)
        try:
            assert wait_for(lambda: len(received['states']) >= 20 and received['description'],
                            PATIENCE)
            state = received['states'][-1]
            assert list(state.name) == ['joint1', 'joint2']
            assert np.all(np.isfinite(state.position)) and len(state.effort) == 2
            assert received['description'][0].data.startswith('<robot name="planar"')
        finally:
            retire_node(executor, node)
            retire_node(executor, probe)


def test_a_bad_urdf_stops_the_node_at_start_with_exit_code_1():
    env = dict(os.environ, PYTHONPATH=str(REPO), ROS_DOMAIN_ID=str(DOMAIN_ID))
    process = subprocess.Popen(
        [sys.executable, '-m', 'rkgnn_ros.sim_arm', '--ros-args', '-p',
         'robot_description:=/no/such/arm.urdf'], env=env, cwd=str(REPO),
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    output, _ = process.communicate(timeout=2 * PATIENCE)
    assert process.returncode == 1, output
    assert "cannot read '/no/such/arm.urdf'" in output and 'Traceback' not in output, output

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

"""ros2_control inputs: a controller's state as commands, its gains as case 2's kp, kd."""

import math
import os
import random
from types import SimpleNamespace as Msg

import numpy as np
import pytest
from rclpy.node import Node
from rclpy.parameter import Parameter
from rkgnn_ros.identification.parameters import ConfigurationError
from rkgnn_ros.identification.ros2_control import controller_gains
from rkgnn_ros.identifier import IdentifierNode
from rkgnn_ros.wire.controller_state import (control_msgs_available, CONTROL_MSGS_REASON,
                                             controller_state_to_joint_state)
from rkgnn_ros.wire.conversions import joint_state_to_arrays, Rejection, seconds_to_stamp
from ros_helpers import retire_node, Rosout, spinning_context, wait_for

DOMAIN_ID = int(os.environ.get('ROS_DOMAIN_ID') or random.SystemRandom().randint(150, 199))
JOINTS = ('joint1', 'joint2', 'joint3')
PATIENCE = 60.0


def point(positions=(), velocities=(), effort=()):
    return Msg(positions=list(positions), velocities=list(velocities), effort=list(effort))


def state(reference=None, desired=None, output=None, names=JOINTS, stamp=12.5):
    fields = {'header': Msg(stamp=seconds_to_stamp(stamp), frame_id='base'),
              'joint_names': list(names)}
    if reference is not None:
        fields['reference'] = reference
    if desired is not None:
        fields['desired'] = desired
    if output is not None:
        fields['output'] = output
    return Msg(**fields)


def test_a_jazzy_controller_state_is_a_command_with_the_commanded_effort():
    msg = state(reference=point([0.1, 0.2, 0.3], [1.0, 2.0, 3.0]),
                output=point(effort=[4.0, 5.0, 6.0]))
    command = controller_state_to_joint_state(msg)
    sample = joint_state_to_arrays(command, JOINTS, need_velocity=True, need_effort=True)
    assert sample.ok and sample.stamp == pytest.approx(12.5)
    np.testing.assert_allclose(sample.position, [0.1, 0.2, 0.3])
    np.testing.assert_allclose(sample.velocity, [1.0, 2.0, 3.0])
    np.testing.assert_allclose(sample.effort, [4.0, 5.0, 6.0])


def test_a_humble_controller_state_reads_desired_and_has_no_effort_without_output():
    command = controller_state_to_joint_state(
        state(desired=point([0.1, 0.2, 0.3], [1.0, 2.0, 3.0])))
    assert list(command.position) == [0.1, 0.2, 0.3]
    assert all(math.isnan(v) for v in command.effort)


@pytest.mark.parametrize('msg, reason', [
    (state(reference=point([0.1, 0.2], [1.0, 2.0])), 'size_mismatch'),
    (state(reference=point([0.1, 0.2, 0.3], [1.0])), 'size_mismatch'),
    (state(reference=point([0.1, 0.2, 0.3])), 'missing_velocity'),
    (state(reference=point()), 'malformed'),
    (state(reference=point([0.1], [1.0]), names=()), 'malformed'),
    (Msg(data='not a controller state'), 'malformed'),
])
def test_a_controller_state_it_cannot_use_is_rejected_with_the_reason(msg, reason):
    rejection = controller_state_to_joint_state(msg)
    assert isinstance(rejection, Rejection) and rejection.reason == reason


def test_controller_gains_become_kp_and_kd_and_bad_ones_are_named():
    values = {'joints': JOINTS, 'kp': (), 'kd': ()}
    given = {'gains.joint1.p': 30.0, 'gains.joint2.p': 40.0, 'gains.joint3.p': 50.0,
             'gains.joint1.d': 3.0, 'gains.joint3.d': 5.0}
    taken = controller_gains(values, given, ValueError)
    assert taken['kp'] == (30.0, 40.0, 50.0) and taken['kd'] == (3.0, 0.0, 5.0)
    assert controller_gains({'joints': JOINTS, 'kp': (30.0, 40.0, 50.0), 'kd': ()}, given,
                            ValueError)['kd'] == (3.0, 0.0, 5.0)
    with pytest.raises(ValueError, match='gains.joint2.p missing'):
        controller_gains(values, {'gains.joint1.p': 1.0, 'gains.joint3.p': 1.0}, ValueError)
    with pytest.raises(ValueError, match=r'kp \[1.0, 1.0, 1.0\] disagrees'):
        controller_gains(dict(values, kp=(1.0, 1.0, 1.0)), given, ValueError)
    with pytest.raises(ValueError, match='gains.elbow.p: not a configured joint'):
        controller_gains(values, {'gains.elbow.p': 1.0}, ValueError)
    with pytest.raises(ValueError, match='must be >= 0'):
        controller_gains(values, dict(given, **{'gains.joint1.d': -1.0}), ValueError)
    assert controller_gains({'joints': (), 'kp': ()}, {}, ValueError)['kp'] == ()


@pytest.fixture(scope='module')
def ros():
    with spinning_context(DOMAIN_ID) as (context, executor):
        yield context, executor


def test_the_identifier_takes_case_2_gains_in_the_controllers_form(ros):
    context, executor = ros
    kp, kd = (32.84, 42.05, 42.31), (42.44, 0.19, 4.86)
    gains = [Parameter(f'gains.{joint}.{term}', value=value)
             for joint, p, d in zip(JOINTS, kp, kd) for term, value in (('p', p), ('d', d))]
    base = [Parameter('case', value='pd_gains'), Parameter('joints', value=list(JOINTS))]
    node = IdentifierNode('identifier_gains', context=context,
                          parameter_overrides=base + gains)  # kp, kd empty: taken from gains
    node.stop()
    node.destroy_node()
    with pytest.raises(ConfigurationError, match='gains.joint3.p missing'):
        IdentifierNode('identifier_gains_missing', context=context,
                       parameter_overrides=base + gains[:4])
    with pytest.raises(ConfigurationError, match='disagrees with gains'):
        IdentifierNode('identifier_gains_both', context=context, parameter_overrides=base + gains
                       + [Parameter('kp', value=[1.0, 1.0, 1.0]),
                          Parameter('kd', value=[1.0, 1.0, 1.0])])


@pytest.mark.skipif(control_msgs_available(), reason='control_msgs is importable here: the '
                    'live input is tested by the next test instead')
def test_without_control_msgs_the_controller_state_input_is_off_and_says_why(ros):
    context, executor = ros
    probe = Node(f'probe_{random.getrandbits(32):08x}', context=context)
    rosout = Rosout(probe)
    executor.add_node(probe)
    node = IdentifierNode('identifier_jtc', context=context, parameter_overrides=[
        Parameter('controller_state', value='/jtc/controller_state')])
    executor.add_node(node)
    try:
        assert wait_for(lambda: rosout.lines('identifier_jtc', 'control_msgs is not importable',
                                             level='warning'), PATIENCE)
    finally:
        node.stop()
        retire_node(executor, node)
        retire_node(executor, probe)


@pytest.mark.skipif(not control_msgs_available(), reason=CONTROL_MSGS_REASON)
def test_a_live_controller_state_feeds_the_command_stream(ros):
    from control_msgs.msg import JointTrajectoryControllerState
    from diagnostic_msgs.msg import DiagnosticArray
    from rkgnn_ros.wire.conversions import make_joint_state
    from sensor_msgs.msg import JointState
    from trajectory_msgs.msg import JointTrajectoryPoint
    context, executor = ros
    node = IdentifierNode('identifier_live_jtc', context=context, parameter_overrides=[
        Parameter('case', value='unknown'), Parameter('controller_state',
                                                      value='/jtc/controller_state')])
    probe = Node(f'probe_{random.getrandbits(32):08x}', context=context)
    buffered = []
    probe.create_subscription(DiagnosticArray, '/diagnostics', lambda m: buffered.extend(
        int(kv.value) for s in m.status if s.name == 'identifier_live_jtc'
        for kv in s.values if kv.key == 'samples_buffered'), 10)
    states = probe.create_publisher(JointState, 'joint_states', 10)
    controller = probe.create_publisher(JointTrajectoryControllerState,
                                        '/jtc/controller_state', 10)
    executor.add_node(node)
    executor.add_node(probe)
    try:
        for k in range(300):
            t = 1000.0 + 0.01 * k
            stamp = seconds_to_stamp(t)
            theta = np.sin([t, 2 * t, 3 * t])
            states.publish(make_joint_state(stamp, JOINTS, theta, np.cos([t, t, t]), None))
            msg = JointTrajectoryControllerState()
            msg.header.stamp = stamp
            msg.joint_names = list(JOINTS)
            msg.reference = JointTrajectoryPoint(positions=list(theta),
                                                 velocities=[0.0, 0.0, 0.0])
            controller.publish(msg)
        # case 3 buffers a state only when a command covers it: the controller's did
        assert wait_for(lambda: buffered and max(buffered) > 100, PATIENCE)
    finally:
        node.stop()
        retire_node(executor, node)
        retire_node(executor, probe)

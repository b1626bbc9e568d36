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
sim_arm with real servos and drivers: PID, gravity compensation, limits, what is published.

In-process nodes on a private ``rclpy.Context`` (domain 150-199 unless ROS_DOMAIN_ID is
set), executor spinning in a background thread, as in ``test_sim_arm.py``.
"""

import os
import random
import re

import numpy as np
import pytest
from rcl_interfaces.srv import SetParameters
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rkgnn_ros.core.sim.arm_simulator import ArmSimulator
from rkgnn_ros.core.sim.plant import PlanarArm
from rkgnn_ros.core.sim.servo import Servo
from rkgnn_ros.core.sim.simulate import simulate
from rkgnn_ros.core.sim.trajectories import paper_reference
from rkgnn_ros.sim_arm import SimArm
from rkgnn_ros.sim_node.parameters import ConfigurationError
from ros_helpers import retire_node, spinning_context, stamp_ns, wait_for
from sensor_msgs.msg import JointState

pytestmark = pytest.mark.ros

DOMAIN_ID = int(os.environ.get('ROS_DOMAIN_ID') or random.SystemRandom().randint(150, 199))
KP = np.array([32.84, 42.05, 42.31])
KD = np.array([42.44, 0.19, 4.86])
ARM = PlanarArm.paper()


@pytest.fixture(scope='module')
def ros():
    """Yield (context, executor) with the executor spinning in a background thread."""
    with spinning_context(DOMAIN_ID) as pair:
        yield pair


def record(context, executor, count, **overrides):
    """Start sim_arm with ``overrides``, return (node, the first ``count`` joint_states)."""
    probe = Node(f'probe_{random.getrandbits(32):08x}', context=context)
    states = []
    probe.create_subscription(JointState, 'joint_states', states.append,
                              QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))
    executor.add_node(probe)
    node = SimArm(context=context, parameter_overrides=[
        Parameter(name, value=value) for name, value in overrides.items()])
    executor.add_node(node)
    try:
        assert wait_for(lambda: len(states) >= count, 30.0), f'no {count} joint_states'
        origin = node.time_origin_ns
        return node, probe, states[:count], origin
    except BaseException:
        retire_node(executor, node)
        retire_node(executor, probe)
        raise


def test_simulator_runs_every_servo_like_simulate_and_compiled_like_numpy():
    reference = paper_reference(3)
    options = {'ki': [15.0, 10.0, 5.0], 'tau_limit': [12.0, 9.0, 2.0],
               'gravity_compensation': 'desired'}
    fast = ArmSimulator(ARM, KP, KD, reference, 5e-4, **options)
    plain = ArmSimulator(ARM, KP, KD, reference, 5e-4, compiled=False, **options)
    states, torques = [], []
    for k in range(1, 101):
        fast.advance(0.01 * k)
        plain.advance(0.01 * k)
        np.testing.assert_allclose(fast.x, plain.x, rtol=0, atol=1e-11)
        theta, _, tau, _, _ = fast.sample()
        states.append(theta)
        torques.append(tau)
    servo = Servo(KP, KD, ki=options['ki'], tau_limit=options['tau_limit'],
                  gravity='desired', arm=ARM)
    truth = simulate(ARM, servo, reference, duration=1.0, rate=100.0)
    assert np.max(np.abs(np.array(states) - truth.theta[1:])) < 1e-5
    np.testing.assert_allclose(torques, truth.tau[1:], atol=1e-3)
    assert fast.x.shape == (9,) and np.any(fast.x[6:] != 0.0)      # the integral moved


def test_digital_pid_matches_simulate():
    reference = paper_reference(3)
    sim = ArmSimulator(ARM, KP, KD, reference, 5e-4, control_rate=500.0, ki=[20.0] * 3,
                       gravity_compensation='measured')
    servo = Servo(KP, KD, ki=[20.0] * 3, gravity='measured', arm=ARM)
    truth = simulate(ARM, servo, reference, duration=0.5, rate=100.0, control_rate=500.0)
    for k in range(1, 51):
        sim.advance(0.01 * k)
        theta, _, tau, _, _ = sim.sample()
        assert np.max(np.abs(theta - truth.theta[k])) < 1e-5
        np.testing.assert_allclose(tau, truth.tau[k], atol=1e-3)


def test_a_driver_without_velocity_or_effort_publishes_empty_fields(ros):
    context, executor = ros
    node, probe, states, origin = record(
        context, executor, 101, gravity_compensation='measured', ki=[10.0],
        **{'sensors.velocity': 'none', 'sensors.effort': False})
    try:
        for m in states:
            assert len(m.position) == 3 and len(m.velocity) == 0 and len(m.effort) == 0
        # the published positions are the arm under PID + gravity compensation
        first = states[0]
        t0 = (stamp_ns(first) - origin) / 1e9
        assert t0 == 0.0                           # sample 0 starts the run on the reference
        servo = Servo(KP, KD, ki=[10.0] * 3, gravity='measured', arm=ARM)
        truth = simulate(ARM, servo, paper_reference(3), duration=1.0, rate=100.0)
        published = np.array([m.position for m in states])
        assert np.max(np.abs(published - truth.theta)) < 1e-4
    finally:
        retire_node(executor, node)
        retire_node(executor, probe)


def test_differenced_velocity_is_published_and_theta_dot_noise_is_refused(ros):
    context, executor = ros
    node, probe, states, _ = record(context, executor, 50,
                                    **{'sensors.velocity': 'difference',
                                       'noise.theta_std': 1e-4})
    try:
        position = np.array([m.position for m in states])
        velocity = np.array([m.velocity for m in states])
        np.testing.assert_allclose(velocity[1:], np.diff(position, axis=0) / 0.01,
                                   rtol=1e-9, atol=1e-9)
        client = probe.create_client(SetParameters, '/sim_arm/set_parameters')
        assert client.wait_for_service(timeout_sec=5.0)
        request = SetParameters.Request(parameters=[
            Parameter('noise.theta_dot_std', value=0.01).to_parameter_msg()])
        future = client.call_async(request)
        assert wait_for(future.done, 5.0), 'timed out waiting for set_parameters'
        result = future.result().results[0]
        assert not result.successful and 'sensors.velocity' in result.reason
        probe.destroy_client(client)
    finally:
        retire_node(executor, node)
        retire_node(executor, probe)


@pytest.mark.parametrize('overrides, name', [
    ({'gravity_compensation': 'sometimes'}, 'gravity_compensation'),
    ({'ki': [1.0, 2.0]}, 'ki'),
    ({'ki': [1.0, -2.0, 0.0]}, 'ki'),
    ({'tau_limit': [5.0, 5.0]}, 'tau_limit'),
    ({'sensors.velocity': 'tacho'}, 'sensors.velocity'),
    ({'sensors.velocity': 'filtered', 'noise.theta_dot_std': 0.01}, 'noise.theta_dot_std'),
    ({'windup_time': 0.0}, 'windup_time'),               # below its range
])
def test_invalid_servo_or_sensor_settings_are_refused_naming_them(ros, overrides, name):
    context, _ = ros
    parameters = [Parameter(key, value=value) for key, value in overrides.items()]
    with pytest.raises(ConfigurationError, match=re.escape(name)):
        SimArm(context=context, parameter_overrides=parameters)

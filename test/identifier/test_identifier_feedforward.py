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
The identifier's feed-forward through its topics and parameters, with sim_arm applying it.

``sim_arm`` (the paper's arm) and ``identifier`` (case 1, ``feedforward.forward_topic``
pointing at sim_arm's input) run in-process on a private context, in a namespace of their
own. The search is paused (``~/pause``): the feed-forward does not depend on it. What the
test sees is what a user sees: ``~/feedforward``, the feed-forward's status in
``/diagnostics``, what sim_arm applies (``joint_states`` effort minus the PD torque of
``joint_commands``), parameters set through ``~/set_parameters``.
"""

import os
import random

from diagnostic_msgs.msg import DiagnosticArray
import numpy as np
import pytest
from rcl_interfaces.srv import SetParameters
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rkgnn_ros.identifier import IdentifierNode
from rkgnn_ros.sim_arm import SimArm
from ros_helpers import retire_node, spinning_context, stamp_ns, wait_for
from sensor_msgs.msg import JointState
from std_srvs.srv import SetBool
from trajectory_msgs.msg import JointTrajectory

pytestmark = pytest.mark.ros

DOMAIN_ID = int(os.environ.get('ROS_DOMAIN_ID') or random.SystemRandom().randint(150, 199))
NS = f'/fftest{os.getpid()}_{random.randint(0, 9999)}'
KP = np.array([32.84, 42.05, 42.31])
KD = np.array([42.44, 0.19, 4.86])
CLIP = np.array([30.0, 20.0, 5.0])
PATIENCE = 90.0  # s: a condition's longest wait on a loaded machine


class Probe:
    """Records what the nodes publish and calls their services."""

    def __init__(self, context, executor):
        self.node = Node(f'ff_probe_{random.getrandbits(32):08x}', context=context)
        self.feedforward, self.status, self.states, self.commands = [], [], {}, {}
        qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        self.node.create_subscription(JointTrajectory, f'{NS}/identifier/feedforward',
                                      self.feedforward.append, qos)
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._diagnostics, 100)
        self.node.create_subscription(JointState, f'{NS}/joint_states',
                                      lambda m: self.states.__setitem__(stamp_ns(m), m), qos)
        self.node.create_subscription(JointState, f'{NS}/joint_commands',
                                      lambda m: self.commands.__setitem__(stamp_ns(m), m), qos)
        self.set_client = self.node.create_client(SetParameters,
                                                  f'{NS}/identifier/set_parameters')
        self.pause_client = self.node.create_client(SetBool, f'{NS}/identifier/pause')
        executor.add_node(self.node)

    def _diagnostics(self, msg):
        for status in msg.status:
            if status.name == 'identifier: feedforward' and status.hardware_id.startswith(NS):
                self.status.append(status.message)

    def call(self, client, request):
        assert client.wait_for_service(timeout_sec=PATIENCE)
        future = client.call_async(request)
        assert wait_for(future.done, PATIENCE)
        return future.result()

    def set_parameters(self, **values):
        result = self.call(self.set_client, SetParameters.Request(parameters=[
            Parameter(name.replace('__', '.'), value=value).to_parameter_msg()
            for name, value in values.items()]))
        assert all(r.successful for r in result.results), result

    def with_points(self, since=0):
        return [m for m in self.feedforward[since:] if m.points]

    def applied(self):
        """Return the feed-forward sim_arm applied at its newest state with a command."""
        stamps = [s for s in list(self.states) if s in self.commands]
        if not stamps:
            return None
        state, command = self.states[max(stamps)], self.commands[max(stamps)]
        pd = KP * (np.array(command.position) - state.position) + \
            KD * (np.array(command.velocity) - state.velocity)
        return np.array(state.effort) - pd


@pytest.fixture(scope='module')
def rig():
    """Yield the probe with sim_arm and the identifier running (search paused)."""
    with spinning_context(DOMAIN_ID) as (context, executor):
        probe = Probe(context, executor)
        arm = SimArm(context=context, namespace=NS)
        identifier = IdentifierNode(context=context, namespace=NS, parameter_overrides=[
            Parameter(name, value=value) for name, value in {
                'case': 'torque', 'window': 8.0, 'min_window': 2.0,
                'validation_fraction': 0.25, 'feedforward.enabled': True,
                'feedforward.max_effort': CLIP.tolist(),
                'feedforward.forward_topic': f'{NS}/sim_arm/feedforward'}.items()])
        executor.add_node(arm)
        executor.add_node(identifier)
        try:
            assert probe.call(probe.pause_client, SetBool.Request(data=True)).success
            yield probe
        finally:
            identifier.stop()
            retire_node(executor, identifier)
            retire_node(executor, arm)
            retire_node(executor, probe.node)


def test_the_feedforward_is_the_plans_torque_within_the_clip_and_is_applied(rig):
    probe = rig
    assert wait_for(lambda: len(probe.with_points()) >= 3, PATIENCE), probe.status[-3:]
    assert 'on' in probe.status
    for msg in probe.with_points():
        effort = np.array([p.effort for p in msg.points])
        assert effort.shape == (len(msg.points), 3) and np.all(np.isfinite(effort))
        assert np.all(np.abs(effort) <= CLIP)
        assert all(len(p.positions) == len(p.velocities) == len(p.accelerations) == 3
                   for p in msg.points)
    # sim_arm adds it: the torque it applies beyond its PD is not zero any more
    assert wait_for(lambda: probe.applied() is not None
                    and np.max(np.abs(probe.applied())) > 0.5, PATIENCE)


def test_the_clip_holds(rig):
    probe = rig
    clip = np.array([2.0, 1.0, 0.2])  # below the gravity torques: every point is clipped
    count = len(probe.feedforward)
    probe.set_parameters(feedforward__max_effort=clip.tolist())
    assert wait_for(lambda: len(probe.with_points(count)) >= 3, PATIENCE), probe.status[-3:]
    late = probe.with_points(count)[2:]
    efforts = np.array([p.effort for m in late for p in m.points])
    assert np.all(np.abs(efforts) <= clip)
    assert np.any(np.isclose(np.abs(efforts), clip))  # the clip was reached
    probe.set_parameters(feedforward__max_effort=CLIP.tolist())


def test_a_model_that_fails_the_gate_never_publishes(rig):
    probe = rig
    probe.set_parameters(feedforward__enabled=False)
    assert wait_for(lambda: probe.status and 'enabled is false' in probe.status[-1], PATIENCE)
    count = len(probe.feedforward)
    probe.set_parameters(feedforward__max_error=1e-6, feedforward__enabled=True)
    # two verdicts (5 s apart, each with its own figure) that the model fails, and
    # nothing sent meanwhile
    assert wait_for(lambda: len({s for s in probe.status if 'exceeds max_error' in s}) >= 2,
                    PATIENCE), probe.status[-3:]
    assert not probe.with_points(count)
    probe.set_parameters(feedforward__max_error=0.05)
    assert wait_for(lambda: probe.with_points(count), PATIENCE), probe.status[-3:]


def test_switching_off_stops_the_servos_feedforward_at_once(rig):
    probe = rig
    assert wait_for(lambda: probe.applied() is not None
                    and np.max(np.abs(probe.applied())) > 0.5, PATIENCE)
    count = len(probe.feedforward)
    probe.set_parameters(feedforward__enabled=False)
    assert wait_for(lambda: any(not m.points for m in probe.feedforward[count:]), PATIENCE)
    # the thread may send with points until it reads the new setting; then one empty message
    off = next(i for i in range(count, len(probe.feedforward))
               if not probe.feedforward[i].points)
    assert wait_for(lambda: np.allclose(probe.applied(), 0.0, atol=1e-9), PATIENCE)
    assert not probe.with_points(off)  # nothing with points after the switch-off message


def test_case_three_says_why_not(rig):
    probe = rig
    probe.set_parameters(feedforward__enabled=True, case='unknown')
    assert wait_for(lambda: probe.status and 'not identifiable' in probe.status[-1], PATIENCE)

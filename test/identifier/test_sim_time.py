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

"""The identifier's time rules on the node clock: a recording replayed under use_sim_time."""

import os
import random
import threading

from bag_helpers import simulated_run, T0, write_run
from diagnostic_msgs.msg import DiagnosticArray
import pytest
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rkgnn_ros.core.fitting.identify import RKGNNModel
from rkgnn_ros.identification.clock import NodeSeconds
from rkgnn_ros.identifier import IdentifierNode
from rkgnn_ros.recordings.player import RecordingPlayer
from ros_helpers import retire_node, Rosout, spinning_context, wait_for
from std_msgs.msg import String

pytest.importorskip('rosbags')

DOMAIN_ID = int(os.environ.get('ROS_DOMAIN_ID') or random.SystemRandom().randint(150, 199))
PATIENCE = 120.0


def test_node_seconds_follow_the_clock_pause_and_continue_after_a_jump_back():
    now = [0]
    seconds = NodeSeconds(lambda: now[0])
    assert seconds() == 0.0                 # no /clock yet
    now[0] = 1_700_000_000_000_000_000      # the first /clock: the origin
    assert seconds() == 0.0
    now[0] += 2_500_000_000
    assert seconds() == pytest.approx(2.5)
    assert seconds() == pytest.approx(2.5)  # paused: no time passes
    now[0] -= 30_000_000_000                # a recording played in a loop starts over
    assert seconds() == pytest.approx(2.5)
    now[0] += 1_000_000_000
    assert seconds() == pytest.approx(3.5)


def test_a_recording_replayed_at_twice_its_speed_under_sim_time_gives_a_model(tmp_path):
    bag = tmp_path / 'arm'
    write_run(bag, simulated_run(20.0))
    with spinning_context(DOMAIN_ID) as (context, executor):
        identifier = IdentifierNode(context=context, parameter_overrides=[
            Parameter('use_sim_time', value=True), Parameter('min_window', value=3.0),
            Parameter('window', value=10.0), Parameter('model_publish_period', value=1.0)])
        executor.add_node(identifier)
        probe = Node(f'probe_{random.getrandbits(32):08x}', context=context)
        models, stamps = [], []
        probe.create_subscription(String, 'identifier/model', models.append, QoSProfile(
            depth=1, reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL))
        probe.create_subscription(
            DiagnosticArray, '/diagnostics',
            lambda m: stamps.append(m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec), 10)
        executor.add_node(probe)
        player_node = Node(f'player_{random.getrandbits(32):08x}', context=context)
        player = RecordingPlayer(player_node, str(bag), rate=2.0)
        stop = threading.Event()
        thread = threading.Thread(target=player.play, args=(stop,), daemon=True)
        try:
            thread.start()
            assert wait_for(lambda: models, PATIENCE), 'no model from the replayed recording'
            model = RKGNNModel.from_yaml(models[-1].data)
            assert model.joint_names == ('joint1', 'joint2', 'joint3')
            # the node's clock is the recording's: its diagnostics are stamped in it
            assert wait_for(lambda: stamps, PATIENCE)
            assert T0 <= stamps[-1] <= T0 + 25.0
        finally:
            stop.set()
            thread.join(10.0)
            identifier.stop()
            for node in (identifier, probe, player_node):
                retire_node(executor, node)


def test_a_pause_of_the_recording_shorter_than_stale_timeout_is_not_stale_when_slowed(tmp_path):
    # 0.8 s without joint_states in the recording, played at half speed: 1.6 s of wall
    # time, over stale_timeout (1 s) by the wall, under it by the node's clock
    bag = tmp_path / 'paused'
    write_run(bag, simulated_run(10.0), skip=lambda t: 7.0 < t < 7.8)
    with spinning_context(DOMAIN_ID) as (context, executor):
        identifier = IdentifierNode('identifier_paused', context=context, parameter_overrides=[
            Parameter('use_sim_time', value=True), Parameter('min_window', value=3.0),
            Parameter('window', value=10.0), Parameter('stale_timeout', value=1.0)])
        executor.add_node(identifier)
        probe = Node(f'probe_{random.getrandbits(32):08x}', context=context)
        rosout = Rosout(probe)
        executor.add_node(probe)
        player_node = Node(f'player_{random.getrandbits(32):08x}', context=context)
        player = RecordingPlayer(player_node, str(bag), rate=0.5,
                                 topics=['/joint_states', '/joint_commands'])
        stop = threading.Event()
        try:
            player.play(stop)  # 10 s of the recording: 20 s
            assert wait_for(lambda: rosout.lines('identifier_paused', 'search started'),
                            PATIENCE), 'the search never started'
            assert not rosout.lines('identifier_paused', 'no data for', level='warning')
        finally:
            stop.set()
            identifier.stop()
            for node in (identifier, probe, player_node):
                retire_node(executor, node)

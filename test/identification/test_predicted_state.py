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

"""~/predicted_state: the prediction's state a fixed look-ahead on, stamped at that time."""

import os
import random
import threading
import time

from bag_helpers import simulated_run, write_run
import numpy as np
import pytest
import rclpy
from rclpy.node import Node
from rclpy.parameter import Parameter
from rkgnn_ros.identifier import ConfigurationError, IdentifierNode
from rkgnn_ros.identify_bag import main as identify_bag
from rkgnn_ros.wire.conversions import make_joint_state
from ros_helpers import retire_node, spinning_context, stamp_ns, wait_for
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory

DOMAIN_ID = int(os.environ.get('ROS_DOMAIN_ID') or random.SystemRandom().randint(150, 199))
JOINTS = ['joint1', 'joint2', 'joint3']
LOOKAHEAD = 0.5
PATIENCE = 60.0


@pytest.fixture(scope='module')
def model_file(tmp_path_factory):
    """Return a model of the paper's arm (identify_bag, a few generations)."""
    folder = tmp_path_factory.mktemp('model')
    write_run(folder / 'bag', simulated_run(20.0))
    assert identify_bag([str(folder / 'bag'), '--out', str(folder / 'out'), '--heldout', '0',
                         '--max-generations', '2', '--quiet']) == 0
    return folder / 'out' / 'model.yaml'


def test_predicted_state_is_the_prediction_lookahead_on_stamped_then(model_file):
    data = simulated_run(20.0)
    with spinning_context(DOMAIN_ID) as (context, executor):
        node = IdentifierNode('identifier_view', context=context, parameter_overrides=[
            Parameter('model_file', value=str(model_file)),
            Parameter('prediction.lookahead', value=LOOKAHEAD),
            Parameter('prediction.rate', value=10.0), Parameter('es.max_generations', value=1),
            # the feed has joint_commands but no plan: predict past it as the arm holding them
            Parameter('prediction.beyond_plan', value='hold')])
        probe = Node(f'probe_{random.getrandbits(32):08x}', context=context)
        predictions, states = {}, []
        probe.create_subscription(JointTrajectory, 'identifier_view/prediction',
                                  lambda m: predictions.__setitem__(stamp_ns(m), m), 100)
        probe.create_subscription(JointState, 'identifier_view/predicted_state', states.append,
                                  100)
        state_pub = probe.create_publisher(JointState, 'joint_states', 100)
        command_pub = probe.create_publisher(JointState, 'joint_commands', 100)
        executor.add_node(node)
        executor.add_node(probe)
        stop = threading.Event()

        def stream():  # the run again and again, stamps going on, until the test is done
            t0 = time.time()
            for step in range(10 ** 6):
                if stop.is_set():
                    return
                k = step % data.t.size
                stamp = t0 + 0.01 * step
                time.sleep(max(0.0, stamp - time.time()))
                state_pub.publish(make_joint_state(stamp, JOINTS, data.theta[k],
                                                   data.theta_dot[k], data.tau[k]))
                command_pub.publish(make_joint_state(stamp, JOINTS, data.theta_d[k],
                                                     data.theta_d_dot[k], None))

        thread = threading.Thread(target=stream, daemon=True)
        thread.start()
        try:
            def pairs():
                return [(s, predictions[stamp_ns(s) - int(LOOKAHEAD * 1e9)]) for s in
                        list(states) if stamp_ns(s) - int(LOOKAHEAD * 1e9) in predictions]
            assert wait_for(lambda: len(pairs()) >= 5, PATIENCE), \
                f'{len(states)} predicted states, {len(predictions)} predictions'
            for state, prediction in pairs():
                assert list(state.name) == JOINTS
                assert state.header.frame_id == prediction.header.frame_id  # model or baseline
                offsets = np.array([p.time_from_start.sec + 1e-9 * p.time_from_start.nanosec
                                    for p in prediction.points])
                positions = np.array([p.positions for p in prediction.points])
                expected = [np.interp(LOOKAHEAD, offsets, positions[:, j]) for j in range(3)]
                np.testing.assert_allclose(state.position, expected, atol=1e-12)
                assert all(np.isnan(state.effort))
        finally:
            stop.set()
            thread.join(10.0)
            node.stop()
            retire_node(executor, node)
            retire_node(executor, probe)


def test_a_lookahead_beyond_the_horizon_is_refused():
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=DOMAIN_ID)
    try:
        with pytest.raises(ConfigurationError, match=r'prediction.lookahead \(3.0\) must be <='):
            IdentifierNode('identifier_far', context=context, parameter_overrides=[
                Parameter('prediction.lookahead', value=3.0)])
    finally:
        rclpy.try_shutdown(context=context)

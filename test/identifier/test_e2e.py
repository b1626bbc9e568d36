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
End to end: the installed executables, started as processes the way a user starts them.

``ros2 run rkgnn_ros <exe>`` finds the package in the ament index and runs
``<prefix>/lib/rkgnn_ros/<exe>``; these tests look the executables up the same way, start
``sim_arm`` and ``identifier`` on a private ROS domain and check, over the real middleware,
that predictions arrive and start from the measured state, and that the pair shuts down
cleanly on SIGINT. Needs ``colcon build`` first (``make test`` does it).
"""

import os
import random
import signal
import subprocess
import time

from ament_index_python.packages import get_package_prefix, get_package_share_directory
import numpy as np
import pytest

pytestmark = pytest.mark.ros

EXECUTABLES = ('sim_arm', 'identifier')


def _installed(name):
    return os.path.join(get_package_prefix('rkgnn_ros'), 'lib', 'rkgnn_ros', name)


def test_package_is_in_the_ament_index_with_its_executables_and_config():
    from ament_index_python.packages import get_packages_with_prefixes
    assert 'rkgnn_ros' in get_packages_with_prefixes()
    for name in EXECUTABLES:
        path = _installed(name)
        assert os.path.isfile(path) and os.access(path, os.X_OK), path
    share = get_package_share_directory('rkgnn_ros')
    for name in ('config/sim_arm.yaml', 'config/identifier.yaml', 'package.xml',
                 'launch/identify_sim.launch.py'):
        assert os.path.exists(os.path.join(share, name)), name


@pytest.fixture
def running_pair(tmp_path):
    domain = random.randint(100, 230)
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED='1')
    share = get_package_share_directory('rkgnn_ros')
    procs = []
    logs = []
    for name, extra in (('sim_arm', []),
                        ('identifier', ['-p', 'min_window:=3.0', '-p', 'prediction.rate:=5.0',
                                        '-p', f"model_file:={tmp_path / 'model.yaml'}"])):
        log = open(tmp_path / f'{name}.log', 'w')
        logs.append(log)
        cmd = [_installed(name), '--ros-args', '--params-file',
               os.path.join(share, 'config', f'{name}.yaml')] + extra
        procs.append(subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT))
    yield domain, procs, tmp_path
    for p in procs:
        if p.poll() is None:
            p.kill()
            p.wait()
    for log in logs:
        log.close()


def test_installed_nodes_predict_from_the_measured_state_and_stop_cleanly(running_pair):
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState
    from std_msgs.msg import String
    from trajectory_msgs.msg import JointTrajectory

    domain, procs, tmp_path = running_pair
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain)
    node = rclpy.create_node('e2e_listener', context=ctx)
    states = {}
    predictions = []

    def stamp_of(msg):
        return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec

    def on_state(msg):
        states[stamp_of(msg)] = (np.array(msg.position), np.array(msg.velocity))

    # reliable and deep (sim_arm publishes reliably): every state must reach the listener,
    # even while a fresh clone compiles its kernels and the machine is busy
    node.create_subscription(JointState, 'joint_states', on_state,
                             QoSProfile(depth=5000, reliability=ReliabilityPolicy.RELIABLE))
    node.create_subscription(JointTrajectory, 'identifier/prediction', predictions.append, 10)
    models = []  # predictions come at once (a baseline until the model earns it); the model
    node.create_subscription(String, 'identifier/model', models.append,  # later
                             QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                                        durability=DurabilityPolicy.TRANSIENT_LOCAL))
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)

    def since_listening():  # discovery matches each publisher on its own: the identifier's
        # predictions may reach the listener before sim_arm's states do, and a prediction
        # from a state published before the listener heard any is not one it can check
        return [m for m in predictions if states and stamp_of(m) >= min(states)]

    def checkable():  # and a reliable writer keeps only its last 10 states: on a machine
        # stalled for 0.1 s the listener can miss one, so its prediction is not checked
        return [m for m in since_listening() if stamp_of(m) in states][:3]

    deadline = time.monotonic() + 240.0  # a fresh clone compiles every kernel first
    try:
        while time.monotonic() < deadline and len(since_listening()) < 3:
            executor.spin_once(timeout_sec=0.1)
            for p in procs:
                assert p.poll() is None, (tmp_path / 'identifier.log').read_text()[-3000:]
        assert len(since_listening()) >= 3, (
            f'no ~/prediction within 240 s after the first state ({len(predictions)} '
            f'predictions, {len(states)} states)')

        def measured():  # the states three start from, and the motion 2 s after the first
            first = checkable()
            return (len(first) == 3 and
                    max(states) >= min(map(stamp_of, first)) + 2_010_000_000)
        deadline = time.monotonic() + 60.0
        while not measured() and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        heard = since_listening()
        assert measured(), (
            'the states of the predictions did not arrive: prediction stamps '
            f'{[stamp_of(m) for m in heard]}, states {min(states)}..{max(states)} '
            f'({len(states)} of them)')
        # every prediction, checked or not, starts on the grid of published stamps
        period = int(np.min(np.diff(sorted(states))))
        assert period == 10_000_000  # config/sim_arm.yaml: publish_rate 100 Hz
        assert all((stamp_of(m) - min(states)) % period == 0 for m in heard)
        predictions = checkable()
        for msg in predictions:
            stamp = stamp_of(msg)
            assert stamp in states, 'a prediction must start from a published state stamp'
            theta, theta_dot = states[stamp]
            first = msg.points[0]
            assert first.time_from_start.sec == 0 and first.time_from_start.nanosec == 0
            np.testing.assert_allclose(first.positions, theta, atol=1e-12)
            np.testing.assert_allclose(first.velocities, theta_dot, atol=1e-12)
            horizon = (msg.points[-1].time_from_start.sec
                       + 1e-9 * msg.points[-1].time_from_start.nanosec)
            assert horizon == pytest.approx(2.0, abs=0.011)
            assert np.all(np.isfinite([v for p in msg.points for v in p.positions]))
        # the error of each prediction against what the arm then actually did
        from rkgnn_ros.core.selfcheck import ahead_errors
        stamps = sorted(states)
        meas_t = 1e-9 * np.array(stamps, dtype=float)
        meas_theta = np.array([states[k][0] for k in stamps])
        t0, err = ahead_errors(
            [m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for m in predictions],
            [[p.time_from_start.sec + 1e-9 * p.time_from_start.nanosec for p in m.points]
             for m in predictions],
            [[list(p.positions) for p in m.points] for m in predictions],
            meas_t, meas_theta, 2.0)
        assert t0.size >= 1, 'no prediction could be scored against the motion that followed'
        assert err.shape == (t0.size, 3) and np.all(np.isfinite(err))
        deadline = time.monotonic() + 240.0
        while not models and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.1)
        assert models, 'no ~/model within 240 s'  # what is saved at shutdown
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
    for p in procs:
        p.send_signal(signal.SIGINT)
    for name, p in zip(EXECUTABLES, procs):
        assert p.wait(timeout=60) == 0, f'{name} did not exit cleanly on SIGINT'
        log = (tmp_path / f'{name}.log').read_text()
        assert 'Traceback' not in log, log[-3000:]
    # the identifier saves its model at shutdown, atomically, in a loadable form
    from rkgnn_ros.core.model.model import RKGNNModel
    model = RKGNNModel.load(tmp_path / 'model.yaml')
    assert model.n_joints == 3

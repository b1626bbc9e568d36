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

"""Recordings written for the tests: a simulated arm's streams in a rosbag2 (rosbags)."""

import numpy as np
from rclpy.serialization import serialize_message
from rkgnn_ros.core.sim.plant import PlanarArm
from rkgnn_ros.core.sim.servo import Servo
from rkgnn_ros.core.sim.simulate import simulate
from rkgnn_ros.core.sim.trajectories import paper_reference
from rkgnn_ros.recordings.reader import RecordingWriter
from rkgnn_ros.wire.conversions import make_joint_state, seconds_to_stamp

#: Where recorded time starts (s): a wall-clock-like stamp.
T0 = 1_700_000_000.0
JOINT_STATE = 'sensor_msgs/msg/JointState'
CONTROLLER_STATE = 'control_msgs/msg/JointTrajectoryControllerState'

#: control_msgs/msg/JointTrajectoryControllerState of Jazzy (the fields read here), for
#: recordings that carry their own definition as ros2 bag record writes it
CONTROLLER_STATE_MSG = """std_msgs/Header header
string[] joint_names
trajectory_msgs/JointTrajectoryPoint reference
trajectory_msgs/JointTrajectoryPoint feedback
trajectory_msgs/JointTrajectoryPoint error
trajectory_msgs/JointTrajectoryPoint output
"""

_RUNS = {}


def simulated_run(duration=30.0):
    """Return the paper's arm under its PD for ``duration`` s at 100 Hz (a Dataset, cached)."""
    if duration not in _RUNS:
        _RUNS[duration] = simulate(PlanarArm.paper(), Servo.paper(), paper_reference(3),
                                   duration, rate=100.0)
    return _RUNS[duration]


def write_run(path, data, storage='mcap', names=('joint1', 'joint2', 'joint3'),
              states='/joint_states', commands='/joint_commands', controller_state='',
              effort=True, skip=None, garbage=0):
    """
    Write ``data`` as joint_states and joint_commands (or controller states) into a bag.

    ``skip(t)`` True leaves a sample out (gaps); ``garbage`` more messages of random bytes
    are written on the states topic, 3 s into the recording.
    """
    rng = np.random.default_rng(0)
    definitions = {CONTROLLER_STATE: CONTROLLER_STATE_MSG} if controller_state else None
    with RecordingWriter(str(path), storage, definitions) as bag:
        types = bag.types()
        for k, t in enumerate(data.t):
            if skip is not None and skip(t):
                continue
            stamp = seconds_to_stamp(T0 + t)
            log_ns = int(round((T0 + t) * 1e9)) + 200_000
            tau = data.tau[k] if effort else None
            state = make_joint_state(stamp, list(names), data.theta[k], data.theta_dot[k], tau)
            if not effort:
                state.effort = []
            bag.write(states, JOINT_STATE, log_ns, serialize_message(state))
            if commands:
                command = make_joint_state(stamp, list(names), data.theta_d[k],
                                           data.theta_d_dot[k], None)
                bag.write(commands, JOINT_STATE, log_ns + 1000, serialize_message(command))
            if controller_state:
                point = types['trajectory_msgs/msg/JointTrajectoryPoint']
                duration = types['builtin_interfaces/msg/Duration'](sec=0, nanosec=0)

                def make_point(positions, velocities, effort_values=()):
                    return point(positions=np.asarray(positions, dtype=float),
                                 velocities=np.asarray(velocities, dtype=float),
                                 accelerations=np.empty(0), effort=np.asarray(
                                     effort_values, dtype=float), time_from_start=duration)

                time_type = types['builtin_interfaces/msg/Time']
                header = types['std_msgs/msg/Header'](
                    stamp=time_type(sec=stamp.sec, nanosec=stamp.nanosec), frame_id='')
                message = types[CONTROLLER_STATE](
                    header=header, joint_names=list(names),
                    reference=make_point(data.theta_d[k], data.theta_d_dot[k]),
                    feedback=make_point(data.theta[k], data.theta_dot[k]),
                    error=make_point(data.theta_d[k] - data.theta[k],
                                     data.theta_d_dot[k] - data.theta_dot[k]),
                    output=make_point([], [], data.tau[k]))
                bag.write(controller_state, CONTROLLER_STATE, log_ns + 2000,
                          bag.serialize(message, CONTROLLER_STATE))
        for i in range(garbage):
            bag.write(states, JOINT_STATE, int((T0 + 3.0) * 1e9) + 10_000 + i,
                      rng.integers(0, 256, 40, dtype=np.uint8).tobytes())

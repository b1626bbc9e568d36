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
A joint_trajectory_controller's state as the identifier's command stream.

ros2_control's joint_trajectory_controller publishes ``~/controller_state``
(control_msgs/msg/JointTrajectoryControllerState): the point it tracks now (``reference``;
``desired`` before Jazzy), what it measured (``feedback``), and what it sent to the
hardware (``output``; efforts when it commands an effort interface). θd and θ̇d are the
reference's positions and velocities, which is exactly what ``joint_commands`` carries,
so :func:`controller_state_to_joint_state` rewrites one message as a JointState with
``position`` θd, ``velocity`` θ̇d and ``effort`` the commanded effort (NaN where there is
none), stamped as the state; the node's command path then applies every drop rule to it.

Read by attribute, so it takes the rclpy message where ``control_msgs`` is installed and
the message a recording's own definitions decode (``rosbags``) alike. A message it cannot
use is a :class:`~rkgnn_ros.wire.conversions.Rejection` with the reason.
"""

import math
from typing import Union

from rkgnn_ros.wire.conversions import Rejection
from sensor_msgs.msg import JointState

__all__ = ['controller_state_to_joint_state', 'CONTROL_MSGS_REASON', 'control_msgs_available']

#: Why the live input is off where control_msgs cannot be imported.
CONTROL_MSGS_REASON = ('control_msgs is not importable (it comes with a ROS 2 install: '
                       'apt install ros-jazzy-control-msgs)')


def control_msgs_available() -> bool:
    """Return whether control_msgs' JointTrajectoryControllerState can be imported."""
    try:
        from control_msgs.msg import JointTrajectoryControllerState  # noqa: F401
    except ImportError:
        return False
    return True


def _point(msg, *names):
    """Return the first of the message's JointTrajectoryPoint fields with positions."""
    for name in names:
        point = getattr(msg, name, None)
        if point is not None and len(getattr(point, 'positions', ())) > 0:
            return point
    return None


def controller_state_to_joint_state(msg) -> Union[JointState, Rejection]:
    """
    Return the controller state as a JointState command (θd, θ̇d, commanded effort).

    Rejections: 'malformed' (no header, names or reference point), 'size_mismatch' (the
    reference's arrays do not match ``joint_names``), 'missing_velocity' (a reference
    without velocities).
    """
    try:
        header = msg.header
        names = [str(name) for name in msg.joint_names]
        point = _point(msg, 'reference', 'desired')
    except AttributeError as error:
        return Rejection('malformed', f'not a JointTrajectoryControllerState: {error}')
    if not names or point is None:
        return Rejection('malformed', 'controller state without joint names or a reference '
                                      'point with positions')
    positions = [float(v) for v in point.positions]
    velocities = [float(v) for v in getattr(point, 'velocities', ())]
    if len(positions) != len(names):
        return Rejection('size_mismatch', f'reference has {len(positions)} positions for '
                                          f'{len(names)} joint_names')
    if not velocities:
        return Rejection('missing_velocity', 'reference point without velocities')
    if len(velocities) != len(names):
        return Rejection('size_mismatch', f'reference has {len(velocities)} velocities for '
                                          f'{len(names)} joint_names')
    output = getattr(msg, 'output', None)
    effort = [float(v) for v in getattr(output, 'effort', ())] if output is not None else []
    if len(effort) != len(names):
        effort = [math.nan] * len(names)
    state = JointState()
    state.header.stamp.sec = int(header.stamp.sec)
    state.header.stamp.nanosec = int(header.stamp.nanosec)
    state.header.frame_id = str(getattr(header, 'frame_id', ''))
    state.name = names
    state.position = positions
    state.velocity = velocities
    state.effort = effort
    return state

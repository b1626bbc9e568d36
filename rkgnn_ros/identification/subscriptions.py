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
The identifier's subscriptions: which streams it takes, with what QoS, and who reads them.

- ``joint_states`` and ``joint_commands`` (the 1 kHz-capable streams): raw CDR, best effort,
  depth 100 (matches best-effort and reliable publishers alike), in a
  :class:`~rkgnn_ros.identification.ingest.PolledGroup`: the executor never takes them,
  the ingest thread does (:meth:`~rkgnn_ros.identification.ingest.Ingestion.start`).
- ``reference_trajectory``: raw (a plan's size budget is checked on its bytes, before its
  points become objects), depth 1 (only the newest plan is used, and the middleware keeps
  a buffer as large as the largest message per history slot), taken in the executor.
- the ``controller_state`` parameter's topic
  (:func:`~rkgnn_ros.identification.ros2_control.subscribe_controller_state`).

No QoS-event handlers are created (:func:`quiet_events`): rclpy adds each one to the wait
set of every spin. Our subscriptions are best effort and our publishers volatile or
transient-local reliable, so the incompatible-QoS events they would log cannot arise with
usual peers.
"""

from typing import Callable, Tuple

from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rkgnn_ros.identification.ingest import PolledGroup
from rkgnn_ros.identification.ros2_control import subscribe_controller_state
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from trajectory_msgs.msg import JointTrajectory

__all__ = ['DESCRIPTION_QOS', 'quiet_events', 'subscribe_description', 'subscribe_streams',
           'STREAM_QOS', 'REFERENCE_QOS']

STREAM_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                        reliability=ReliabilityPolicy.BEST_EFFORT,
                        durability=DurabilityPolicy.VOLATILE)
REFERENCE_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                           reliability=ReliabilityPolicy.BEST_EFFORT,
                           durability=DurabilityPolicy.VOLATILE)
#: robot_state_publisher's: a late subscriber gets the last description at once
DESCRIPTION_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                             reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)


def quiet_events() -> Tuple[PublisherEventCallbacks, SubscriptionEventCallbacks]:
    """Return publisher and subscription event callbacks that create no QoS-event handler."""
    return (PublisherEventCallbacks(use_default_callbacks=False),
            SubscriptionEventCallbacks(use_default_callbacks=False))


def subscribe_streams(node, ingestion, on_reference: Callable[[bytes], None],
                      controller_state: str) -> Tuple[object, object]:
    """
    Create the identifier's subscriptions; return the polled ``(state, command)`` pair.

    ``on_reference`` takes a plan's raw bytes (in the executor); ``controller_state`` is the
    topic of a joint_trajectory_controller's state ('' for none).
    """
    _, events = quiet_events()
    polled = PolledGroup()
    state_sub = node.create_subscription(
        JointState, 'joint_states', lambda raw: None, STREAM_QOS, callback_group=polled,
        event_callbacks=events, raw=True)
    command_sub = node.create_subscription(
        JointState, 'joint_commands', lambda raw: None, STREAM_QOS, callback_group=polled,
        event_callbacks=events, raw=True)
    node.create_subscription(JointTrajectory, 'reference_trajectory', on_reference,
                             REFERENCE_QOS, event_callbacks=events, raw=True)
    subscribe_controller_state(node, controller_state, ingestion, STREAM_QOS)
    return state_sub, command_sub


def subscribe_description(node, on_description: Callable[[bytes], None]) -> object:
    """Subscribe to ``robot_description`` (raw std_msgs/String, taken in the executor)."""
    _, events = quiet_events()
    return node.create_subscription(String, 'robot_description', on_description,
                                    DESCRIPTION_QOS, event_callbacks=events, raw=True)

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
ros2_control's forms of the identifier's inputs: controller gains and controller state.

A joint_trajectory_controller is configured with ``joints`` and per-joint gains
``gains.<joint>.p`` / ``.d`` (``.i`` ...), and publishes ``~/controller_state``. The
identifier takes both as they are:

- :func:`declare_controller_gains`: with ``joints`` set, ``gains.<joint>.p`` and
  ``gains.<joint>.d`` are declared (read-only) and, where given, are case 2's ``kp`` and
  ``kd`` (a missing ``d`` is 0, as the controller takes it); given together with ``kp`` /
  ``kd`` they must agree. The parameters file of the controller can thus be passed to the
  identifier as well.
- :func:`subscribe_controller_state`: with the ``controller_state`` parameter set to the
  controller's topic, θd, θ̇d (and the commanded effort) come from its
  JointTrajectoryControllerState (:mod:`rkgnn_ros.wire.controller_state`) into the command
  stream, under every rule ``joint_commands`` is under. The subscription is raw: a message
  over :data:`MAX_CONTROLLER_STATE_BYTES` is dropped as ``over_budget`` before it is
  decoded. It needs ``control_msgs``; without it the input stays off with one warning
  saying why.
"""

import math
from typing import Callable, Mapping, Optional

from rcl_interfaces.msg import ParameterDescriptor
from rclpy.serialization import deserialize_message, serialize_message
from rkgnn_ros.wire.cdr import encapsulation_problem
from rkgnn_ros.wire.controller_state import (control_msgs_available, CONTROL_MSGS_REASON,
                                             controller_state_to_joint_state)
from rkgnn_ros.wire.conversions import MAX_STATE_BYTES, Rejection

__all__ = ['MAX_CONTROLLER_STATE_BYTES', 'controller_gains', 'declare_controller_gains',
           'subscribe_controller_state']

#: Largest controller state taken (bytes): its four trajectory points (reference, feedback,
#: error, output) and names are about four JointStates of the same joints.
MAX_CONTROLLER_STATE_BYTES = 4 * MAX_STATE_BYTES


def declare_controller_gains(node, values: Mapping, error: Callable[[str], Exception]) -> dict:
    """
    Declare ``gains.<joint>.p`` / ``.d`` for the configured joints; return values with kp, kd.

    See :func:`controller_gains` for the rules and errors.
    """
    given = {}
    for joint in values.get('joints') or ():
        for term in ('p', 'd'):
            name = f'gains.{joint}.{term}'
            descriptor = ParameterDescriptor(
                description=f"ros2_control form of case 2's {'kp' if term == 'p' else 'kd'} "
                            f'for {joint} (as a joint_trajectory_controller takes it)',
                read_only=True)
            given[name] = node.declare_parameter(name, math.nan, descriptor).value
    return controller_gains(values, given, error)


def controller_gains(values: Mapping, given: Mapping, error: Callable[[str], Exception]) -> dict:
    """
    Return ``values`` with ``kp``, ``kd`` taken from ``given`` ``gains.<joint>.p`` / ``.d``.

    Only the configured ``joints`` are read (none without them). Raises ``error(reason)``
    if some joints have a ``p`` and others not, a gain is negative or not a number, a gain
    names a joint that is not configured, or the gains disagree with ``kp`` / ``kd`` lists.
    """
    values = dict(values)
    joints = list(values.get('joints') or ())
    known = {f'gains.{j}.{t}' for j in joints for t in ('p', 'd')}
    other = sorted(name for name in given if name not in known and name.endswith(('.p', '.d')))
    if other:
        raise error(f'{", ".join(other)}: not a configured joint (joints {joints}); the '
                    'gains form needs the joints parameter')
    try:
        gains = {name: float(given.get(name, math.nan)) for name in known}
    except (TypeError, ValueError):
        raise error(f'gains.<joint>.p and .d must be numbers, got {dict(given)}') from None
    given_p = [j for j in joints if math.isfinite(gains[f'gains.{j}.p'])]
    if not given_p:
        return values
    if len(given_p) != len(joints):
        missing = [f'gains.{j}.p' for j in joints if j not in given_p]
        raise error(f'{", ".join(missing)} missing: give the p gain of every joint')
    kp = tuple(gains[f'gains.{j}.p'] for j in joints)
    kd = tuple(gains[f'gains.{j}.d'] if math.isfinite(gains[f'gains.{j}.d']) else 0.0
               for j in joints)
    if any(v < 0.0 for v in kp + kd):
        raise error(f'gains.<joint>.p and .d must be >= 0, got p {list(kp)}, d {list(kd)}')
    for name, listed, taken in (('kp', values.get('kp'), kp), ('kd', values.get('kd'), kd)):
        if listed and tuple(float(v) for v in listed) != taken:
            raise error(f'{name} {list(listed)} disagrees with gains.<joint>.'
                        f'{"p" if name == "kp" else "d"} {list(taken)}: give one form')
    values['kp'], values['kd'] = kp, kd
    return values


def subscribe_controller_state(node, topic: str, ingestion, qos) -> Optional[object]:
    """
    Subscribe to a controller's state as the command stream; return the subscription.

    Returns None (and logs why once) when ``topic`` is empty or control_msgs is missing.
    """
    if not topic:
        return None
    if not control_msgs_available():
        node.get_logger().warning(f'controller_state {topic!r} is not read: '
                                  f'{CONTROL_MSGS_REASON}')
        return None
    from control_msgs.msg import JointTrajectoryControllerState

    def on_state(raw: bytes) -> None:
        try:
            if len(raw) > MAX_CONTROLLER_STATE_BYTES:
                ingestion.drops.reject(topic, 'command', 'over_budget',
                                       f'a controller state of {len(raw)} bytes is over the '
                                       f'budget of {MAX_CONTROLLER_STATE_BYTES}')
                return
            problem = encapsulation_problem(raw, 'JointTrajectoryControllerState')
            if problem is not None:  # rclpy would print a line on stderr for each
                ingestion.drops.reject(topic, 'command', 'malformed', problem)
                return
            msg = deserialize_message(raw, JointTrajectoryControllerState)
            command = controller_state_to_joint_state(msg)
            if isinstance(command, Rejection):
                ingestion.drops.reject(topic, 'command', command.reason, command.message)
                return
            ingestion.handle_command(serialize_message(command))
        except Exception:  # noqa: B902 - bad input is counted, never raised
            ingestion.drops.internal_error(topic)

    return node.create_subscription(JointTrajectoryControllerState, topic, on_state, qos,
                                    raw=True)

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
Which arm ``sim_arm`` simulates: the paper's planar arm, or a URDF arm.

With an empty ``robot_description`` (the default) ``sim_arm`` simulates the planar arm of
its ``masses``, ``lengths``, ... parameters. Given a URDF (its XML, a file path, or
``example-robot-data:<path under robots/>``), it simulates that arm instead
(:class:`~rkgnn_ros.core.sim.urdf_arm.UrdfArm`): the joints of ``urdf.joints`` move (all
revolute joints by default), every other movable joint is locked (at
``urdf.locked_positions``, else 0 clipped into its limits), the references swing about
``urdf.home`` (default the middle of each joint's limits) and the node publishes the
reduced URDF on ``robot_description``. ``gravity``, ``viscous``, ``coulomb``,
``coulomb_velocity`` and the servo's gains apply to both; ``joint_names``, ``masses``,
``lengths`` and ``mass_model`` describe the planar arm only.

This module holds those parameter rows and turns their values into the plant, so the node
only chooses between the two.
"""

from functools import partial
from typing import NamedTuple, Optional, Tuple

import numpy as np
from rclpy.parameter import Parameter
from rkgnn_ros.core.sim.urdf_arm import UrdfArm, UrdfError
from rkgnn_ros.node.parameters import Change, ParameterSpec

__all__ = ['URDF_PARAMETERS', 'UrdfChoice', 'build_urdf_arm', 'reference_limit_warning']

_Spec = partial(ParameterSpec, change=Change.START)

#: The parameters of a URDF arm (read-only), appended to sim_arm's table.
URDF_PARAMETERS = (
    _Spec('robot_description', '',
          "The arm's URDF: its XML, a file path, or example-robot-data:<path under robots/> "
          '(e.g. example-robot-data:ur_description/urdf/ur5_robot.urdf); empty: the planar '
          'arm of joint_names, masses, lengths. Gravity acts along -z of the root link.'),
    _Spec('urdf.joints', [], 'URDF arm: the joints that move, base to tip; empty: every '
          'revolute joint. The published joint names.', ptype=Parameter.Type.STRING_ARRAY,
          constraints='revolute joints with limits'),
    _Spec('urdf.locked_joints', [], 'URDF arm: movable joints locked at '
          'urdf.locked_positions; any other joint that does not move is locked at 0 clipped '
          'into its limits.', ptype=Parameter.Type.STRING_ARRAY),
    _Spec('urdf.locked_positions', [], 'URDF arm: one position (rad or m) per '
          'urdf.locked_joints.', ptype=Parameter.Type.DOUBLE_ARRAY),
    _Spec('urdf.home', [], 'URDF arm: the pose the references swing about (rad), one per '
          "moving joint; empty: the middle of each joint's limits.",
          ptype=Parameter.Type.DOUBLE_ARRAY),
    _Spec('urdf.armature', [], 'URDF arm: rotor inertia of the drive of each joint (kg m^2, '
          'the rotor times the gear ratio squared), one per moving joint or one for all; '
          'empty: none.', ptype=Parameter.Type.DOUBLE_ARRAY, constraints='each >= 0'),
)


class UrdfChoice(NamedTuple):
    """A URDF arm as ``sim_arm`` builds it."""

    arm: UrdfArm
    joint_names: Tuple[str, ...]
    home: np.ndarray        # (n,) centre of the references
    description: str        # the reduced URDF, published on robot_description


def build_urdf_arm(values: dict, error=ValueError) -> Optional[UrdfChoice]:
    """
    Return the URDF arm the parameter values describe, or None for the planar arm.

    Parameters
    ----------
    values : dict
        sim_arm's parameter values by name.
    error : type
        The exception raised for a bad value (the node's ConfigurationError); its message
        names the parameter or the URDF and the problem.

    """
    description = values.get('robot_description', '')
    if not description.strip():
        return None
    locked_names = list(values['urdf.locked_joints'])
    locked_values = list(values['urdf.locked_positions'])
    if len(locked_names) != len(locked_values):
        raise error(f'urdf.locked_positions has {len(locked_values)} values for the '
                    f'{len(locked_names)} urdf.locked_joints; give one per joint')
    try:
        arm = UrdfArm(description, joints=list(values['urdf.joints']) or None,
                      locked=dict(zip(locked_names, locked_values)),
                      gravity=values['gravity'], coulomb_velocity=values['coulomb_velocity'])
    except UrdfError as problem:
        raise error(str(problem)) from None
    n = arm.n_joints
    armature = np.asarray(values.get('urdf.armature', []), dtype=float)
    if armature.size:
        if armature.size not in (1, n):
            raise error(f'urdf.armature has {armature.size} values for the {n} moving joints '
                        f'{list(arm.joint_names)}: give one per joint or one for all')
        try:
            arm.set_armature(armature if armature.size == n else float(armature[0]))
        except ValueError as problem:
            raise error(f'urdf.armature: {problem}') from None
    home = np.asarray(values['urdf.home'], dtype=float)
    if home.size == 0:
        home = arm.home
    elif home.shape != (n,):
        raise error(f'urdf.home has {home.size} values for the {n} moving joints '
                    f'{list(arm.joint_names)}')
    return UrdfChoice(arm, arm.joint_names, home, arm.urdf)


def reference_limit_warning(arm: UrdfArm, reference, duration: float = 60.0) -> Optional[str]:
    """Return a warning if the reference leaves a joint's limits in its first seconds."""
    theta_d, _ = reference.evaluate(np.linspace(0.0, duration, 2001))
    below = np.any(theta_d < arm.lower, axis=0)
    above = np.any(theta_d > arm.upper, axis=0)
    outside = [name for name, b, a in zip(arm.joint_names, below, above) if b or a]
    if not outside:
        return None
    return (f'the reference leaves the URDF limits of {outside} within {duration:g} s (the '
            'simulation does not stop at limits); move urdf.home or lower '
            'reference.amplitude')

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

"""The identifier's robot description: sources, joints matched by name, bad descriptions."""

import time

import pytest

pytest.importorskip('pinocchio')

from rkgnn_ros.identification.description import (  # noqa: E402
    description_text, MAX_DESCRIPTION_BYTES, RobotDescription)
from urdf_helpers import planar_urdf  # noqa: E402

UR5 = 'example-robot-data:ur_description/urdf/ur5_robot.urdf'
UR5_JOINTS = ('shoulder_pan_joint', 'shoulder_lift_joint', 'elbow_joint', 'wrist_1_joint',
              'wrist_2_joint', 'wrist_3_joint')


def described(text, joints=('joint1', 'joint2', 'joint3'), locked=(), positions=(),
              topic=False):
    lines = []
    description = RobotDescription(lambda level, line: lines.append((level, line)))
    description.configure('' if topic else text, locked, positions, 9.81)
    if topic:
        description.take_message(text)
    return description, description.structure(joints), lines


def test_the_parameter_or_the_topic_gives_the_structure_of_the_joints_in_their_order():
    urdf = planar_urdf([6.0, 4.0, 3.0], [0.2, 0.3, 0.1])
    for topic in (False, True):
        description, structure, lines = described(urdf, ('joint3', 'joint1', 'joint2'),
                                                  topic=topic)
        assert structure is not None and structure.joint_names == ('joint3', 'joint1', 'joint2')
        assert 'in use' in description.status and lines[-1][0] == 'info'
    # the same description and joints give the same structure without a second build
    assert description.structure(('joint3', 'joint1', 'joint2')) is structure
    # a parameter wins over the topic
    description.configure(planar_urdf([1.0, 1.0, 1.0], [0.2, 0.3, 0.1]), (), (), 9.81)
    assert description.structure(('joint3', 'joint1', 'joint2')) is not structure


def test_urdf_joints_not_identified_are_held_and_said_in_the_log():
    description, structure, lines = described(UR5, UR5_JOINTS[:3], ['wrist_1_joint'], [0.5])
    assert structure is not None and structure.n_joints == 3
    assert 'wrist_1_joint = 0.5' in lines[-1][1] and 'wrist_2_joint = 0' in lines[-1][1]


@pytest.mark.parametrize('text, joints, words', [
    ('<robot name="x"><link name="a"', None, 'not valid XML'),
    ('<?xml version="1.0"?><!DOCTYPE r [<!ENTITY a "aaaaaaaaaa"><!ENTITY b "&a;&a;&a;&a;">]>'
     '<robot name="r">&b;</robot>', None, 'document type'),
    ('<html/>', None, 'not a URDF'),
    (planar_urdf([6.0, 4.0, 3.0], [0.2, 0.3, 0.1]), ('joint1', 'joint2', 'gripper'),
     "no joint named 'gripper'"),
    (planar_urdf([6.0, 4.0, 3.0], [0.2, 0.3, 0.1], joint_type='prismatic'), None,
     'prismatic'),
    (planar_urdf([6.0, 4.0, 3.0], [0.2, 0.3, 0.1], joint_type='continuous'), None,
     'continuous'),
    (planar_urdf([6.0, 'nan', 3.0], [0.2, 0.3, 0.1]), None, 'finite'),
    (planar_urdf([6.0, -4.0, 3.0], [0.2, 0.3, 0.1]), None, 'negative'),
    ('/no/such/file.urdf', None, 'cannot read'),
])
def test_a_bad_description_is_refused_once_with_a_clear_message(text, joints, words):
    description, structure, lines = described(text, joints or ('joint1', 'joint2', 'joint3'))
    assert structure is None
    assert words in description.status, description.status
    assert len(lines) == 1 and lines[0][0] == 'error' and 'without kinematics' in lines[0][1]
    description.structure(joints or ('joint1', 'joint2', 'joint3'))
    assert len(lines) == 1                      # said once, not at every step


def test_a_huge_description_is_refused_before_it_is_parsed():
    huge = '<robot name="r">' + ' ' * (MAX_DESCRIPTION_BYTES + 10) + '</robot>'
    start = time.monotonic()
    description, structure, lines = described(huge)
    assert structure is None and 'bytes' in description.status
    assert time.monotonic() - start < 30.0       # refused, not parsed (no hang)
    with pytest.raises(ValueError, match='bytes'):
        description_text(b'\0' * (MAX_DESCRIPTION_BYTES + 1000))


def test_a_raw_message_decodes_to_its_text():
    from rclpy.serialization import serialize_message
    from std_msgs.msg import String
    assert description_text(serialize_message(String(data='<robot name="r"/>'))) == \
        '<robot name="r"/>'
    with pytest.raises(ValueError, match='decode'):
        description_text(b'\x00\x01')

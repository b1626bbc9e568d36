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
Start the simulated arm and the online identifier with the package's config files.

Arguments: ``namespace`` (one arm per namespace: ``namespace:=arm1``; the config files'
``/**/`` keys apply there), ``use_sim_time`` (``true`` to follow ``/clock``, e.g. a
recording played with ``ros2 bag play --clock``), ``sim`` (``false``: the identifier alone,
for a real arm's streams), ``sim_params`` and ``identifier_params`` (the parameters files;
``sim_params:=.../config/sim_arm_ur5.yaml`` simulates a UR5).
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue


def generate_launch_description():
    share = get_package_share_directory('rkgnn_ros')
    sim_params = LaunchConfiguration('sim_params')
    identifier_params = LaunchConfiguration('identifier_params')
    namespace = LaunchConfiguration('namespace')
    sim_time = {'use_sim_time': ParameterValue(LaunchConfiguration('use_sim_time'),
                                               value_type=bool)}
    return LaunchDescription([
        DeclareLaunchArgument(
            'sim_params', default_value=os.path.join(share, 'config', 'sim_arm.yaml'),
            description='parameters file of sim_arm'),
        DeclareLaunchArgument(
            'identifier_params',
            default_value=os.path.join(share, 'config', 'identifier.yaml'),
            description='parameters file of the identifier'),
        DeclareLaunchArgument('namespace', default_value='',
                              description='namespace of both nodes (one arm per namespace)'),
        DeclareLaunchArgument('use_sim_time', default_value='false',
                              description='true: both nodes follow /clock'),
        DeclareLaunchArgument('sim', default_value='true',
                              description='false: start the identifier alone (a real arm)'),
        Node(package='rkgnn_ros', executable='sim_arm', name='sim_arm', namespace=namespace,
             parameters=[sim_params, sim_time], output='screen',
             condition=IfCondition(LaunchConfiguration('sim'))),
        Node(package='rkgnn_ros', executable='identifier', name='identifier',
             namespace=namespace, parameters=[identifier_params, sim_time], output='screen'),
    ])

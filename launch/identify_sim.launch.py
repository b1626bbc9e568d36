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

"""Start the simulated arm and the online identifier with the package's config files."""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description():
    share = get_package_share_directory('rkgnn_ros')
    sim_params = LaunchConfiguration('sim_params')
    identifier_params = LaunchConfiguration('identifier_params')
    return LaunchDescription([
        DeclareLaunchArgument(
            'sim_params', default_value=os.path.join(share, 'config', 'sim_arm.yaml'),
            description='parameters file of sim_arm'),
        DeclareLaunchArgument(
            'identifier_params',
            default_value=os.path.join(share, 'config', 'identifier.yaml'),
            description='parameters file of the identifier'),
        Node(package='rkgnn_ros', executable='sim_arm', name='sim_arm',
             parameters=[sim_params], output='screen'),
        Node(package='rkgnn_ros', executable='identifier', name='identifier',
             parameters=[identifier_params], output='screen'),
    ])

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

"""URDFs written for the tests."""


def planar_urdf(masses, lengths, joint_type='revolute', limits=True, inertial=True):
    """Return a URDF of the planar arm of core/sim/plant.py: point masses at the link tips."""
    links = ['<link name="base"/>']
    joints = []
    parent = 'base'
    for i, (m, length) in enumerate(zip(masses, lengths)):
        name = f'link{i + 1}'
        mass = (f'<inertial><origin xyz="{length} 0 0"/><mass value="{m}"/><inertia ixx="0" '
                'ixy="0" ixz="0" iyy="0" iyz="0" izz="0"/></inertial>') if inertial else ''
        links.append(f'<link name="{name}">{mass}</link>')
        origin = '0 0 0' if i == 0 else f'{lengths[i - 1]} 0 0'
        limit = '<limit lower="-3" upper="3" effort="100" velocity="5"/>' if limits else ''
        # axis -y: a positive angle turns x towards +z, gravity acts along -z
        joints.append(f'<joint name="joint{i + 1}" type="{joint_type}"><parent link="{parent}"/>'
                      f'<child link="{name}"/><origin xyz="{origin}"/><axis xyz="0 -1 0"/>'
                      f'{limit}</joint>')
        parent = name
    return '<robot name="planar">' + ''.join(links + joints) + '</robot>'

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
The identified URDF: the robot description with its inertials replaced by what was fitted.

Each moving joint's child link gets the identified body (the link and everything fixed to
it: one rigid body to the data) as its ``<inertial>``: mass (kg), centre of mass as the
origin (m, in the link's frame, which is the joint's), inertia about the centre of mass
(kg m²); every link fixed to it loses its own, so the whole mass is counted once. Each
moving joint's ``<dynamics>`` gets the viscous (``damping``, N m s/rad) and Coulomb
(``friction``, N m) coefficients. URDF has no field for rotor inertia or a torque offset:
they go in a comment at the top of the file, beside the identified values' source. Links
before the first moving joint keep what the description said (nothing moves them).
"""

from typing import Optional

import numpy as np

__all__ = ['identified_urdf']


def _inertials(bodies: np.ndarray):
    """Return (mass, centre of mass, inertia about it) per body of parameters (B, 10)."""
    mass = bodies[:, 0]
    safe = np.where(mass > 0.0, mass, 1.0)
    com = np.where(mass[:, None] > 0.0, bodies[:, 1:4] / safe[:, None], 0.0)
    inertia = np.empty((bodies.shape[0], 3, 3))
    inertia[:, 0, 0], inertia[:, 1, 1], inertia[:, 2, 2] = bodies[:, 4], bodies[:, 5], bodies[:, 6]
    inertia[:, 0, 1] = inertia[:, 1, 0] = bodies[:, 7]
    inertia[:, 0, 2] = inertia[:, 2, 0] = bodies[:, 8]
    inertia[:, 1, 2] = inertia[:, 2, 1] = bodies[:, 9]
    outer = com[:, :, None] * com[:, None, :]
    c2 = np.sum(com * com, axis=1)
    inertia -= mass[:, None, None] * (c2[:, None, None] * np.eye(3) - outer)
    return mass, com, inertia


def identified_urdf(structure, parameters, note: Optional[str] = None) -> str:
    """
    Return ``structure``'s URDF with the identified ``parameters`` (module docstring).

    ``note``: a line for the comment at the top (e.g. when and from what it was fitted).
    """
    import xml.etree.ElementTree as ElementTree
    import pinocchio
    parameters = np.asarray(parameters, dtype=float).reshape(-1)
    n = structure.n_joints
    root = ElementTree.fromstring(structure.urdf)
    model = pinocchio.buildModelFromXML(structure.urdf)
    links = {link.get('name'): link for link in root.findall('link')}
    joints = {joint.get('name'): joint for joint in root.findall('joint')}
    mass, com, inertia = _inertials(parameters[:10 * n].reshape(n, 10))
    joint_terms = parameters[10 * n:].reshape(n, 4)
    # the links each moving joint carries: the frames of kind BODY that hang on it
    carried = {j: [] for j in range(1, model.njoints)}
    for frame in model.frames:
        if frame.type == pinocchio.FrameType.BODY and frame.parentJoint in carried:
            carried[frame.parentJoint].append(frame.name)
    for j in range(1, model.njoints):
        name = model.names[j]
        b = j - 1
        child = joints[name].find('child').get('link')
        for link_name in carried[j]:
            link = links.get(link_name)
            if link is None:
                continue
            for old in link.findall('inertial'):
                link.remove(old)
        link = links[child]
        inertial = ElementTree.SubElement(link, 'inertial')
        ElementTree.SubElement(inertial, 'origin', xyz=' '.join(repr(float(v)) for v in com[b]),
                               rpy='0 0 0')
        ElementTree.SubElement(inertial, 'mass', value=repr(float(mass[b])))
        i = inertia[b]
        ElementTree.SubElement(inertial, 'inertia', ixx=repr(float(i[0, 0])),
                               ixy=repr(float(i[0, 1])), ixz=repr(float(i[0, 2])),
                               iyy=repr(float(i[1, 1])), iyz=repr(float(i[1, 2])),
                               izz=repr(float(i[2, 2])))
        column = structure.tree.col[b]
        joint = joints[name]
        for old in joint.findall('dynamics'):
            joint.remove(old)
        ElementTree.SubElement(joint, 'dynamics', damping=repr(float(joint_terms[column, 1])),
                               friction=repr(float(joint_terms[column, 2])))
    lines = ['identified by rkgnn_ros' + (f': {note}' if note else '')]
    lines += [f'{name}: rotor inertia {row[0]:.6g} kg m^2, Coulomb smoothing '
              f'{structure.tree.coulomb_velocity:g} rad/s, torque offset {row[3]:.6g} N m'
              for name, row in zip(structure.joint_names, joint_terms)]
    comment = '<!-- ' + '\n     '.join(line.replace('--', '- -') for line in lines) + ' -->\n'
    return comment + ElementTree.tostring(root, encoding='unicode')

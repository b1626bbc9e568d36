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
The identified rigid-body model as the identifier publishes it on ``~/model``.

:class:`RigidModel` holds an identified :class:`~.rigid_fit.RigidArm`, the servo law it
predicts with and what the fit says of itself. Its YAML (``kind: rigid_body``) gives,
per moving body (the joint's child link with every link fixed to it), the mass (kg), the
centre of mass (m) and the inertia about the centre of mass (kg m², in the joint's frame,
as a URDF ``<inertial>`` gives them), per joint the rotor inertia (kg m²), viscous (N m
s/rad) and Coulomb friction (N m, smoothed by tanh(θ̇ / v_c)) and a torque offset (N m),
the full parameter vector in :mod:`rkgnn_ros.core.rigid`'s order, the base parameters,
and the law. In case 3 every number is in the units the robot description's masses fix
(``info['scale_from']``).
"""

import math
from typing import Optional

import numpy as np
import yaml

from .controller_laws import ControllerLaw
from .rigid_fit import RigidArm

__all__ = ['FORMAT', 'RigidModel', 'body_inertials']

#: Version of the YAML layout.
FORMAT = 1


def body_inertials(bodies: np.ndarray):
    """
    Return (mass (B,), centre of mass (B, 3), inertia about it (B, 3, 3)) of body parameters.

    ``bodies`` (B, 10): m, m c, the inertia about the frame's origin; a body without mass
    has its centre at the origin.
    """
    bodies = np.asarray(bodies, dtype=float).reshape(-1, 10)
    mass = bodies[:, 0]
    com = np.where(mass[:, None] > 0.0, bodies[:, 1:4] / np.where(mass > 0.0, mass, 1.0)[:, None],
                   0.0)
    inertia = np.empty((bodies.shape[0], 3, 3))
    inertia[:, 0, 0], inertia[:, 1, 1], inertia[:, 2, 2] = bodies[:, 4], bodies[:, 5], bodies[:, 6]
    inertia[:, 0, 1] = inertia[:, 1, 0] = bodies[:, 7]
    inertia[:, 0, 2] = inertia[:, 2, 0] = bodies[:, 8]
    inertia[:, 1, 2] = inertia[:, 2, 1] = bodies[:, 9]
    # parallel axes: I_c = I_o − m (|c|² 1 − c cᵀ)
    c2 = np.sum(com * com, axis=1)
    outer = com[:, :, None] * com[:, None, :]
    inertia -= mass[:, None, None] * (c2[:, None, None] * np.eye(3) - outer)
    return mass, com, inertia


def _plain(value):
    if isinstance(value, (float, np.floating)):
        value = float(value)
        return value if math.isfinite(value) else None
    if isinstance(value, np.ndarray):
        return [_plain(v) for v in value.tolist()]
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    return value


class RigidModel:
    """
    An identified rigid-body model of a robot description and the law it predicts with.

    Parameters
    ----------
    arm : RigidArm
        The identified arm.
    law : ControllerLaw or None
        The servo's law (fitted in cases 1 and 3, the known gains in case 2).
    case : str
        'torque', 'pd_gains' or 'unknown'.
    dt : float
        The data's sampling interval (s).
    info : dict, optional
        What the fit says of itself (held-out errors, samples, scale).

    """

    kind = 'rigid_body'

    def __init__(self, arm: RigidArm, law: Optional[ControllerLaw], case: str, dt: float,
                 info: Optional[dict] = None):
        self.arm, self.law, self.case, self.dt = arm, law, case, float(dt)
        self.info = dict(arm.info)
        self.info.update(info or {})

    @property
    def joint_names(self):
        """Return the joint names, in the joint vector's order."""
        return tuple(self.arm.joint_names)

    @property
    def n_joints(self) -> int:
        """Return the number of joints n."""
        return self.arm.n_joints

    @property
    def kp(self):
        """Return the law's Kp (N m/rad), or None without a law."""
        return None if self.law is None else self.law.kp

    @property
    def kd(self):
        """Return the law's Kd (N m s/rad), or None without a law."""
        return None if self.law is None else self.law.kd

    def implied_gains(self):
        """Return the law's (Kp, Kd), or None without a law."""
        return None if self.law is None else (self.law.kp.copy(), self.law.kd.copy())

    def simulate(self, x0, t, tau=None, theta_d=None, theta_d_dot=None, reference=None,
                 substeps=None) -> np.ndarray:
        """
        Roll the model out from ``x0`` over ``t``: closed with its law along the commands.

        The commands are ``theta_d``, ``theta_d_dot`` (K, n) or ``reference.evaluate(t)``;
        without a law, open loop under ``tau`` (held per interval). ``substeps`` is the
        loop's RKG steps per interval (None: from its stiffness). States (K, 2n).
        """
        from .rigid_loop import RigidLoop
        if self.law is None or (theta_d is None and reference is None):
            if tau is None:
                raise ValueError('a rigid-body model without a law rolls out under torque only')
            return self.arm.simulate(x0, t, tau=tau)
        if theta_d is None:
            theta_d, theta_d_dot = reference.evaluate(np.asarray(t, dtype=float))
        return RigidLoop(self.arm, self.law, substeps).simulate(x0, t, theta_d, theta_d_dot)

    def warm_up(self) -> None:
        """Compile (or load from numba's cache) the rollout kernel this model predicts with."""
        from .rigid_loop import precompile_rigid_loop
        precompile_rigid_loop(self.arm.structure)

    def to_dict(self) -> dict:
        """Return the plain-data form published on ``~/model`` (module docstring)."""
        structure = self.arm.structure
        names = structure.joint_names
        mass, com, inertia = body_inertials(self.arm.bodies())
        order = np.argsort(structure.tree.col)       # bodies in joint-vector order
        bodies = [{'joint': names[structure.tree.col[b]], 'mass': float(mass[b]),
                   'com': com[b].tolist(),
                   'inertia': [inertia[b, 0, 0], inertia[b, 1, 1], inertia[b, 2, 2],
                               inertia[b, 0, 1], inertia[b, 0, 2], inertia[b, 1, 2]]}
                  for b in order]
        joints = [{'joint': name, 'armature': float(row[0]), 'viscous': float(row[1]),
                   'coulomb': float(row[2]), 'offset': float(row[3])}
                  for name, row in zip(names, self.arm.joint_terms())]
        return _plain({
            'kind': self.kind, 'format': FORMAT, 'case': self.case,
            'joint_names': list(names), 'dt': self.dt, 'source': structure.source,
            'coulomb_velocity': float(structure.tree.coulomb_velocity),
            'bodies': bodies, 'joints': joints,
            'parameters': self.arm.parameters,
            'base_parameters': structure.base.of(self.arm.parameters),
            'controller_law': None if self.law is None else self.law.to_dict(),
            'info': self.info})

    def save(self, path) -> None:
        """Write :meth:`to_yaml` atomically (temp file in the same folder, fsync, replace)."""
        from ..model.files import save_text_atomic
        save_text_atomic(path, self.to_yaml())

    def to_yaml(self) -> str:
        """Return the YAML text of :meth:`to_dict`."""
        return yaml.safe_dump(self.to_dict(), sort_keys=False, default_flow_style=None,
                              width=100)

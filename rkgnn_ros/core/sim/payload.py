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
A payload on the arm's last link: the plant the simulator integrates after a pick-up.

:func:`with_payload` returns a copy of the arm carrying a point mass ``mass`` (kg) at
``com`` (m) on its last moving link: for a URDF arm in the last joint's frame (added to its
inertia, Pinocchio's ``Inertia`` of a point mass), for the planar arm of point masses at
the link tip (added to the last mass; ``com`` is not used). The arm given is not changed, so
a servo that compensates gravity keeps the nominal model, as a real servo does.
"""

import copy
from dataclasses import replace

import numpy as np

from .plant import PlanarArm

__all__ = ['with_payload']


def with_payload(arm, mass: float, com=(0.0, 0.0, 0.0)):
    """Return a copy of ``arm`` with the payload on its last link (module docstring)."""
    mass = float(mass)
    com = np.asarray(com, dtype=float).reshape(-1)
    if not (np.isfinite(mass) and mass >= 0.0):
        raise ValueError(f'a payload mass must be finite and >= 0, got {mass}')
    if com.shape != (3,) or not np.all(np.isfinite(com)):
        raise ValueError(f'a payload centre of mass must be 3 finite numbers (m), got {com}')
    if isinstance(arm, PlanarArm):
        params = arm.params
        if params.mass_model != 'point':
            raise ValueError(f"a payload on the planar arm needs mass_model 'point' (a mass "
                             f'at the tip), not {params.mass_model!r}')
        masses = np.array(params.masses, dtype=float)
        masses[-1] += mass
        return PlanarArm(replace(params, masses=masses))
    import pinocchio
    out = copy.copy(arm)
    out.model = pinocchio.Model(arm.model)
    last = out.model.njoints - 1
    out.model.inertias[last] = out.model.inertias[last] + pinocchio.Inertia(
        mass, com, np.zeros((3, 3)))
    out._data = out.model.createData()
    return out

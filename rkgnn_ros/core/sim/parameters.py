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
The physical parameters of a planar n-link arm: masses, lengths, mass model, gravity, friction.

Validated once, at construction; :class:`.plant.PlanarArm` derives its dynamics from them.
"""

from dataclasses import dataclass
from typing import Optional

import numpy as np

MASS_MODELS = ('point', 'rod')


def _vector(name: str, value, n: Optional[int] = None, *, positive=False,
            nonnegative=False) -> np.ndarray:
    """Validate a finite 1-D float vector (a scalar is broadcast when ``n`` is given)."""
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 0 and n is not None:
        arr = np.full(n, float(arr))
    if arr.ndim != 1:
        raise ValueError(f'{name} must be a 1-D array, got shape {arr.shape}')
    if n is not None and arr.size != n:
        raise ValueError(f'{name} must have {n} entries, got {arr.size}')
    if not np.all(np.isfinite(arr)):
        raise ValueError(f'{name} must be finite, got {arr}')
    if positive and np.any(arr <= 0.0):
        raise ValueError(f'{name} must be positive, got {arr}')
    if nonnegative and np.any(arr < 0.0):
        raise ValueError(f'{name} must be non-negative, got {arr}')
    return arr


@dataclass(frozen=True, eq=False)
class ArmParameters:
    """
    Physical parameters of a planar n-link arm.

    Attributes
    ----------
    masses : ndarray, shape (n,)
        Link masses m_i (kg), positive.
    lengths : ndarray, shape (n,)
        Link lengths l_i (m), positive.
    mass_model : {'point', 'rod'}
        ``'point'`` (default): each mass is a point at the distal end of its link, c_i = l_i,
        no inertia about the centre of mass (the paper's Table 1 gives only masses and
        lengths). ``'rod'``: uniform slender rods, c_i = l_i / 2, inertia m_i l_i² / 12 about
        the centre of mass.
    gravity : float
        Gravitational acceleration g (m/s²) along -y; the arm moves in a vertical plane.
    viscous : ndarray, shape (n,)
        Viscous friction coefficients (N m s/rad), default zeros.
    coulomb : ndarray, shape (n,)
        Coulomb friction levels (N m), default zeros. The friction torque is
        ``viscous * θ̇ + coulomb * tanh(θ̇ / coulomb_velocity)``.
    coulomb_velocity : float
        Smoothing velocity (rad/s) of the Coulomb term, positive.

    """

    masses: np.ndarray
    lengths: np.ndarray
    mass_model: str = 'point'
    gravity: float = 9.81
    viscous: Optional[np.ndarray] = None
    coulomb: Optional[np.ndarray] = None
    coulomb_velocity: float = 0.05

    def __post_init__(self):
        masses = _vector('masses', self.masses, positive=True)
        n = masses.size
        if n < 1:
            raise ValueError('masses must have at least one entry (n >= 1)')
        lengths = _vector('lengths', self.lengths, n, positive=True)
        if self.mass_model not in MASS_MODELS:
            raise ValueError(f'mass_model must be one of {MASS_MODELS}, got {self.mass_model!r}')
        gravity = float(self.gravity)
        if not np.isfinite(gravity):
            raise ValueError(f'gravity must be finite, got {self.gravity}')
        viscous = _vector('viscous', 0.0 if self.viscous is None else self.viscous, n,
                          nonnegative=True)
        coulomb = _vector('coulomb', 0.0 if self.coulomb is None else self.coulomb, n,
                          nonnegative=True)
        coulomb_velocity = float(self.coulomb_velocity)
        if not (np.isfinite(coulomb_velocity) and coulomb_velocity > 0.0):
            raise ValueError(f'coulomb_velocity must be positive, got {self.coulomb_velocity}')
        for name, value in (('masses', masses), ('lengths', lengths), ('gravity', gravity),
                            ('viscous', viscous), ('coulomb', coulomb),
                            ('coulomb_velocity', coulomb_velocity)):
            object.__setattr__(self, name, value)

    @classmethod
    def paper(cls, mass_model: str = 'point') -> 'ArmParameters':
        """
        Return the three-link arm of the paper's Table 1 with modest friction.

        Masses (6, 4, 3) kg and lengths (0.2, 0.3, 0.1) m are the paper's. The paper gives no
        friction values; these are plausible for small geared joints, decreasing towards the
        wrist: viscous (0.5, 0.3, 0.1) N m s/rad and Coulomb (0.3, 0.2, 0.1) N m, smoothed
        with ``tanh(θ̇ / 0.05 rad/s)``.
        """
        return cls(masses=np.array([6.0, 4.0, 3.0]), lengths=np.array([0.2, 0.3, 0.1]),
                   mass_model=mass_model, gravity=9.81,
                   viscous=np.array([0.5, 0.3, 0.1]), coulomb=np.array([0.3, 0.2, 0.1]),
                   coulomb_velocity=0.05)

    @property
    def n_joints(self) -> int:
        """Count of links and joints, n."""
        return self.masses.size

    @property
    def com_distances(self) -> np.ndarray:
        """Distance c_i of each link's centre of mass from its joint, shape (n,)."""
        return self.lengths if self.mass_model == 'point' else 0.5 * self.lengths

    @property
    def com_inertias(self) -> np.ndarray:
        """Inertia of each link about its own centre of mass (kg m²), shape (n,)."""
        if self.mass_model == 'point':
            return np.zeros(self.n_joints)
        return self.masses * self.lengths ** 2 / 12.0

    @property
    def first_moments(self) -> np.ndarray:
        """First moments m_i c_i of the links about their joints (kg m), shape (n,)."""
        return self.masses * self.com_distances

    @property
    def joint_inertias(self) -> np.ndarray:
        """Inertias J_i = m_i c_i² + I_ci of the links about their joints, shape (n,)."""
        return self.masses * self.com_distances ** 2 + self.com_inertias

    def without_friction(self) -> 'ArmParameters':
        """Return a copy with zero viscous and Coulomb friction."""
        return ArmParameters(self.masses, self.lengths, self.mass_model, self.gravity,
                             coulomb_velocity=self.coulomb_velocity)

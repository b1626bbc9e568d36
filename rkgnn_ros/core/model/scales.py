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
The physical scales of the data, which map the normalised genome to physical units.

Every genome element is of order one and is mapped to physical units by the scales measured
on the data (RMS torque, velocity, acceleration, spread of θ), so that one mutation spread
suits every element and the search does not depend on units.

Case 3 has a gauge freedom: scaling M, V, G, F and the torque network by one factor leaves
the motion unchanged, so without torque the absolute scale is not identifiable. The torque
scale is then fixed to 1 N m (:meth:`Scales.from_datasets`); identified gains are relative.
"""

from dataclasses import asdict, dataclass
from typing import Dict

import numpy as np


@dataclass(frozen=True)
class Scales:
    """
    Physical scales that map the normalised genome to physical units, one value per joint.

    Attributes
    ----------
    theta_center, theta_spread : ndarray, shape (n,)
        Mean and standard deviation of θ (rad): where RBF centres start and how far apart.
    velocity, acceleration : ndarray, shape (n,)
        RMS of θ̇ (rad/s) and of θ̈ (rad/s²).
    torque : ndarray, shape (n,)
        RMS of τ (N m); 1 in case 3, where it is not identifiable.
    error, error_rate : ndarray, shape (n,)
        RMS of θd - θ and of θ̇d - θ̇ (inputs of the torque network).

    """

    theta_center: np.ndarray
    theta_spread: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray
    torque: np.ndarray
    error: np.ndarray
    error_rate: np.ndarray

    def __post_init__(self):
        n = None
        for name, value in asdict(self).items():
            arr = np.asarray(value, dtype=float).reshape(-1)
            if n is None:
                n = arr.size
            if arr.size != n or not np.all(np.isfinite(arr)):
                raise ValueError(f'Scales.{name} must be {n} finite values, got {value!r}')
            if name != 'theta_center' and np.any(arr <= 0.0):
                raise ValueError(f'Scales.{name} must be positive, got {arr.tolist()}')
            object.__setattr__(self, name, arr)

    @property
    def inertia(self) -> np.ndarray:
        """Inertia scale per joint, torque / acceleration (kg m²), shape (n,)."""
        return self.torque / self.acceleration

    @classmethod
    def from_datasets(cls, datasets, case, kp=None, kd=None) -> 'Scales':
        """Measure the scales on a list of :class:`~rkgnn_ros.core.data.Dataset`."""
        if case == 'torque' and any(d.tau is None for d in datasets):
            raise ValueError("case 'torque' needs measured torque (Dataset.tau)")
        if case in ('pd_gains', 'unknown') and any(
                d.theta_d is None or d.theta_d_dot is None for d in datasets):
            raise ValueError(f'case {case!r} needs the desired trajectory '
                             '(Dataset.theta_d, theta_d_dot)')
        theta = np.vstack([d.theta for d in datasets])
        theta_dot = np.vstack([d.theta_dot for d in datasets])
        acc = np.vstack([np.gradient(d.theta_dot, d.dt, axis=0) for d in datasets])
        n = theta.shape[1]
        floor = 1e-3

        def rms(a, low=floor):
            return np.maximum(np.sqrt(np.mean(np.square(a), axis=0)), low)

        if case in ('pd_gains', 'unknown'):
            err = np.vstack([d.theta_d - d.theta for d in datasets])
            derr = np.vstack([d.theta_d_dot - d.theta_dot for d in datasets])
        else:
            err = derr = np.ones((1, n))
        if case == 'torque':
            torque = rms(np.vstack([d.tau for d in datasets]))
        elif case == 'pd_gains':
            torque = rms(err * np.asarray(kp, dtype=float) + derr * np.asarray(kd, dtype=float))
        else:
            torque = np.ones(n)
        return cls(theta_center=theta.mean(axis=0),
                   theta_spread=np.maximum(theta.std(axis=0), 0.05),
                   velocity=rms(theta_dot, 0.05), acceleration=rms(acc, 0.5),
                   torque=torque, error=rms(err), error_rate=rms(derr))

    def to_dict(self) -> Dict[str, list]:
        """Plain lists, for YAML."""
        return {k: np.asarray(v).tolist() for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d) -> 'Scales':
        """Inverse of :meth:`to_dict`; raises ValueError on missing or bad entries."""
        names = ('theta_center', 'theta_spread', 'velocity', 'acceleration', 'torque',
                 'error', 'error_rate')
        missing = [k for k in names if k not in d]
        if missing:
            raise ValueError(f'scales: missing {missing}')
        return cls(**{k: d[k] for k in names})

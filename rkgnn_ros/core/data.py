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
Uniformly sampled joint data: the one container every part of the core exchanges.

A :class:`Dataset` is one contiguous segment sampled at a fixed interval ``dt``. Data with
gaps is a list of datasets (no rollout ever crosses a gap).
"""

from dataclasses import dataclass, field, replace
from typing import Optional, Tuple

import numpy as np


def finite_array(name: str, value, shape: Optional[Tuple[int, ...]] = None,
                 ndim: Optional[int] = None, min_ndim: int = 0) -> np.ndarray:
    """
    Return ``value`` as a finite float array, or raise a ValueError naming ``name``.

    Checked in this order: numeric, ``shape`` (if given), exactly ``ndim`` dimensions (if
    given), at least ``min_ndim`` (1: a joint axis), then no NaN or inf.
    """
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f'{name} must be numeric: {exc}') from None
    if shape is not None and arr.shape != shape:
        raise ValueError(f'{name} must have shape {shape}, got {arr.shape}')
    if ndim is not None and arr.ndim != ndim:
        raise ValueError(f'{name} must be {ndim}-D, got shape {arr.shape}')
    if arr.ndim < min_ndim:
        raise ValueError(f'{name} must have a joint axis, got a scalar')
    if not np.all(np.isfinite(arr)):
        raise ValueError(f'{name} must be finite (no NaN or inf)')
    return arr


@dataclass(frozen=True)
class Dataset:
    """
    One uniformly sampled, gap-free segment of joint data.

    Attributes
    ----------
    t : ndarray, shape (N,)
        Sample times in seconds, ``t[k] = t[0] + k * dt``.
    theta : ndarray, shape (N, n)
        Measured joint angles θ (rad).
    theta_dot : ndarray, shape (N, n)
        Measured joint velocities θ̇ (rad/s).
    tau : ndarray, shape (N, n) or None
        Applied joint torques (N m), held constant over each interval ``[t[k], t[k+1])``.
    theta_d, theta_d_dot : ndarray, shape (N, n) or None
        Desired trajectory θd, θ̇d at the same times.
    joint_names : tuple of str
        Names of the n joints, in column order.

    """

    t: np.ndarray
    theta: np.ndarray
    theta_dot: np.ndarray
    tau: Optional[np.ndarray] = None
    theta_d: Optional[np.ndarray] = None
    theta_d_dot: Optional[np.ndarray] = None
    joint_names: Tuple[str, ...] = field(default=())

    def __post_init__(self):
        t = np.asarray(self.t, dtype=float)
        if t.ndim != 1 or t.size < 2:
            raise ValueError(f'Dataset.t must be 1-D with at least 2 samples, got shape {t.shape}')
        object.__setattr__(self, 't', t)
        n_samples = t.size
        n_joints = None
        for name in ('theta', 'theta_dot', 'tau', 'theta_d', 'theta_d_dot'):
            value = getattr(self, name)
            if value is None:
                if name in ('theta', 'theta_dot'):
                    raise ValueError(f'Dataset.{name} is required')
                continue
            arr = np.asarray(value, dtype=float)
            if arr.ndim != 2 or arr.shape[0] != n_samples:
                raise ValueError(
                    f'Dataset.{name} must have shape (N={n_samples}, n), got {arr.shape}')
            if n_joints is None:
                n_joints = arr.shape[1]
            elif arr.shape[1] != n_joints:
                raise ValueError(
                    f'Dataset.{name} has {arr.shape[1]} joints, expected {n_joints}')
            if not np.all(np.isfinite(arr)):
                raise ValueError(f'Dataset.{name} contains NaN or inf')
            object.__setattr__(self, name, arr)
        if not np.all(np.isfinite(t)):
            raise ValueError('Dataset.t contains NaN or inf')
        steps = np.diff(t)
        if np.any(steps <= 0.0):
            raise ValueError('Dataset.t must be strictly increasing')
        if not np.allclose(steps, steps[0], rtol=1e-6, atol=1e-9):
            raise ValueError('Dataset.t must be uniformly sampled (resample first)')
        names = tuple(self.joint_names) or tuple(f'joint{i + 1}' for i in range(n_joints))
        if len(names) != n_joints:
            raise ValueError(f'{len(names)} joint names for {n_joints} joints')
        object.__setattr__(self, 'joint_names', names)

    @property
    def n_joints(self) -> int:
        """Return the number of joints n."""
        return self.theta.shape[1]

    @property
    def n_samples(self) -> int:
        """Return the number of samples N."""
        return self.t.size

    @property
    def dt(self) -> float:
        """Return the sampling interval in seconds."""
        return float((self.t[-1] - self.t[0]) / (self.t.size - 1))

    @property
    def duration(self) -> float:
        """Return the time spanned, ``t[-1] - t[0]``."""
        return float(self.t[-1] - self.t[0])

    @property
    def state(self) -> np.ndarray:
        """Return the measured states x = [θ, θ̇], shape (N, 2n)."""
        return np.hstack([self.theta, self.theta_dot])

    def slice(self, start: int, stop: int) -> 'Dataset':  # noqa: A003
        """Return samples ``start:stop`` as a new dataset (at least 2 samples)."""
        def cut(a):
            return None if a is None else a[start:stop]
        return replace(self, t=self.t[start:stop], theta=cut(self.theta),
                       theta_dot=cut(self.theta_dot), tau=cut(self.tau),
                       theta_d=cut(self.theta_d), theta_d_dot=cut(self.theta_d_dot))

    def split_time(self, t_split: float) -> Tuple['Dataset', 'Dataset']:
        """Split into the samples before ``t_split`` and those from it on."""
        k = int(np.searchsorted(self.t, t_split))
        return self.slice(0, k), self.slice(k, self.n_samples)

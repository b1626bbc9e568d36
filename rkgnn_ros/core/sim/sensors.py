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
What an arm's driver publishes: encoder noise, how it gets θ̇, and which fields it fills.

Real drivers differ in what reaches ``joint_states``:

- ``velocity='sensor'``: a measured θ̇ (tachometer, or a fine velocity estimate in the
  drive) with white noise ``theta_dot_std``;
- ``velocity='difference'``: the backward difference of consecutive published (noisy)
  positions, (θ_k − θ_{k−1}) / dt, what a driver without velocity sensing computes: its
  noise is about √2 ``theta_std`` / dt and it lags by dt / 2;
- ``velocity='filtered'``: that difference through a first-order low-pass at
  ``velocity_cutoff`` Hz (exponential smoothing, the usual driver filter): less noise,
  more lag (about 1 / (2π f_c) at low frequencies);
- ``velocity='none'``: no velocity at all (NaN here; the node publishes an empty field);
- ``effort=False``: no torque (no current sensing, or not published).

Everything is causal, one sample after the other, as a driver runs: :class:`SensorStream`
measures sample by sample (the ``sim_arm`` node) and :meth:`SensorModel.apply` runs the
same stream over recorded arrays (offline data), so both give identical numbers for one
seed. The plant and the servo always see the true state; only what is published is noisy.
"""

from dataclasses import dataclass
import math
from typing import Optional, Tuple

import numpy as np

#: Where the published θ̇ comes from (see the module docstring).
VELOCITY_SOURCES = ('sensor', 'difference', 'filtered', 'none')


@dataclass(frozen=True)
class SensorModel:
    """
    The measurement chain of an arm's driver.

    Attributes
    ----------
    theta_std : float
        White encoder noise on θ (rad).
    theta_dot_std : float
        White noise on a sensed θ̇ (rad/s); only with ``velocity='sensor'``.
    velocity : {'sensor', 'difference', 'filtered', 'none'}
        How the published θ̇ is obtained.
    velocity_cutoff : float
        Cut-off (Hz) of the low-pass of ``velocity='filtered'``.
    effort : bool
        Whether the applied torque is published.
    tau_std : float
        White noise on the published torque (N m).

    """

    theta_std: float = 0.0
    theta_dot_std: float = 0.0
    velocity: str = 'sensor'
    velocity_cutoff: float = 20.0
    effort: bool = True
    tau_std: float = 0.0

    def __post_init__(self):
        for name in ('theta_std', 'theta_dot_std', 'tau_std'):
            value = float(getattr(self, name))
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f'SensorModel.{name} must be finite and >= 0, got {value}')
            object.__setattr__(self, name, value)
        if self.velocity not in VELOCITY_SOURCES:
            raise ValueError(f'SensorModel.velocity must be one of {VELOCITY_SOURCES}, '
                             f'got {self.velocity!r}')
        if self.velocity != 'sensor' and self.theta_dot_std > 0.0:
            raise ValueError(f'SensorModel.theta_dot_std must be 0 with velocity '
                             f'{self.velocity!r} (only a sensed velocity has its own noise)')
        cutoff = float(self.velocity_cutoff)
        if not (math.isfinite(cutoff) and cutoff > 0.0):
            raise ValueError(f'SensorModel.velocity_cutoff must be positive, got {cutoff}')
        object.__setattr__(self, 'velocity_cutoff', cutoff)
        object.__setattr__(self, 'effort', bool(self.effort))

    @classmethod
    def exact(cls) -> 'SensorModel':
        """Return exact encoders, sensed velocity and torque (the paper's data)."""
        return cls()

    @classmethod
    def differenced(cls, theta_std: float = 1e-4) -> 'SensorModel':
        """Return noisy encoders with θ̇ by backward differences (a common cheap driver)."""
        return cls(theta_std=theta_std, velocity='difference')

    def stream(self, dt: float, rng: Optional[np.random.Generator] = None) -> 'SensorStream':
        """Return a sample-by-sample measurement at interval ``dt`` (s)."""
        return SensorStream(self, dt, rng)

    def apply(self, theta: np.ndarray, theta_dot: np.ndarray, tau: Optional[np.ndarray],
              dt: float, rng: Optional[np.random.Generator] = None):
        """
        Measure recorded true samples, as the stream would one after the other.

        Parameters
        ----------
        theta, theta_dot : ndarray, shape (N, n)
            True joint angles and velocities at interval ``dt``.
        tau : ndarray, shape (N, n) or None
            Applied torques.
        dt : float
            Sampling interval (s).
        rng : numpy.random.Generator, optional
            Source of the noise.

        Returns
        -------
        theta, theta_dot, tau : ndarray, shape (N, n)
            Published values; a field the driver does not publish is all NaN (``tau`` is
            None when given None).

        """
        theta = np.asarray(theta, dtype=float)
        stream = self.stream(dt, rng)
        zeros = np.zeros(theta.shape[1])
        out = [np.empty_like(theta) for _ in range(3)]
        for k in range(theta.shape[0]):
            values = stream.measure(theta[k], theta_dot[k], zeros if tau is None else tau[k])
            for arr, value in zip(out, values):
                arr[k] = value
        return out[0], out[1], None if tau is None else out[2]


class SensorStream:
    """
    One driver's measurement chain, sample by sample (it keeps the previous sample).

    Parameters
    ----------
    model : SensorModel
        What the driver does.
    dt : float
        Interval between samples (s).
    rng : numpy.random.Generator, optional
        Source of the noise; three (n,) normal vectors are drawn per sample whatever the
        settings, so changing a noise level at run time never shifts the random stream.

    """

    def __init__(self, model: SensorModel, dt: float,
                 rng: Optional[np.random.Generator] = None):
        if not (math.isfinite(dt) and dt > 0.0):
            raise ValueError(f'dt must be positive, got {dt}')
        self.model = model
        self.dt = float(dt)
        self.rng = rng if rng is not None else np.random.default_rng()
        self.theta_std = model.theta_std
        self.theta_dot_std = model.theta_dot_std
        #: weight of the new difference in the exponential smoothing of 'filtered'
        self.alpha = 1.0 - math.exp(-2.0 * math.pi * model.velocity_cutoff * self.dt)
        self._last_theta: Optional[np.ndarray] = None
        self._velocity: Optional[np.ndarray] = None

    def set_noise(self, theta_std: Optional[float] = None,
                  theta_dot_std: Optional[float] = None) -> None:
        """Change the noise levels from the next sample on (finite, >= 0)."""
        for name, value in (('theta_std', theta_std), ('theta_dot_std', theta_dot_std)):
            if value is None:
                continue
            value = float(value)
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f'{name} must be finite and >= 0, got {value}')
            setattr(self, name, value)

    def measure(self, theta, theta_dot, tau) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """
        Return the published θ, θ̇ and τ of one true sample, each (n,).

        The first sample's differenced velocity is 0 (no previous position yet); fields the
        driver does not publish are NaN.
        """
        theta = np.asarray(theta, dtype=float)
        noise = self.rng.standard_normal((3, theta.size))
        measured = theta + self.theta_std * noise[0]
        kind = self.model.velocity
        if kind == 'sensor':
            velocity = np.asarray(theta_dot, dtype=float) + self.theta_dot_std * noise[1]
        elif kind == 'none':
            velocity = np.full(theta.size, np.nan)
        else:
            if self._last_theta is None:
                difference = np.zeros(theta.size)
            else:
                difference = (measured - self._last_theta) / self.dt
            if kind == 'difference' or self._velocity is None:
                velocity = difference
            else:
                velocity = self._velocity + self.alpha * (difference - self._velocity)
            self._velocity = velocity
        self._last_theta = measured
        if self.model.effort:
            effort = np.asarray(tau, dtype=float) + self.model.tau_std * noise[2]
        else:
            effort = np.full(theta.size, np.nan)
        return measured, velocity.copy(), effort

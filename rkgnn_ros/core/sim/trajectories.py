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
Desired joint trajectories θd(t), θ̇d(t) for the PD servo.

Every reference evaluates vectorised: a scalar time gives arrays of shape (n,), a 1-D array
of T times gives (T, n). Derivatives are exact (analytic or of the interpolant), never
finite differences of the evaluated positions.
"""

from abc import ABC, abstractmethod
import math
from typing import Tuple

import numpy as np
from scipy.interpolate import CubicHermiteSpline

from ..data import finite_array

#: The hanging pose of the vertical-plane arm: joint 1 at -π/2 rad, the others straight.
HANGING_SHOULDER = -0.5 * np.pi


def hanging_pose(n_joints: int) -> np.ndarray:
    """Return the hanging pose (-π/2, 0, ..., 0), shape (n,)."""
    if int(n_joints) != n_joints or n_joints < 1:
        raise ValueError(f'n_joints must be a positive integer, got {n_joints}')
    pose = np.zeros(int(n_joints))
    pose[0] = HANGING_SHOULDER
    return pose


def _per_joint(name: str, value, n: int) -> np.ndarray:
    """Return a scalar or (n,) value as a finite (n,) array."""
    arr = finite_array(name, value)
    if arr.ndim == 0:
        return np.full(n, float(arr))
    if arr.shape != (n,):
        raise ValueError(f'{name} must be a scalar or have shape ({n},), got {arr.shape}')
    return arr


class Reference(ABC):
    """
    A desired joint trajectory.

    Subclasses implement :attr:`n_joints` and ``_evaluate(t)`` for a 1-D array of times;
    :meth:`evaluate` validates the times and restores a scalar's shape.
    """

    @property
    @abstractmethod
    def n_joints(self) -> int:
        """Count of joints, n."""

    @abstractmethod
    def _evaluate(self, t: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Return θd and θ̇d, each shape (T, n), for finite times ``t`` of shape (T,)."""

    def evaluate(self, t) -> Tuple[np.ndarray, np.ndarray]:
        """
        Return the desired angles and velocities at time(s) ``t``.

        Parameters
        ----------
        t : float or array_like, shape (T,)
            Time(s) in seconds.

        Returns
        -------
        theta_d, theta_d_dot : ndarray, shape (n,) for a scalar ``t``, (T, n) for an array

        """
        if isinstance(t, float):
            # the simulator's path: one time per call
            if not math.isfinite(t):
                raise ValueError('t must be finite (no NaN or inf)')
            theta_d, theta_d_dot = self._evaluate(np.array([t]))
            return theta_d[0], theta_d_dot[0]
        t = np.asarray(t, dtype=float)
        if t.ndim > 1:
            raise ValueError(f't must be a scalar or 1-D array, got shape {t.shape}')
        if not np.all(np.isfinite(t)):
            raise ValueError('t must be finite (no NaN or inf)')
        theta_d, theta_d_dot = self._evaluate(np.atleast_1d(t))
        if t.ndim == 0:
            return theta_d[0], theta_d_dot[0]
        return theta_d, theta_d_dot

    __call__ = evaluate


class SumOfSines(Reference):
    """
    θd_i(t) = offset_i + Σ_k A_ik sin(2π f_ik t + φ_ik), with its exact derivative.

    Parameters
    ----------
    offsets : array_like, shape (n,)
        Centre of each joint's motion (rad).
    amplitudes : array_like, shape (n, K)
        Amplitudes A (rad).
    frequencies_hz : array_like, shape (n, K)
        Frequencies f (Hz).
    phases : array_like, shape (n, K)
        Phases φ (rad).

    """

    def __init__(self, offsets, amplitudes, frequencies_hz, phases):
        self.offsets = finite_array('offsets', offsets, ndim=1)
        n = self.offsets.size
        if n < 1:
            raise ValueError('offsets must have at least one joint')
        self.amplitudes = finite_array('amplitudes', amplitudes, ndim=2)
        if self.amplitudes.shape[0] != n:
            raise ValueError(
                f'amplitudes must have shape ({n}, K), got {self.amplitudes.shape}')
        shape = self.amplitudes.shape
        self.frequencies_hz = finite_array('frequencies_hz', frequencies_hz, shape=shape)
        self.phases = finite_array('phases', phases, shape=shape)
        self._omega = 2.0 * np.pi * self.frequencies_hz
        self._rate_amplitudes = self.amplitudes * self._omega

    @classmethod
    def random(cls, n_joints: int, rng: np.random.Generator, n_terms: int = 3,
               amplitude: float = 0.5, max_frequency_hz: float = 0.8,
               min_frequency_hz: float = 0.1, offsets=None) -> 'SumOfSines':
        """
        Draw a random sum of sines (e.g. a held-out validation reference).

        Each joint gets ``n_terms`` frequencies uniform in [min, max] Hz, phases uniform in
        [0, 2π) and amplitudes whose sum is ``amplitude`` (so |θd - offset| <= amplitude).

        Parameters
        ----------
        n_joints : int
            Number of joints n.
        rng : numpy.random.Generator
            Source of randomness (kept by the caller; never a global seed).
        n_terms : int
            Sines per joint, K.
        amplitude : float
            Total amplitude per joint (rad).
        max_frequency_hz, min_frequency_hz : float
            Frequency band (Hz).
        offsets : array_like, shape (n,), optional
            Centre pose; default the hanging pose.

        """
        if n_terms < 1:
            raise ValueError(f'n_terms must be >= 1, got {n_terms}')
        if not 0.0 < min_frequency_hz <= max_frequency_hz:
            raise ValueError('need 0 < min_frequency_hz <= max_frequency_hz, got '
                             f'{min_frequency_hz}, {max_frequency_hz}')
        if not amplitude >= 0.0:
            raise ValueError(f'amplitude must be non-negative, got {amplitude}')
        offsets = hanging_pose(n_joints) if offsets is None else offsets
        shape = (int(n_joints), int(n_terms))
        weights = rng.uniform(0.3, 1.0, size=shape)
        amplitudes = amplitude * weights / weights.sum(axis=1, keepdims=True)
        frequencies = rng.uniform(min_frequency_hz, max_frequency_hz, size=shape)
        phases = rng.uniform(0.0, 2.0 * np.pi, size=shape)
        return cls(offsets, amplitudes, frequencies, phases)

    @property
    def n_joints(self) -> int:
        """Count of joints, n."""
        return self.offsets.size

    def _evaluate(self, t):
        arg = self._omega * t[:, None, None] + self.phases       # (T, n, K)
        theta_d = self.offsets + np.sum(self.amplitudes * np.sin(arg), axis=-1)
        theta_d_dot = np.sum(self._rate_amplitudes * np.cos(arg), axis=-1)
        return theta_d, theta_d_dot


class Chirp(Reference):
    """
    Linear chirp θd_i(t) = offset_i + A_i sin(ψ(t)), sweeping f0 to f1 over ``duration``.

    The instantaneous frequency is f0 for t < 0, rises linearly to f1 at t = ``duration``
    and then stays at f1 (the final sweep frequency is held, with a continuous phase), so
    θd and θ̇d are continuous everywhere::

        ψ(t) = 2π f0 t                                  t < 0
        ψ(t) = 2π (f0 t + (f1 - f0) t² / (2 duration))   0 <= t <= duration
        ψ(t) = ψ(duration) + 2π f1 (t - duration)        t > duration

    Parameters
    ----------
    offsets : array_like, shape (n,)
    amplitudes : array_like, shape (n,)
    f0_hz, f1_hz : float or array_like, shape (n,)
        Start and end frequencies (Hz), non-negative.
    duration : float
        Sweep time (s), positive.

    """

    def __init__(self, offsets, amplitudes, f0_hz, f1_hz, duration):
        self.offsets = finite_array('offsets', offsets, ndim=1)
        n = self.offsets.size
        if n < 1:
            raise ValueError('offsets must have at least one joint')
        self.amplitudes = finite_array('amplitudes', amplitudes, shape=(n,))
        self.f0_hz = _per_joint('f0_hz', f0_hz, n)
        self.f1_hz = _per_joint('f1_hz', f1_hz, n)
        if np.any(self.f0_hz < 0.0) or np.any(self.f1_hz < 0.0):
            raise ValueError('f0_hz and f1_hz must be non-negative')
        self.duration = float(finite_array('duration', duration, shape=()))
        if self.duration <= 0.0:
            raise ValueError(f'duration must be positive, got {duration}')

    @property
    def n_joints(self) -> int:
        """Count of joints, n."""
        return self.offsets.size

    def _evaluate(self, t):
        f0, f1, span = self.f0_hz, self.f1_hz, self.duration
        tc = np.clip(t, 0.0, span)[:, None]                      # (T, 1)
        before = np.minimum(t, 0.0)[:, None]
        after = np.maximum(t - span, 0.0)[:, None]
        rate = (f1 - f0) / span
        psi = 2.0 * np.pi * (f0 * before + f0 * tc + 0.5 * rate * tc ** 2 + f1 * after)
        freq = f0 + rate * tc                                     # (T, n), held outside
        theta_d = self.offsets + self.amplitudes * np.sin(psi)
        theta_d_dot = self.amplitudes * 2.0 * np.pi * freq * np.cos(psi)
        return theta_d, theta_d_dot


class SampledReference(Reference):
    """
    A reference given by samples, interpolated by cubic Hermite splines.

    The interpolant passes exactly through the samples with the given velocities (or, when
    ``theta_d_dot`` is None, velocities from second-order finite differences of
    ``theta_d``). Outside ``[t[0], t[-1]]`` the end position is held and the velocity is 0.

    Parameters
    ----------
    t : array_like, shape (N,)
        Strictly increasing sample times, N >= 2.
    theta_d : array_like, shape (N, n)
    theta_d_dot : array_like, shape (N, n), optional

    """

    def __init__(self, t, theta_d, theta_d_dot=None):
        t = finite_array('t', t, ndim=1)
        if t.size < 2:
            raise ValueError(f't must have at least 2 samples, got {t.size}')
        if np.any(np.diff(t) <= 0.0):
            raise ValueError('t must be strictly increasing')
        theta_d = finite_array('theta_d', theta_d, ndim=2)
        if theta_d.shape[0] != t.size or theta_d.shape[1] < 1:
            raise ValueError(
                f'theta_d must have shape (N={t.size}, n), got {theta_d.shape}')
        if theta_d_dot is None:
            edge = 2 if t.size >= 3 else 1
            theta_d_dot = np.gradient(theta_d, t, axis=0, edge_order=edge)
        else:
            theta_d_dot = finite_array('theta_d_dot', theta_d_dot, shape=theta_d.shape)
        self.t = t
        self.theta_d = theta_d
        self.theta_d_dot = theta_d_dot
        self._spline = CubicHermiteSpline(t, theta_d, theta_d_dot, axis=0, extrapolate=False)
        self._velocity = self._spline.derivative()

    @property
    def n_joints(self) -> int:
        """Count of joints, n."""
        return self.theta_d.shape[1]

    def _evaluate(self, t):
        tc = np.clip(t, self.t[0], self.t[-1])
        theta_d = self._spline(tc)
        theta_d_dot = self._velocity(tc)
        # at a knot return the sample itself (the polynomial is exact only up to rounding)
        knot = np.minimum(np.searchsorted(self.t, tc), self.t.size - 1)
        hit = self.t[knot] == tc
        theta_d[hit] = self.theta_d[knot[hit]]
        theta_d_dot[hit] = self.theta_d_dot[knot[hit]]
        outside = (t < self.t[0]) | (t > self.t[-1])
        theta_d_dot[outside] = 0.0
        return theta_d, theta_d_dot


class Switched(Reference):
    """
    One reference until ``at``, another from ``at + blend``, joined smoothly.

    Between the two, θd = (1 - w) θd₁ + w θd₂ with w = 3u² - 2u³, u = (t - at) / blend, and
    θ̇d its exact derivative (w' (θd₂ - θd₁) included), so θd and θ̇d are continuous: the
    servo sees no step. A task change of a real arm (a new pose, other frequencies).

    Parameters
    ----------
    first, second : Reference
        Before and after the switch; the same count of joints.
    at : float
        Start of the switch (s).
    blend : float
        Length of the join (s), > 0.

    """

    def __init__(self, first: Reference, second: Reference, at: float, blend: float = 2.0):
        if first.n_joints != second.n_joints:
            raise ValueError(f'the references have {first.n_joints} and {second.n_joints} '
                             'joints')
        self.first, self.second = first, second
        self.at = float(finite_array('at', at))
        self.blend = float(finite_array('blend', blend))
        if not self.blend > 0.0:
            raise ValueError(f'blend must be > 0, got {blend}')

    @property
    def n_joints(self) -> int:
        """Count of joints, n."""
        return self.first.n_joints

    def _evaluate(self, t):
        u = np.clip((t - self.at) / self.blend, 0.0, 1.0)[:, None]       # (T, 1)
        w = u * u * (3.0 - 2.0 * u)
        w_dot = 6.0 * u * (1.0 - u) / self.blend
        theta_1, theta_dot_1 = self.first._evaluate(t)
        theta_2, theta_dot_2 = self.second._evaluate(t)
        theta_d = (1.0 - w) * theta_1 + w * theta_2
        theta_d_dot = (1.0 - w) * theta_dot_1 + w * theta_dot_2 + w_dot * (theta_2 - theta_1)
        return theta_d, theta_d_dot


#: Sum-of-sines table of :func:`paper_reference` for up to three joints: per joint the
#: amplitudes (rad), frequencies (Hz) and phases (rad) of three sines.
_PAPER_AMPLITUDES = np.array([[0.30, 0.15, 0.08],
                              [0.35, 0.15, 0.06],
                              [0.40, 0.12, 0.06]])
_PAPER_FREQUENCIES = np.array([[0.11, 0.27, 0.53],
                               [0.17, 0.41, 0.71],
                               [0.13, 0.37, 0.79]])
_PAPER_PHASES = np.array([[0.0, 1.1, 2.3],
                          [0.7, 2.9, 4.1],
                          [1.9, 0.4, 5.2]])


def paper_reference(n_joints: int = 3) -> SumOfSines:
    """
    Return the default (fitting) reference: fixed sums of sines about the hanging pose.

    The paper does not publish its desired trajectory. This one swings every joint about
    the hanging pose (-π/2, 0, ...), since the arm moves in a vertical plane and the PD has
    no gravity compensation. Each joint has three sines between 0.11 and 0.79 Hz with total
    amplitude 0.53 to 0.58 rad. Joints beyond the third reuse the table cyclically with
    shifted phases. Deterministic.
    """
    n = int(n_joints)
    if n != n_joints or n < 1:
        raise ValueError(f'n_joints must be a positive integer, got {n_joints}')
    rows = np.arange(n) % 3
    shift = 0.7 * (np.arange(n) // 3)[:, None]
    return SumOfSines(hanging_pose(n), _PAPER_AMPLITUDES[rows], _PAPER_FREQUENCIES[rows],
                      _PAPER_PHASES[rows] + shift)


def heldout_reference(n_joints: int = 3, seed: int = 1) -> SumOfSines:
    """
    Return a validation reference unlike :func:`paper_reference`.

    Four random sines per joint (``SumOfSines.random`` with ``default_rng(seed)``), between
    0.15 and 0.7 Hz, total amplitude 0.45 rad, about the hanging pose.
    """
    rng = np.random.default_rng(seed)
    return SumOfSines.random(n_joints, rng, n_terms=4, amplitude=0.45,
                             max_frequency_hz=0.7, min_frequency_hz=0.15)

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
Joint servos as real arms run them: PD, gravity compensation, PID, feed-forward, limits.

The paper's servo is a pure PD, eq. (9). An industrial servo adds a model-based gravity
torque Ĝ(θ) (on the measured or on the desired position), often an integral term, an
additive feed-forward torque τ_ff(t) sent with the plan (what a servo with an effort
interface takes), and its drive saturates. A :class:`Servo` is all of these in one law,
per joint::

    τ_raw = Kp e + Kd ė + I + Ĝ(θ or θd) + τ_ff(t),   e = θd − θ,   ė = θ̇d − θ̇
    τ     = clip(τ_raw, −τ_max, τ_max)        (the applied torque, what a driver reports)
    İ     = Ki e + (τ − τ_raw) / T_t          (back-calculation anti-windup)

The integral term I is kept in torque units (N m): it is a state of the closed loop, so a
continuous simulation integrates it beside [θ, θ̇], and a digital servo advances it once
per tick. Back-calculation (Åström and Hägglund) bleeds the integral while the drive
saturates, with the tracking time constant T_t (``windup_time``), instead of letting it
grow without bound; it changes nothing while the torque is inside its limits.

Ĝ is the simulated arm's own gravity vector (:meth:`PlanarArm.gravity_terms`), i.e. exact
compensation, the best case a servo vendor can reach. With ``Ki = 0``, no limit and no
compensation a :class:`Servo` is the paper's PD (:class:`PDController`).

The feed-forward reaches a servo as points of a trajectory (a JointTrajectory with
``effort`` filled). :class:`FeedforwardTrack` holds one such trajectory and evaluates
τ_ff at the servo's own time: linear between points, as joint_trajectory_controller
interpolates efforts, and zero before the first point and after the last, so a plan that
has ended or not yet begun leaves the PD alone (joint_trajectory_controller would hold the
last effort; a feed-forward computed for a motion that is over is not a safe torque to
hold). A malformed trajectory (NaN, an effort beyond the drive's limit, times not
increasing) is refused whole when the track is built, with the reason, and the servo runs
without it.

:func:`servo_torque_into` and :func:`servo_integral_rate_into` are the compiled twins used
inside compiled simulation steps; they take the record :class:`ServoConstants` from
:meth:`Servo.constants` and agree with the numpy methods to rounding.
"""

import math
from typing import NamedTuple, Optional, Tuple, Union

from numba import njit
import numpy as np

from .plant import PlanarArm
from ..servo_law import compiled_pd_torque, pd_torque

#: Where a gravity-compensating servo evaluates Ĝ: nowhere, at the measured θ, at θd.
GRAVITY_MODES = ('none', 'measured', 'desired')

#: Default back-calculation time constant T_t (s).
DEFAULT_WINDUP_TIME = 0.1

ArrayLike = Union[float, np.ndarray]


class ServoConstants(NamedTuple):
    """
    Constants of the compiled servo functions (a record numba accepts as one argument).

    Attributes
    ----------
    kp, kd, ki : ndarray, shape (n,)
        Gains (N m/rad, N m s/rad, N m/(rad s)).
    tau_limit : ndarray, shape (n,)
        Saturation levels (N m); ``inf`` where there is none.
    windup_gain : ndarray, shape (n,)
        1 / T_t where Ki > 0, else 0 (the integral then stays 0).
    gh : ndarray, shape (n,)
        The arm's gravity moments g h_i (:meth:`PlanarArm.kernel_constants`), zeros
        without gravity compensation.
    on_desired : bool
        Ĝ is evaluated at θd instead of θ.

    """

    kp: np.ndarray
    kd: np.ndarray
    ki: np.ndarray
    tau_limit: np.ndarray
    windup_gain: np.ndarray
    gh: np.ndarray
    on_desired: bool


def _joint_vector(name: str, value, n: int, *, allow_inf: bool = False) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 0:
        arr = np.full(n, float(arr))
    if arr.shape != (n,):
        raise ValueError(f'{name} must be a scalar or have {n} entries, got shape {arr.shape}')
    finite = np.isfinite(arr) | (allow_inf & (arr == np.inf))
    if not np.all(finite) or np.any(arr < 0.0):
        raise ValueError(f'{name} must be finite and >= 0, got {arr.tolist()}')
    return arr.copy()


class Servo:
    """
    A joint servo: PD, optional gravity compensation, optional integral, torque limits.

    Parameters
    ----------
    kp, kd : array_like, shape (n,)
        Diagonal proportional and derivative gains, each >= 0.
    ki : array_like, shape (n,) or scalar
        Integral gains (N m/(rad s)); 0 (default) means no integral term.
    tau_limit : array_like, shape (n,) or scalar, optional
        Saturation |τ_i| <= tau_limit_i (N m), each > 0 or ``inf``. None: no limit.
    gravity : {'none', 'measured', 'desired'}
        Gravity compensation Ĝ(θ) or Ĝ(θd) from ``arm``'s own model.
    arm : PlanarArm or UrdfArm, optional
        The arm whose gravity is compensated; required unless ``gravity == 'none'``.
    windup_time : float
        Back-calculation time constant T_t (s), positive.

    """

    def __init__(self, kp, kd, ki=0.0, tau_limit=None, gravity: str = 'none',
                 arm: Optional[PlanarArm] = None, windup_time: float = DEFAULT_WINDUP_TIME):
        kp_arr = np.asarray(kp, dtype=float)
        if kp_arr.ndim != 1 or kp_arr.size < 1:
            raise ValueError(f'kp must be a 1-D array of the n gains, got shape {kp_arr.shape}')
        n = kp_arr.size
        self.kp = _joint_vector('kp', kp_arr, n)
        self.kd = _joint_vector('kd', kd, n)
        self.ki = _joint_vector('ki', ki, n)
        limit = np.inf if tau_limit is None else tau_limit
        self.tau_limit = _joint_vector('tau_limit', limit, n, allow_inf=True)
        if np.any(self.tau_limit <= 0.0):
            raise ValueError(f'tau_limit must be > 0, got {self.tau_limit.tolist()}')
        if gravity not in GRAVITY_MODES:
            raise ValueError(f'gravity must be one of {GRAVITY_MODES}, got {gravity!r}')
        if gravity != 'none':
            if not hasattr(arm, 'gravity_terms'):
                raise ValueError(f"gravity compensation {gravity!r} needs the arm's model "
                                 '(arm=PlanarArm or UrdfArm)')
            if arm.n_joints != n:
                raise ValueError(f'the arm has {arm.n_joints} joints, the gains {n}')
        self.gravity = gravity
        self.arm = arm if gravity != 'none' else None
        windup_time = float(windup_time)
        if not (math.isfinite(windup_time) and windup_time > 0.0):
            raise ValueError(f'windup_time must be positive, got {windup_time}')
        self.windup_time = windup_time

    @classmethod
    def paper(cls) -> 'Servo':
        """Return the paper's PD, Kp = (32.84, 42.05, 42.31), Kd = (42.44, 0.19, 4.86)."""
        return cls(np.array([32.84, 42.05, 42.31]), np.array([42.44, 0.19, 4.86]))

    @property
    def n_joints(self) -> int:
        """Count of joints, n."""
        return self.kp.size

    @property
    def has_integral(self) -> bool:
        """Return whether any joint has an integral term (the loop then has n more states)."""
        return bool(np.any(self.ki > 0.0))

    @property
    def limited(self) -> bool:
        """Return whether any joint saturates."""
        return bool(np.any(np.isfinite(self.tau_limit)))

    def describe(self) -> str:
        """Return a short description for logs, e.g. 'PID + gravity compensation (θd)'."""
        kind = 'PID' if self.has_integral else 'PD'
        if self.gravity != 'none':
            kind += f' + gravity compensation ({self.gravity} position)'
        if self.limited:
            kind += ', torque-limited'
        return kind

    def gravity_torque(self, theta: ArrayLike, theta_d: ArrayLike) -> np.ndarray:
        """Return Ĝ at θ or θd (zeros without compensation), shape (..., n)."""
        theta = np.asarray(theta, dtype=float)
        if self.gravity == 'none':
            return np.zeros(np.broadcast_shapes(theta.shape, np.shape(theta_d)))
        at = theta if self.gravity == 'measured' else np.asarray(theta_d, dtype=float)
        return self.arm.gravity_terms(at)

    def torques(self, theta: ArrayLike, theta_dot: ArrayLike, theta_d: ArrayLike,
                theta_d_dot: ArrayLike, integral: Optional[ArrayLike] = None,
                feedforward: Optional[ArrayLike] = None) -> Tuple[np.ndarray, np.ndarray]:
        """
        Return the unsaturated and the applied torque.

        Parameters
        ----------
        theta, theta_dot, theta_d, theta_d_dot : array_like, shape (..., n)
            Measured and desired joint angles and velocities.
        integral : array_like, shape (..., n), optional
            The integral term I (N m); zero when None.
        feedforward : array_like, shape (..., n), optional
            The feed-forward torque τ_ff (N m) at this instant, added before saturation
            (e.g. :meth:`FeedforwardTrack.evaluate` at the servo's time); zero when None.

        Returns
        -------
        raw, applied : ndarray, shape (..., n)

        """
        theta = np.asarray(theta, dtype=float)
        theta_d = np.asarray(theta_d, dtype=float)
        raw = (pd_torque(self.kp, self.kd, theta_d - theta,
                         np.asarray(theta_d_dot, dtype=float) - theta_dot)
               + self.gravity_torque(theta, theta_d))
        if integral is not None:
            raw = raw + integral
        if feedforward is not None:
            raw = raw + np.asarray(feedforward, dtype=float)
        return raw, np.clip(raw, -self.tau_limit, self.tau_limit)

    def torque(self, theta: ArrayLike, theta_dot: ArrayLike, theta_d: ArrayLike,
               theta_d_dot: ArrayLike, integral: Optional[ArrayLike] = None,
               feedforward: Optional[ArrayLike] = None) -> np.ndarray:
        """Return the applied (saturated) torque, shape (..., n); see :meth:`torques`."""
        return self.torques(theta, theta_dot, theta_d, theta_d_dot, integral, feedforward)[1]

    __call__ = torque

    def integral_rate(self, theta: ArrayLike, theta_d: ArrayLike, raw: ArrayLike,
                      applied: ArrayLike) -> np.ndarray:
        """Return İ = Ki e + (τ − τ_raw) / T_t (0 where Ki = 0), shape (..., n)."""
        e = np.asarray(theta_d, dtype=float) - np.asarray(theta, dtype=float)
        rate = self.ki * e + (np.asarray(applied) - np.asarray(raw)) / self.windup_time
        return np.where(self.ki > 0.0, rate, 0.0)

    def constants(self) -> ServoConstants:
        """Return the record of the compiled functions (fresh C-contiguous copies)."""
        gh = (np.zeros(self.n_joints) if self.arm is None
              else np.array(self.arm.kernel_constants().gh, dtype=float, order='C'))
        windup = np.where(self.ki > 0.0, 1.0 / self.windup_time, 0.0)
        return ServoConstants(
            kp=np.ascontiguousarray(self.kp), kd=np.ascontiguousarray(self.kd),
            ki=np.ascontiguousarray(self.ki), tau_limit=np.ascontiguousarray(self.tau_limit),
            windup_gain=np.ascontiguousarray(windup), gh=gh,
            on_desired=self.gravity == 'desired')


class FeedforwardTrack:
    """
    A feed-forward torque trajectory as a servo with an effort interface applies it.

    Parameters
    ----------
    t : array_like, shape (K,)
        Times of the points on the servo's clock (s): finite, strictly increasing, K >= 2.
    effort : array_like, shape (K, n)
        The feed-forward torque at each point (N m), finite.
    tau_limit : array_like, shape (n,) or scalar, optional
        The drive's limits (N m); a point beyond them makes the track malformed (a plan that
        asks for more than the drive has is not applied, not even in part). None: no check.

    Raises
    ------
    ValueError
        If the track is malformed; the message says how. The servo then runs without it.

    """

    def __init__(self, t, effort, tau_limit=None):
        try:
            t = np.asarray(t, dtype=float)
            effort = np.asarray(effort, dtype=float)
        except (TypeError, ValueError) as exc:
            raise ValueError(f'feed-forward: not numeric ({exc})') from None
        if t.ndim != 1 or t.size < 2:
            raise ValueError(f'feed-forward: needs at least 2 points, got times of shape '
                             f'{t.shape}')
        if effort.ndim != 2 or effort.shape[0] != t.size or effort.shape[1] < 1:
            raise ValueError(f'feed-forward: efforts must have shape ({t.size}, n), got '
                             f'{effort.shape}')
        if not np.all(np.isfinite(t)):
            raise ValueError('feed-forward: a point time is NaN or inf')
        if np.any(np.diff(t) <= 0.0):
            raise ValueError('feed-forward: point times must be strictly increasing')
        if not np.all(np.isfinite(effort)):
            bad = sorted(set(np.nonzero(~np.isfinite(effort))[1].tolist()))
            raise ValueError(f'feed-forward: NaN or inf effort for joint(s) {bad}')
        if tau_limit is not None:
            limit = _joint_vector('tau_limit', tau_limit, effort.shape[1], allow_inf=True)
            over = np.abs(effort) > limit
            if np.any(over):
                joint = int(np.nonzero(over)[1][0])
                raise ValueError(
                    f'feed-forward: effort {effort[over][0]:.6g} N m for joint {joint} beyond '
                    f'its limit {limit[joint]:.6g} N m')
        self.t = t
        self.effort = effort

    @property
    def n_joints(self) -> int:
        """Count of joints, n."""
        return self.effort.shape[1]

    @property
    def start(self) -> float:
        """Return the time of the first point (s)."""
        return float(self.t[0])

    @property
    def end(self) -> float:
        """Return the time of the last point (s); later, the track is stale."""
        return float(self.t[-1])

    def covers(self, t: ArrayLike) -> Union[bool, np.ndarray]:
        """Return whether time(s) ``t`` lie within [start, end]."""
        t = np.asarray(t, dtype=float)
        inside = (t >= self.t[0]) & (t <= self.t[-1])
        return bool(inside) if inside.ndim == 0 else inside

    def evaluate(self, t: ArrayLike) -> np.ndarray:
        """
        Return τ_ff at time(s) ``t``: linear between points, zero outside [start, end].

        Parameters
        ----------
        t : float or array_like, shape (T,)
            The servo's time(s) (s), finite.

        Returns
        -------
        ndarray, shape (n,) for a scalar ``t``, (T, n) for an array

        """
        tq = np.asarray(t, dtype=float)
        if tq.ndim > 1 or not np.all(np.isfinite(tq)):
            raise ValueError(f't must be a finite scalar or 1-D array, got {tq!r}')
        times = np.atleast_1d(tq)
        k = np.clip(np.searchsorted(self.t, times, side='right') - 1, 0, self.t.size - 2)
        w = (times - self.t[k]) / (self.t[k + 1] - self.t[k])
        out = self.effort[k] + w[:, None] * (self.effort[k + 1] - self.effort[k])
        out[~self.covers(times)] = 0.0
        return out[0] if tq.ndim == 0 else out


@njit(cache=True, nogil=True)
def servo_torque_into(c, theta, theta_dot, theta_d, theta_d_dot, integral, raw, out,
                      feedforward=None):
    """
    Write the unsaturated torque into ``raw`` and the applied torque into ``out``.

    The compiled twin of :meth:`Servo.torques` for one state. ``c`` is the record of
    :meth:`Servo.constants`; every array has shape (n,); ``raw`` and ``out`` must not alias
    the inputs. Ĝ_i = Σ_{k>=i} g h_k cos(θ_1 + ... + θ_k) at θ or θd (zero when ``c.gh`` is).
    ``feedforward`` (n,), τ_ff at this instant, is added before saturation; omitted or None,
    there is none (numba compiles that case without the addition).
    """
    n = theta.shape[0]
    at = theta_d if c.on_desired else theta
    # Ĝ by a reverse cumulative sum over the absolute link angles, into out
    acc = 0.0
    for i in range(n):
        acc += at[i]
        out[i] = c.gh[i] * math.cos(acc)
    for i in range(n - 2, -1, -1):
        out[i] += out[i + 1]
    for i in range(n):
        r = (compiled_pd_torque(c.kp[i], c.kd[i], theta_d[i] - theta[i],
                                theta_d_dot[i] - theta_dot[i])
             + integral[i] + out[i])
        if feedforward is not None:
            r += feedforward[i]
        raw[i] = r
        limit = c.tau_limit[i]
        out[i] = limit if r > limit else (-limit if r < -limit else r)


@njit(cache=True, nogil=True)
def servo_integral_rate_into(c, theta, theta_d, raw, applied, out):
    """Write İ (see :meth:`Servo.integral_rate`) of one state into ``out`` (n,)."""
    for i in range(theta.shape[0]):
        if c.ki[i] > 0.0:
            out[i] = (c.ki[i] * (theta_d[i] - theta[i])
                      + c.windup_gain[i] * (applied[i] - raw[i]))
        else:
            out[i] = 0.0

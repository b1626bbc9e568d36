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
The torque a plan needs, from a model of the arm: feed-forward and computed torque.

A PD servo produces torque only from error: to carry gravity and to accelerate the links
along the plan it must first fall behind. The feed-forward gives it that torque in advance,
the inverse dynamics along the planned trajectory (θd, θ̇d, θ̈d)::

    τ_ff = M(θd) θ̈d + V(θd, θ̇d) + G(θd) + F(θ̇d)

so that with a right model the PD only corrects what the model missed. The computed-torque
law (an option, for a drive that takes torque directly) closes the loop through the model
at the measured state, with outer-loop gains in acceleration units::

    τ = M(θ) (θ̈d + Kp e + Kd ė) + V(θ, θ̇) + G(θ) + F(θ̇),   e = θd − θ,  ė = θ̇d − θ̇

which is the inverse dynamics at (θ, θ̇) with the commanded acceleration, so both need from
the model one method, ``inverse_dynamics(theta, theta_dot, theta_ddot)`` over (N, n)
arrays: :class:`~rkgnn_ros.core.model.model.RKGNNModel`, the simulated
:class:`~rkgnn_ros.core.sim.plant.PlanarArm` (the true model) and a least-squares model all
have it, for any n.

θ̈d. A plan arrives as points with θd and θ̇d (``reference_trajectory``), without
accelerations. :func:`hermite_acceleration` takes θ̈d as the second derivative of the
cubic Hermite interpolant through the points' positions and velocities, the interpolant the
identifier builds for references (``SampledReference``) and the one joint_trajectory_controller
follows between points that carry positions and velocities. Within a segment of length h
that second derivative is linear; at a point it has one value from each side, each exact
for cubics and off by −h² θd⁗ / 12 for smooth motion; interior points take the mean of the
two. The centred difference of θ̇d, (θ̇d[k+1] − θ̇d[k−1]) / 2h, is off by +h² θd⁗ / 6 (twice
as much) and ignores the positions.

Nothing here checks or clips what a model returns: a model may give NaN or huge torques,
and :mod:`rkgnn_ros.core.control.gate` decides whether an effort may leave.
"""

from dataclasses import dataclass

import numpy as np

from ..data import finite_array
from ..servo_law import pd_torque


def _samples(name: str, value, shape=None) -> np.ndarray:
    """Return ``value`` as a finite float array of at least 1 dimension (shape checked)."""
    return finite_array(name, value, shape, min_ndim=1)


def _times(t, n_points: int) -> np.ndarray:
    t = _samples('t', t, (n_points,))
    if n_points < 2:
        raise ValueError(f'a plan needs at least 2 points, got {n_points}')
    if np.any(np.diff(t) <= 0.0):
        raise ValueError('t must be strictly increasing')
    return t


def hermite_acceleration(t, theta_d, theta_d_dot) -> np.ndarray:
    """
    Return θ̈d at the points: the cubic Hermite interpolant's second derivative.

    Parameters
    ----------
    t : array_like, shape (N,)
        Point times (s), strictly increasing, N >= 2.
    theta_d, theta_d_dot : array_like, shape (N, n)
        Planned positions (rad) and velocities (rad/s) at the points.

    Returns
    -------
    ndarray, shape (N, n)
        At interior points the mean of the two one-sided values, at the ends the one side
        there is (see the module docstring for the error).

    """
    theta_d = _samples('theta_d', theta_d)
    if theta_d.ndim != 2:
        raise ValueError(f'theta_d must have shape (N, n), got {theta_d.shape}')
    theta_d_dot = _samples('theta_d_dot', theta_d_dot, theta_d.shape)
    t = _times(t, theta_d.shape[0])
    h = np.diff(t)[:, None]                                         # (N-1, 1)
    slope = np.diff(theta_d, axis=0) / h                            # (N-1, n)
    v0, v1 = theta_d_dot[:-1], theta_d_dot[1:]
    # p'' at the start and at the end of each segment [t_k, t_k+1]
    start = (6.0 * slope - 4.0 * v0 - 2.0 * v1) / h
    end = (-6.0 * slope + 2.0 * v0 + 4.0 * v1) / h
    acc = np.empty_like(theta_d)
    acc[0] = start[0]
    acc[-1] = end[-1]
    acc[1:-1] = 0.5 * (end[:-1] + start[1:])
    return acc


def feedforward_torque(model, theta_d, theta_d_dot, theta_d_ddot,
                       torque_scale: float = 1.0) -> np.ndarray:
    """
    Return τ_ff = M(θd) θ̈d + V(θd, θ̇d) + G(θd) + F(θ̇d) of ``model``.

    Parameters
    ----------
    model : object
        Anything with ``inverse_dynamics(theta, theta_dot, theta_ddot) -> (N, n)``.
    theta_d, theta_d_dot, theta_d_ddot : array_like, shape (N, n)
        The plan at its points, finite.
    torque_scale : float
        N m per model torque unit: 1 for a model identified with torque (cases 1 and 2);
        for case 3 the scale fixed by a measurement (see
        :func:`rkgnn_ros.core.fitting.torque_check.torque_scale_from_effort`).

    Returns
    -------
    ndarray, shape (N, n)
        The model's torques as it gives them (non-finite if the model is).

    """
    theta_d = _samples('theta_d', theta_d)
    shape = theta_d.shape
    theta_d_dot = _samples('theta_d_dot', theta_d_dot, shape)
    theta_d_ddot = _samples('theta_d_ddot', theta_d_ddot, shape)
    tau = np.asarray(model.inverse_dynamics(theta_d, theta_d_dot, theta_d_ddot), dtype=float)
    if tau.shape != shape:
        raise ValueError(f'the model returned torques of shape {tau.shape}, expected {shape}')
    return float(torque_scale) * tau


@dataclass(frozen=True)
class FeedforwardPlan:
    """
    A plan and its feed-forward, point by point (what goes out as a JointTrajectory).

    Attributes
    ----------
    t : ndarray, shape (N,)
        Point times (s).
    theta_d, theta_d_dot, theta_d_ddot : ndarray, shape (N, n)
        The plan; θ̈d as given or from :func:`hermite_acceleration`.
    effort : ndarray, shape (N, n)
        The feed-forward torque τ_ff at the points (N m), not yet gated.

    """

    t: np.ndarray
    theta_d: np.ndarray
    theta_d_dot: np.ndarray
    theta_d_ddot: np.ndarray
    effort: np.ndarray


def plan_feedforward(model, t, theta_d, theta_d_dot, theta_d_ddot=None,
                     torque_scale: float = 1.0) -> FeedforwardPlan:
    """
    Return the feed-forward of ``model`` at the points of a plan.

    Parameters
    ----------
    model : object
        Anything with ``inverse_dynamics`` (see :func:`feedforward_torque`).
    t : array_like, shape (N,)
        Point times (s), strictly increasing, N >= 2.
    theta_d, theta_d_dot : array_like, shape (N, n)
        Planned positions and velocities at the points.
    theta_d_ddot : array_like, shape (N, n), optional
        Planned accelerations; by default :func:`hermite_acceleration`.
    torque_scale : float
        See :func:`feedforward_torque`.

    Returns
    -------
    FeedforwardPlan

    """
    theta_d = _samples('theta_d', theta_d)
    if theta_d.ndim != 2:
        raise ValueError(f'theta_d must have shape (N, n), got {theta_d.shape}')
    theta_d_dot = _samples('theta_d_dot', theta_d_dot, theta_d.shape)
    t = _times(t, theta_d.shape[0])
    if theta_d_ddot is None:
        theta_d_ddot = hermite_acceleration(t, theta_d, theta_d_dot)
    else:
        theta_d_ddot = _samples('theta_d_ddot', theta_d_ddot, theta_d.shape)
    effort = feedforward_torque(model, theta_d, theta_d_dot, theta_d_ddot, torque_scale)
    return FeedforwardPlan(t=t, theta_d=theta_d, theta_d_dot=theta_d_dot,
                           theta_d_ddot=theta_d_ddot, effort=effort)


def computed_torque(model, theta, theta_dot, theta_d, theta_d_dot, theta_d_ddot, gains,
                    torque_scale: float = 1.0) -> np.ndarray:
    """
    Return the computed-torque law τ = M(θ)(θ̈d + Kp e + Kd ė) + V(θ, θ̇) + G(θ) + F(θ̇).

    With the true model the error obeys ë + Kd ė + Kp e = 0 per joint, whatever the arm's
    coupling: Kp = ω², Kd = 2ζω place its poles.

    Parameters
    ----------
    model : object
        Anything with ``inverse_dynamics`` (see :func:`feedforward_torque`).
    theta, theta_dot : array_like, shape (..., n)
        Measured state.
    theta_d, theta_d_dot, theta_d_ddot : array_like, shape (..., n)
        The plan at the same instants.
    gains : (kp, kd), each array_like of shape (n,) or scalar
        Outer-loop gains in acceleration units (1/s², 1/s), non-negative.
    torque_scale : float
        See :func:`feedforward_torque`.

    Returns
    -------
    ndarray, shape (..., n)

    """
    theta = _samples('theta', theta)
    shape = theta.shape
    theta_dot = _samples('theta_dot', theta_dot, shape)
    theta_d = _samples('theta_d', theta_d, shape)
    theta_d_dot = _samples('theta_d_dot', theta_d_dot, shape)
    theta_d_ddot = _samples('theta_d_ddot', theta_d_ddot, shape)
    kp, kd = gains
    gains = []
    for name, value in (('kp', kp), ('kd', kd)):
        gain = _samples(name, np.broadcast_to(np.asarray(value, dtype=float), shape[-1:]))
        if np.any(gain < 0.0):
            raise ValueError(f'{name} must be >= 0, got {gain.tolist()}')
        gains.append(gain)
    command = theta_d_ddot + pd_torque(gains[0], gains[1], theta_d - theta,
                                       theta_d_dot - theta_dot)
    tau = np.asarray(model.inverse_dynamics(theta, theta_dot, command), dtype=float)
    if tau.shape != shape:
        raise ValueError(f'the model returned torques of shape {tau.shape}, expected {shape}')
    return float(torque_scale) * tau

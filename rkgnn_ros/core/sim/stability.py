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
How large a Runge-Kutta-Gill step the arm under PD control can take: its closed-loop stiffness.

The closed loop ẋ = [θ̇, M⁻¹(Kp(θd - θ) + Kd(θ̇d - θ̇) - V - G - F)] is linearised by
central differences; a step h is stable where h λ lies inside the RK4 stability region for
every eigenvalue λ (:func:`rkgnn_ros.core.integration.rkg.stability_radius`). The analysis
needs only ``forward_dynamics`` and ``n_joints``, so it is a mixin of the plant
(:class:`ClosedLoopAnalysis`); :func:`max_stable_rkg_step` applies it along a reference.
"""

from typing import Optional, Union

import numpy as np

from ..integration.rkg import stability_radius
from ..servo_law import pd_torque_coupled

ArrayLike = Union[float, np.ndarray]


def gain_matrix(name: str, value, n: int) -> np.ndarray:
    """Return a gain as an (n, n) matrix; a scalar or (n,) vector means a diagonal gain."""
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 0:
        arr = np.full(n, float(arr))
    if arr.ndim == 1:
        if arr.size != n:
            raise ValueError(f'{name} must have {n} diagonal entries, got {arr.size}')
        arr = np.diag(arr)
    if arr.shape != (n, n):
        raise ValueError(f'{name} must be a scalar, shape ({n},) or ({n}, {n}), got {arr.shape}')
    if not np.all(np.isfinite(arr)):
        raise ValueError(f'{name} must be finite')
    return arr


class ClosedLoopAnalysis:
    """
    Closed-loop stiffness of an arm under a PD servo (a mixin of :class:`.plant.PlanarArm`).

    Needs ``n_joints``, ``_joint_array(name, value)`` and
    ``forward_dynamics(theta, theta_dot, tau)`` (batched over leading axes) from the class.
    """

    def closed_loop_eigenvalues(self, theta: ArrayLike, theta_dot: ArrayLike, kp, kd,
                                theta_d: Optional[ArrayLike] = None,
                                theta_d_dot: Optional[ArrayLike] = None,
                                eps: float = 1e-6) -> np.ndarray:
        """
        Return the eigenvalues of the Jacobian ∂f/∂x of the PD closed loop at a state.

        The closed loop is ẋ = f(x) = [θ̇, M⁻¹(Kp(θd - θ) + Kd(θ̇d - θ̇) - V - G - F)] with
        θd, θ̇d frozen (default: equal to θ, θ̇, i.e. on the reference). The Jacobian is
        taken by central differences with relative step ``eps``.

        Parameters
        ----------
        theta, theta_dot : array_like, shape (..., n)
            States at which to linearise.
        kp, kd : array_like, scalar, shape (n,) or (n, n)
            Proportional and derivative gains (a vector means a diagonal gain).
        theta_d, theta_d_dot : array_like, shape (..., n), optional
            Frozen desired trajectory; default ``theta`` and ``theta_dot``.
        eps : float
            Relative finite-difference step.

        Returns
        -------
        ndarray, shape (..., 2n), complex

        """
        n = self.n_joints
        kp, kd, (theta, theta_dot, theta_d, theta_d_dot) = self._loop_arguments(
            theta, theta_dot, kp, kd, theta_d, theta_d_dot)
        x = np.concatenate([theta, theta_dot], axis=-1)             # (..., 2n)
        step = eps * np.maximum(1.0, np.abs(x))                      # (..., 2n)
        delta = np.eye(2 * n) * step[..., None, :]                   # (..., 2n, 2n) rows
        xs = np.concatenate([x[..., None, :] + delta, x[..., None, :] - delta], axis=-2)
        th, thd = xs[..., :n], xs[..., n:]
        ref = theta_d[..., None, :]
        ref_dot = theta_d_dot[..., None, :]
        tau = pd_torque_coupled(kp, kd, ref - th, ref_dot - thd)
        f = np.concatenate([thd, self.forward_dynamics(th, thd, tau)], axis=-1)
        jac_t = (f[..., :2 * n, :] - f[..., 2 * n:, :]) / (2.0 * step[..., :, None])
        return np.linalg.eigvals(np.swapaxes(jac_t, -1, -2))

    def _loop_arguments(self, theta, theta_dot, kp, kd, theta_d, theta_d_dot):
        """Return Kp, Kd (n, n) and θ, θ̇, θd, θ̇d broadcast (θd, θ̇d default θ, θ̇)."""
        n = self.n_joints
        theta = self._joint_array('theta', theta)
        theta_dot = self._joint_array('theta_dot', theta_dot)
        theta_d = theta if theta_d is None else self._joint_array('theta_d', theta_d)
        theta_d_dot = (theta_dot if theta_d_dot is None
                       else self._joint_array('theta_d_dot', theta_d_dot))
        return (gain_matrix('kp', kp, n), gain_matrix('kd', kd, n),
                np.broadcast_arrays(theta, theta_dot, theta_d, theta_d_dot))

    def closed_loop_stiffness(self, theta: ArrayLike, theta_dot: ArrayLike, kp, kd,
                              **kwargs) -> Union[float, np.ndarray]:
        """
        Return the largest |λ| of the PD closed-loop Jacobian at a state (1/s).

        See :meth:`closed_loop_eigenvalues` for the arguments. A float for a single state,
        otherwise an array of shape (...).
        """
        lam = np.abs(self.closed_loop_eigenvalues(theta, theta_dot, kp, kd, **kwargs))
        out = lam.max(axis=-1)
        return float(out) if out.ndim == 0 else out

    def stable_step(self, kp, kd, theta: ArrayLike, theta_dot: ArrayLike,
                    safety: float = 0.5, **kwargs) -> float:
        """
        Return the largest Runge-Kutta-Gill step that is stable at all the given states.

        For each eigenvalue λ of the closed-loop Jacobian the limit is r(arg λ) / |λ|, where
        r is the distance from the origin to the boundary of the RK4 stability region along
        the ray through λ (2.785 on the negative real axis); the result is ``safety`` times
        the smallest limit. See :func:`rkgnn_ros.core.integration.rkg.stability_radius`.

        Parameters
        ----------
        kp, kd : array_like
            PD gains, as for :meth:`closed_loop_eigenvalues`.
        theta, theta_dot : array_like, shape (..., n)
            States (e.g. along a reference trajectory).
        safety : float
            Safety factor in (0, 1]; 0.5 by default, since the linearisation is local and the
            trajectory leaves the sampled states.

        """
        if not 0.0 < safety <= 1.0:
            raise ValueError(f'safety must be in (0, 1], got {safety}')
        lam = self.closed_loop_eigenvalues(theta, theta_dot, kp, kd, **kwargs).ravel()
        lam = lam[np.abs(lam) > 0.0]
        if lam.size == 0:
            return float('inf')
        return float(safety * np.min(stability_radius(lam) / np.abs(lam)))


def max_stable_rkg_step(arm, kp, kd, reference, duration: float,
                        t0: float = 0.0, samples: int = 200, safety: float = 0.5) -> float:
    """
    Estimate the largest stable Runge-Kutta-Gill step along a reference trajectory.

    Samples ``samples`` states on the reference (θ = θd(t), θ̇ = θ̇d(t)) over
    ``[t0, t0 + duration]`` and returns :meth:`PlanarArm.stable_step` over all of them. A
    sampling interval dt larger than this needs ``ceil(dt / h)`` RKG sub-steps per sample.

    Parameters
    ----------
    arm : PlanarArm
        The plant.
    kp, kd : array_like
        PD gains (a vector means a diagonal gain).
    reference : Reference
        Anything with ``evaluate(t) -> (theta_d, theta_d_dot)``.
    duration : float
        Time span to sample (s), positive.
    t0 : float
        Start time.
    samples : int
        Number of states.
    safety : float
        Safety factor, 0.5 by default.

    Returns
    -------
    float
        Step h in seconds.

    """
    if not (np.isfinite(duration) and duration > 0.0):
        raise ValueError(f'duration must be positive, got {duration}')
    if samples < 1:
        raise ValueError(f'samples must be >= 1, got {samples}')
    t = t0 + np.linspace(0.0, duration, int(samples))
    theta, theta_dot = reference.evaluate(t)
    return arm.stable_step(kp, kd, theta, theta_dot, safety=safety)

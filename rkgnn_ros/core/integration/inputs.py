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
The inputs of a rollout at every Runge-Kutta-Gill stage time, from sampled data.

A rollout between two samples takes ``substeps`` RKG steps, whose stages need the input u
at t, t + h/2 and t + h of every step: the measured torque held or interpolated between its
samples (case 1), or the desired trajectory θd, θ̇d (cases 2 and 3) evaluated from a
reference or interpolated by cubic Hermite from its samples. The model's rollouts and the
fitness problem both build their inputs here, once per segment.
"""

from numba import njit
import numpy as np


def hermite(t_knots, values, slopes, t_eval):
    """
    Cubic Hermite interpolation on a uniform grid, held constant outside it.

    Parameters
    ----------
    t_knots : ndarray, shape (N,)
        Uniform knot times.
    values, slopes : ndarray, shape (N, m)
        Values and derivatives at the knots.
    t_eval : ndarray, shape (T,)
        Where to evaluate.

    Returns
    -------
    ndarray, shape (T, m)

    """
    dt = (t_knots[-1] - t_knots[0]) / (t_knots.size - 1)
    s = np.clip((np.asarray(t_eval) - t_knots[0]) / dt, 0.0, t_knots.size - 1)
    i = np.minimum(np.floor(s).astype(int), t_knots.size - 2)
    u = (s - i)[:, None]
    h00 = 2 * u ** 3 - 3 * u ** 2 + 1
    h10 = u ** 3 - 2 * u ** 2 + u
    h01 = -2 * u ** 3 + 3 * u ** 2
    h11 = u ** 3 - u ** 2
    return (h00 * values[i] + h10 * dt * slopes[i] + h01 * values[i + 1]
            + h11 * dt * slopes[i + 1])


@njit(cache=True, nogil=True)
def _desired_stages(theta_d, theta_d_dot, dt, substeps):  # pragma: no cover - compiled
    """
    Return [θd, θ̇d] by cubic Hermite at every stage time, shape (N-1, substeps, 3, 2n).

    θd's slopes are θ̇d; θ̇d's are its central differences (``np.gradient``'s, one-sided at
    the ends). On a uniform grid the stages sit at the same fractions of every interval, so
    the four Hermite weights are computed once per stage. Compiled: built with numpy, these
    inputs took longer than the rollout they feed (a prediction at 1 kHz, bench/latency.py).
    """
    k_all, n = theta_d.shape
    acc = np.empty((k_all, n))
    for j in range(n):
        acc[0, j] = (theta_d_dot[1, j] - theta_d_dot[0, j]) / dt
        acc[k_all - 1, j] = (theta_d_dot[k_all - 1, j] - theta_d_dot[k_all - 2, j]) / dt
        for k in range(1, k_all - 1):
            acc[k, j] = (theta_d_dot[k + 1, j] - theta_d_dot[k - 1, j]) / (2.0 * dt)
    weights = np.empty((substeps, 3, 4))
    for s in range(substeps):
        for c in range(3):
            u = (s + 0.5 * c) / substeps
            u2 = u * u
            u3 = u2 * u
            weights[s, c, 0] = 2.0 * u3 - 3.0 * u2 + 1.0
            weights[s, c, 1] = (u3 - 2.0 * u2 + u) * dt
            weights[s, c, 2] = -2.0 * u3 + 3.0 * u2
            weights[s, c, 3] = (u3 - u2) * dt
    out = np.empty((k_all - 1, substeps, 3, 2 * n))
    for k in range(k_all - 1):
        for s in range(substeps):
            for c in range(3):
                w0, w1, w2, w3 = (weights[s, c, 0], weights[s, c, 1], weights[s, c, 2],
                                  weights[s, c, 3])
                for j in range(n):
                    out[k, s, c, j] = (w0 * theta_d[k, j] + w1 * theta_d_dot[k, j]
                                       + w2 * theta_d[k + 1, j] + w3 * theta_d_dot[k + 1, j])
                    out[k, s, c, n + j] = (w0 * theta_d_dot[k, j] + w1 * acc[k, j]
                                           + w2 * theta_d_dot[k + 1, j] + w3 * acc[k + 1, j])
    return out


def stage_times(t0, dt, n_intervals, substeps):
    """Stage times t, t + h/2, t + h of every substep, shape (n_intervals, substeps, 3)."""
    h = dt / substeps
    base = t0 + dt * np.arange(n_intervals)[:, None] + h * np.arange(substeps)[None, :]
    return base[:, :, None] + np.array([0.0, 0.5 * h, h])[None, None, :]


def stage_inputs(case, t, substeps, tau=None, theta_d=None, theta_d_dot=None, reference=None,
                 torque_interpolation='hold'):
    """
    Return the input u at every RKG stage of a uniformly sampled segment.

    Parameters
    ----------
    case : str
        'torque', 'pd_gains' or 'unknown'.
    t : ndarray, shape (N,)
        Uniform sample times.
    substeps : int
        RKG steps per sampling interval.
    tau : ndarray, shape (N, n), optional
        Case 'torque': the measured torque, held over each interval ('hold') or
        interpolated linearly ('linear': first-order hold).
    theta_d, theta_d_dot : ndarray, shape (N, n), optional
        Other cases: desired samples, interpolated by cubic Hermite (θ̇d as the slope of θd,
        finite differences of θ̇d as its own slope) unless ``reference`` is given.
    reference : object with ``evaluate(times) -> (θd, θ̇d)``, optional
        Evaluated exactly at the stage times.
    torque_interpolation : str
        'hold' or 'linear'.

    Returns
    -------
    ndarray, shape (N-1, substeps, 3, m)
        m = n (torque) or 2n ([θd, θ̇d]); the stages are t, t + h/2 and t + h.

    """
    t = np.asarray(t, dtype=float)
    n_int = t.size - 1
    dt = (t[-1] - t[0]) / n_int
    if case == 'torque':
        if tau is None:
            raise ValueError("case 'torque' needs measured torque (Dataset.tau)")
        tau = np.asarray(tau, dtype=float)
        n = tau.shape[1]
        if torque_interpolation == 'hold':
            u = np.broadcast_to(tau[:-1, None, None, :], (n_int, substeps, 3, n))
            return np.ascontiguousarray(u)
        if torque_interpolation != 'linear':
            raise ValueError(f"torque_interpolation must be 'hold' or 'linear', "
                             f'got {torque_interpolation!r}')
        frac = (stage_times(0.0, dt, n_int, substeps)
                - dt * np.arange(n_int)[:, None, None]) / dt
        tau0 = tau[:-1, None, None, :]
        tau1 = tau[1:, None, None, :]
        return np.ascontiguousarray(tau0 + frac[..., None] * (tau1 - tau0))
    if reference is None:
        if theta_d is None or theta_d_dot is None:
            raise ValueError(f'case {case!r} needs the desired trajectory '
                             '(Dataset.theta_d, theta_d_dot) or a reference')
        theta_d = np.asarray(theta_d, dtype=float)
        theta_d_dot = np.asarray(theta_d_dot, dtype=float)
        if theta_d.ndim != 2 or theta_d.shape[0] < 2 or theta_d_dot.shape != theta_d.shape:
            raise ValueError('theta_d and theta_d_dot must both be (N >= 2, n), got '
                             f'{theta_d.shape} and {theta_d_dot.shape}')
        return _desired_stages(np.ascontiguousarray(theta_d), np.ascontiguousarray(theta_d_dot),
                               float(dt), int(substeps))
    times = stage_times(t[0], dt, n_int, substeps).reshape(-1)
    qd, qd_dot = reference.evaluate(times)
    qd = np.asarray(qd)
    u = np.concatenate([qd, np.asarray(qd_dot)], axis=-1)
    return np.ascontiguousarray(u.reshape(n_int, substeps, 3, 2 * qd.shape[-1]))

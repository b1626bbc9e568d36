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
Scoring predictions against the motion that followed (used by the demo and the benchmarks).

A prediction made from the state at time t0 covers [t0, t0 + horizon]. Its k-ahead error is
the predicted θ at t0 + k minus the measured θ at that time (linear interpolation of the
measured stream). The figure users ask for is the RMSE of the ``ahead``-second error over
the predictions whose target time has been measured, divided by the range of θ.
"""

from typing import Sequence

import numpy as np


def ahead_errors(stamps: Sequence[float], times: Sequence[np.ndarray],
                 thetas: Sequence[np.ndarray], meas_t, meas_theta, ahead):
    """
    Errors of every prediction ``ahead`` seconds after its start.

    Parameters
    ----------
    stamps : sequence of float, length M
        Start time t0 of each prediction.
    times : sequence of ndarray, shape (K_m,)
        Offsets from t0 of each prediction's points (``time_from_start``).
    thetas : sequence of ndarray, shape (K_m, n)
        Predicted θ at those points.
    meas_t : ndarray, shape (T,)
        Increasing times of the measured stream.
    meas_theta : ndarray, shape (T, n)
        Measured θ.
    ahead : float
        How far ahead to score (s); a prediction shorter than that is skipped.

    Returns
    -------
    t0 : ndarray, shape (M',)
        Start times of the scored predictions.
    errors : ndarray, shape (M', n)
        Predicted minus measured θ at t0 + ahead.

    """
    meas_t = np.asarray(meas_t, dtype=float)
    meas_theta = np.asarray(meas_theta, dtype=float)
    out_t, out_e = [], []
    if meas_t.size < 2:
        return np.empty(0), np.empty((0, meas_theta.shape[-1] if meas_theta.ndim == 2 else 0))
    for t0, off, th in zip(stamps, times, thetas):
        off = np.asarray(off, dtype=float)
        th = np.asarray(th, dtype=float)
        target = t0 + ahead
        if off.size < 2 or off[-1] < ahead - 1e-9 or target > meas_t[-1] or target < meas_t[0]:
            continue
        pred = np.array([np.interp(ahead, off, th[:, j]) for j in range(th.shape[1])])
        meas = np.array([np.interp(target, meas_t, meas_theta[:, j])
                         for j in range(meas_theta.shape[1])])
        out_t.append(t0)
        out_e.append(pred - meas)
    if not out_t:
        return np.empty(0), np.empty((0, meas_theta.shape[1]))
    return np.asarray(out_t), np.asarray(out_e)


def range_normalised_rmse(errors, theta_range) -> float:
    """RMSE per joint divided by the θ range per joint, averaged over joints (NaN if empty)."""
    errors = np.asarray(errors, dtype=float)
    if errors.size == 0:
        return float('nan')
    rmse = np.sqrt(np.mean(np.square(errors), axis=0))
    return float(np.mean(rmse / np.maximum(np.asarray(theta_range, dtype=float), 1e-12)))

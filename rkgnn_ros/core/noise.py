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
The measurement noise a joint stream shows: the floor under any prediction's score.

A prediction is scored against the measured θ, so no predictor scores below the noise of
the measurement, and two predictors whose errors are both about that noise cannot be told
apart. :func:`encoder_noise` measures it from the stream itself, per joint, whatever the
driver says: each sample against the cubic through its two neighbours on each side (on
their stamps, so jitter and dropped samples are taken as they come), scaled so that white
noise of std σ on every sample gives residuals of std σ, and the median absolute residual
turned into a std (× 1.4826, robust to the moments the arm jerks). The motion itself leaves
a residual of about θ⁗ dt⁴ / 6 (at 100 Hz and 1 rad/s² of jerk rate, 2e-9 rad), far below
any encoder's resolution. Stencils over a gap longer than ``max_gap`` are left out: what the
arm did there is not noise.
"""

import math

import numpy as np

__all__ = ['encoder_noise', 'MIN_RESIDUALS', 'MAX_SAMPLES']

#: Residuals needed per joint for an estimate (fewer: NaN).
MIN_RESIDUALS = 20
#: Only the newest samples are used: the cost stays bounded whatever the rate.
MAX_SAMPLES = 4000
_MAD_TO_STD = 1.4826


def encoder_noise(t, theta, max_gap: float = math.inf) -> np.ndarray:
    """
    Return the std (rad) of the measurement noise on each joint's θ, (n,).

    Parameters
    ----------
    t : array_like, shape (T,)
        Increasing stamps (s).
    theta : array_like, shape (T, n)
        Measured θ (rad).
    max_gap : float
        Samples further apart than this (s) are not neighbours.

    Returns
    -------
    ndarray, shape (n,)
        NaN where fewer than :data:`MIN_RESIDUALS` samples have two neighbours on each side.

    """
    t = np.asarray(t, dtype=float).reshape(-1)
    theta = np.asarray(theta, dtype=float)
    if theta.ndim != 2 or theta.shape[0] != t.size:
        raise ValueError(f'theta must have shape (T, n) with T = {t.size}, got {theta.shape}')
    t, theta = t[-MAX_SAMPLES:], theta[-MAX_SAMPLES:]
    n = theta.shape[1]
    if t.size < 5:
        return np.full(n, np.nan)
    centre = t[2:-2]
    near = np.stack([t[:-4], t[1:-3], t[3:-1], t[4:]])                       # (4, M)
    steps = np.diff(t)
    spans = np.stack([steps[i:steps.size - 3 + i] for i in range(4)])        # (4, M)
    usable = np.all((spans > 0.0) & (spans <= max_gap), axis=0)
    # Lagrange weights of the cubic through the four neighbours, at the centre's stamp
    weights = np.ones_like(near)
    values = np.stack([theta[:-4], theta[1:-3], theta[3:-1], theta[4:]])     # (4, M, n)
    with np.errstate(all='ignore'):  # stamps too close: non-finite, left out below
        for i in range(4):
            for m in range(4):
                if m != i:
                    weights[i] *= (centre - near[m]) / (near[i] - near[m])
        residual = theta[2:-2] - np.einsum('im,imn->mn', weights, values)
        z = residual / np.sqrt(1.0 + np.sum(weights ** 2, axis=0))[:, None]
    good = usable & np.all(np.isfinite(z), axis=1)
    if good.sum() < MIN_RESIDUALS:
        return np.full(n, np.nan)
    return _MAD_TO_STD * np.median(np.abs(z[good]), axis=0)

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
The band a prediction must stay in: a model that starts to diverge, seen on its own rollout.

A score comes a horizon after its prediction. A model that turns bad (a refit, a new law, a
state where its dynamics blow up) would be published for that long if only scores judged
it; its own rollout shows it at once. A servoed arm goes from where it is toward where the
plan tells it to go, within its tracking error; a prediction that leaves that region by
more than the errors seen lately is not believed.

The band, per joint and point of a prediction, in rad: the hull of the start θ0 and the
plan's θd up to that point (``min(θ0, min θd[0..k])`` to ``max(θ0, max θd[0..k])``),
widened on both sides by :data:`BAND_FACTOR` × (the recent RMSE of following the reference
+ the recent RMSE of the predicting model + the encoder noise), each RMSE at that offset
(interpolated between the scored horizons, held before the first and after the last), plus
:data:`OVERSHOOT` × the hull's own width there (a servo overshoots a move it was not seen
making lately: a step of the plan after a quiet spell). A model that behaves as it did
lately stays inside by construction (its error and the arm's tracking error are both within
a few RMSE); one that diverges leaves it, growing, within a fraction of the horizon.
"""

from typing import Dict, NamedTuple, Optional, Sequence

import numpy as np

__all__ = ['BAND_FACTOR', 'OVERSHOOT', 'Excursion', 'band_width', 'leaves_band']

#: Half-width of the band beyond the plan's hull, in recent RMSEs (see the module).
BAND_FACTOR = 4.0
#: ... plus this share of the hull's width (a servo's overshoot of a move: 25 % is a
#: damping ratio of 0.4).
OVERSHOOT = 0.25


class Excursion(NamedTuple):
    """Where a prediction first left its band: offset (s), joint, rad outside, half-width."""

    offset: float
    joint: int
    outside: float  # rad beyond the plan's hull
    width: float    # the band's half-width there (rad)


def _at_offsets(offsets: np.ndarray, horizons: Sequence[float],
                table: Dict[float, np.ndarray]) -> Optional[np.ndarray]:
    """Return a per-horizon RMSE table (n,) each at ``offsets``, (K, n); None if unscored."""
    values = np.vstack([table[h] for h in horizons])                                # (H, n)
    finite = np.all(np.isfinite(values), axis=1)
    if not np.any(finite):
        return None
    knots, values = np.asarray(horizons, dtype=float)[finite], values[finite]
    at = np.interp(offsets, knots, np.arange(knots.size, dtype=float))  # (K,) knot index
    low = np.minimum(at.astype(int), knots.size - 1)
    high = np.minimum(low + 1, knots.size - 1)
    share = (at - low)[:, None]
    return (1.0 - share) * values[low] + share * values[high]


def band_width(offsets, horizons: Sequence[float], follow: Dict[float, np.ndarray],
               model: Dict[float, np.ndarray], noise) -> Optional[np.ndarray]:
    """
    Return the band's half-width beyond the plan's hull (rad) at ``offsets`` (K,), (K, n).

    ``follow`` and ``model``: horizon (s) -> recent RMSE per joint (n,) in rad, of following
    the reference and of the predicting model; ``noise`` (n,): the encoder noise (rad).
    None while the model has no score (nothing to judge it by); following the reference
    without a score counts 0.
    """
    offsets = np.asarray(offsets, dtype=float).reshape(-1)
    mine = _at_offsets(offsets, horizons, model)
    if mine is None:
        return None
    theirs = _at_offsets(offsets, horizons, follow)
    noise = np.nan_to_num(np.asarray(noise, dtype=float), nan=0.0)
    return BAND_FACTOR * (mine + (0.0 if theirs is None else theirs) + noise)


def leaves_band(offsets, theta, theta0, theta_d, width) -> Optional[Excursion]:
    """
    Return where the prediction ``theta`` (K, n) leaves its band, None if it stays inside.

    ``offsets`` (K,) from the start state θ0 (n,); ``theta_d`` (K, n) the plan at them;
    ``width`` (K, n) from :func:`band_width`, to which :data:`OVERSHOOT` × the hull's width
    is added. The excursion reported is the first point outside, at the joint furthest
    outside there relative to the band's half-width.
    """
    offsets = np.asarray(offsets, dtype=float).reshape(-1)
    theta = np.asarray(theta, dtype=float)
    theta_d = np.asarray(theta_d, dtype=float)
    theta0 = np.asarray(theta0, dtype=float).reshape(1, -1)
    low = np.minimum(np.minimum.accumulate(theta_d, axis=0), theta0)
    high = np.maximum(np.maximum.accumulate(theta_d, axis=0), theta0)
    width = np.asarray(width, dtype=float) + OVERSHOOT * (high - low)
    outside = np.maximum(low - theta, theta - high)                       # (K, n), rad
    outside = np.where(np.isfinite(outside), outside, np.inf)
    excess = outside - width
    if not np.any(excess > 0.0):
        return None
    k = int(np.argmax(np.any(excess > 0.0, axis=1)))          # the first point outside
    j = int(np.argmax(excess[k] / np.maximum(width[k], 1e-300)))
    return Excursion(float(offsets[k]), int(j), float(outside[k, j]), float(width[k, j]))

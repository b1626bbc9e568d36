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
A steady driver's stamps, put back on its sampling grid.

A driver that samples at a fixed rate but stamps each message a little late or early (at
its publish time, under a loaded scheduler) puts every sample at the wrong time: at 1 ms of
jitter and 1 rad/s that is 1e-3 rad, ten times a good encoder's noise, and it reaches θ̈ as
differentiated noise. :class:`StampGrid` follows the grid the stamps scatter about with a
phase-locked loop: the next grid point is a whole number of periods after the previous
output (dropped messages keep their slots, up to :data:`MAX_STEPS` periods); a stamp within
:data:`TOLERANCE` of a period from it is moved onto it, the grid's phase following by
:data:`FOLLOW` of the difference and its period by :data:`FOLLOW`² / 4 of it per period (a
critically damped second-order loop: a clock that drifts is followed without a lasting
offset; the jitter is reduced about √(FOLLOW / 2), seven to ten times). It starts as a
least-squares line through the stamps (larger gains that fall to these), so its first
period estimate leaves no offset. It acts only on a regular stream whose stamps jitter:
until :data:`MIN_INTERVALS` intervals are seen, while their spread (median absolute
deviation) exceeds :data:`REGULAR` of the period, or while consecutive intervals are not
anticorrelated (lag-1 correlation above :data:`ANTICORRELATION` to start, :data:`RELEASE`
to stop: irregular sampling stamped truly gives independent intervals), every stamp is
returned as it came; so is one off the grid (a pause, a restart), which starts the grid
anew. A stream stamped exactly on a grid comes out unchanged (to rounding).
"""

from collections import deque
import math

__all__ = ['ANTICORRELATION', 'FOLLOW', 'MAX_STEPS', 'MIN_INTERVALS', 'REGULAR', 'RELEASE',
           'StampGrid', 'TOLERANCE']

#: Largest distance from the grid point (share of a period) that is jitter.
TOLERANCE = 0.3
#: Share of each stamp's distance from the grid that moves the grid.
FOLLOW = 0.02
#: Largest spread of the intervals (median absolute deviation / period) of a regular stream.
REGULAR = 0.2
#: Intervals seen before the grid is used (and kept to judge the stream).
MIN_INTERVALS = 200
#: Most periods between two stamps that still count as drops (beyond: a pause, anew).
MAX_STEPS = 20
#: Intervals between two judgements of the stream (each sorts the history).
JUDGE_EVERY = 32
#: Lag-1 correlation of the intervals at or below which they are jitter about a grid ...
ANTICORRELATION = -0.3
#: ... and above which a grid in use is given up.
RELEASE = -0.1


class StampGrid:
    """Moves the stamps of a steady stream onto its sampling grid (module docstring)."""

    def __init__(self, history: int = 256):
        self._intervals = deque(maxlen=int(history))
        self._raw = None       # the previous stamp as it came
        self._out = None       # the previous stamp returned
        self._period = None    # the loop's period (s), once the stream is regular
        self._count = 0        # stamps the loop has taken since it started
        self._unjudged = 0     # intervals since the stream was last judged

    def reset(self) -> None:
        """Forget the grid (a cleared buffer, a clock jump)."""
        self._intervals.clear()
        self._raw = self._out = self._period = None
        self._count = self._unjudged = 0

    def _regular_period(self):
        """Return the median interval if the stream jitters about a grid, else None."""
        if len(self._intervals) < MIN_INTERVALS:
            return None
        values = sorted(self._intervals)
        period = values[len(values) // 2]
        spread = sorted(abs(v - period) for v in values)[len(values) // 2]
        if not (period > 0.0 and spread <= REGULAR * period):
            return None
        # jitter about a grid makes consecutive intervals anticorrelated (one late stamp
        # lengthens one interval and shortens the next: -0.5); stamps of irregular sampling,
        # true as they are, give independent intervals (0) and are left alone. Hysteresis
        # keeps the decision from flickering with the estimate's noise.
        deviations = [v - period for v in self._intervals]
        pairs = [(a, b) for a, b in zip(deviations, deviations[1:])
                 if abs(a) < 0.5 * period and abs(b) < 0.5 * period]
        power = sum(a * a for a, _ in pairs)
        if power <= len(pairs) * (1e-6 * period) ** 2:
            return period                           # exact: on the grid already
        correlation = sum(a * b for a, b in pairs) / power
        bar = RELEASE if self._period is not None else ANTICORRELATION
        return period if correlation <= bar else None

    def __call__(self, t: float) -> float:
        """Return the stamp ``t`` (s) moved onto the grid, or as it came."""
        if t == self._raw:                  # a repeated stamp stays a repeated stamp
            return self._out
        raw, self._raw = self._raw, t
        if raw is not None and t > raw:
            self._intervals.append(t - raw)
            self._unjudged += 1
        if self._unjudged >= JUDGE_EVERY:      # the stream is judged anew now and then
            self._unjudged = 0
            regular = self._regular_period()
            if regular is None:
                self._period = None
            elif self._period is None:
                self._period, self._count = regular, 0
        previous, period, out = self._out, self._period, t
        if previous is not None and period is not None:
            steps = round((t - previous) / period)
            target = previous + steps * period
            error = t - target
            if abs(error) <= 1e-9 * max(1.0, abs(t)):
                out = t                                 # on the grid already: exact
            elif 1 <= steps <= MAX_STEPS and abs(error) <= TOLERANCE * period:
                # the gains of a least-squares line through the stamps so far, until they
                # fall to the loop's own (an alpha-beta filter that starts with a growing
                # memory, so the first estimate of the period costs no lasting offset)
                self._count += 1
                k = self._count + 1
                phase = max(FOLLOW, 2.0 * (2 * k - 1) / (k * (k + 1)))
                rate = max(0.25 * FOLLOW * FOLLOW, 6.0 / (k * (k + 1)))
                out = target + phase * error
                self._period = period + rate * error / steps
        if not math.isfinite(out):
            out = t
        self._out = out
        return out

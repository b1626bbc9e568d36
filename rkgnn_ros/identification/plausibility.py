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
Samples no arm could produce: dropped and counted before they reach a buffer or a fit.

Finite garbage within the ±1e6 the buffer's ``out_of_range`` rule lets through (two
messages a second among a good stream sufficed) poisoned every fit: the feed-forward's
model reached a stiffness of 7e9 1/s (its rollout then asked for 37 GiB) and the search's
saved cost was 15,199 against 0.06 on clean data. :class:`PlausibilityFilter` compares each
sample with the last one it let through (the *anchor*), per joint:

``implausible_jump``
    θ moved more than ``V Δt + JUMP_FLOOR``: V is the larger of :data:`SPEED_FLOOR` and
    :data:`FACTOR` times the speed the stream has shown (rad/s).
``implausible_velocity``
    a measured θ̇ beyond ``2 V``, or one that changed more than ``A Δt + VELOCITY_FLOOR``:
    A the larger of :data:`ACCELERATION_FLOOR` and FACTOR times the shown acceleration.
``implausible_effort``
    τ changed more than ``FACTOR T + EFFORT_FLOOR``: T the larger of the largest |τ| the
    stream has shown and the anchor's own.

*Shown* means robustly: the median, over the last :data:`BLOCKS` blocks of :data:`BLOCK`
samples let through, of each block's largest value, so that no single sample raises it.
A real change that fails these (the arm hit something, a driver re-homed an encoder, the
stream started somewhere else) is not lost: a sample that fails is held, and when
:data:`RUN` held samples in a row agree with each other (each plausible after the one
before) they are all let through, in order, and the last becomes the anchor. Held samples
that do not make such a run are dropped with the reason each failed for. The first
samples of a stream are held the same way until RUN of them agree. Interleaved garbage
never makes a run (it agrees neither with the stream nor with itself), so it never
reaches the buffer; a steady stream never waits.

No ROS, no clock: the caller gives each sample's stamp and takes back what to pass on and
what to count.
"""

from collections import deque
from typing import List, NamedTuple, Optional, Tuple

import numpy as np

__all__ = ['ACCELERATION_FLOOR', 'BLOCK', 'BLOCKS', 'EFFORT_FLOOR', 'FACTOR', 'JUMP_FLOOR',
           'PLAUSIBILITY_REASONS', 'PlausibilityFilter', 'RUN', 'SPEED_FLOOR',
           'VELOCITY_FLOOR']

#: The drop reasons of this module.
PLAUSIBILITY_REASONS = ('implausible_jump', 'implausible_velocity', 'implausible_effort')

FACTOR = 10.0               # how far beyond what the stream has shown is implausible
SPEED_FLOOR = 50.0          # rad/s: a speed always allowed (arm joints reach a few rad/s)
JUMP_FLOOR = 0.1            # rad: a step always allowed (noise, quantisation)
ACCELERATION_FLOOR = 1000.0  # rad/s^2 always allowed
VELOCITY_FLOOR = 5.0        # rad/s: a change of θ̇ always allowed (differenced noise)
EFFORT_FLOOR = 1.0          # N m: a change of τ always allowed
RUN = 3                     # held samples that agree with each other are let through
BLOCK = 64                  # samples per block of the shown scales
BLOCKS = 16                 # blocks whose median is the shown scale


class _Sample(NamedTuple):
    t: float
    theta: List[float]
    theta_dot: Optional[List[float]]
    tau: Optional[List[float]]


class _Scale:
    """The robust largest value of a per-joint quantity: median of recent block maxima."""

    def __init__(self, n: int):
        self._block = [0.0] * n
        self._count = 0
        self._maxima: deque = deque(maxlen=BLOCKS)
        self.value = [0.0] * n

    def add(self, values: List[float]) -> bool:
        """Add one sample's values; return whether :attr:`value` changed."""
        self._block = [max(a, b) for a, b in zip(self._block, values)]
        self._count += 1
        if self._count < BLOCK:
            return False
        self._maxima.append(self._block)
        self.value = np.median(np.array(self._maxima), axis=0).tolist()
        self._block = [0.0] * len(self._block)
        self._count = 0
        return True


def _listed(values) -> Optional[List[float]]:
    return None if values is None else np.asarray(values, dtype=float).tolist()


class PlausibilityFilter:
    """
    Let through the samples an arm could produce; hold or drop the others (module doc).

    Parameters
    ----------
    names : sequence of str
        The joints, in column order (messages name them).

    """

    def __init__(self, names):
        self.names = tuple(names)
        self.n = len(self.names)
        self._anchor: Optional[_Sample] = None
        self._held: List[Tuple[object, _Sample, str, str]] = []  # payload, sample, reason, why
        self._speed = _Scale(self.n)
        self._acceleration = _Scale(self.n)
        self._effort = _Scale(self.n)
        self._limits()

    def _limits(self) -> None:
        """Derive the allowed speed, acceleration and shown |τ| from the scales."""
        self._speed_limit = [max(SPEED_FLOOR, FACTOR * v) for v in self._speed.value]
        self._acceleration_limit = [max(ACCELERATION_FLOOR, FACTOR * v)
                                    for v in self._acceleration.value]
        self._effort_shown = max(self._effort.value, default=0.0)

    def reset(self) -> None:
        """Forget the anchor, the held samples and the shown scales."""
        self.__init__(self.names)

    @property
    def held(self) -> int:
        """Return the count of samples waiting for a run or a drop."""
        return len(self._held)

    def offer(self, payload, t: float, theta, theta_dot=None, tau=None):
        """
        Take one sample; return ``(passed, dropped)``.

        ``passed`` lists the payloads to use now, oldest first (this one, or a run of held
        ones ending with it, or nothing); ``dropped`` lists ``(payload, reason, message)``
        of held samples that are dropped now.
        """
        sample = _Sample(float(t), _listed(theta), _listed(theta_dot), _listed(tau))
        failure = None if self._anchor is None else self._failure(self._anchor, sample)
        if self._anchor is not None and failure is None:
            dropped = self._drop_held() if self._held else []
            self._accept(sample)
            return [payload], dropped
        dropped = []
        if self._held and self._failure(self._held[-1][1], sample) is not None:
            dropped = self._drop_held()
        reason, why = failure if failure is not None else (
            'implausible_jump', 'it disagrees with the samples after it (nothing before it '
                                'to compare with)')
        self._held.append((payload, sample, reason, why))
        if len(self._held) < RUN:
            return [], dropped
        passed = [entry[0] for entry in self._held]
        for entry in self._held:
            self._accept(entry[1])
        self._held = []
        return passed, dropped

    def _drop_held(self):
        dropped = [(payload, reason, why) for payload, _, reason, why in self._held]
        self._held = []
        return dropped

    def _accept(self, sample: _Sample) -> None:
        """Make ``sample`` the anchor; add what it shows to the scales."""
        anchor, changed = self._anchor, False
        if anchor is not None and sample.t > anchor.t:
            rate = 1.0 / (sample.t - anchor.t)
            changed = self._speed.add([abs(x - y) * rate
                                       for x, y in zip(sample.theta, anchor.theta)])
            if sample.theta_dot is not None and anchor.theta_dot is not None:
                changed |= self._acceleration.add(
                    [abs(x - y) * rate for x, y in zip(sample.theta_dot, anchor.theta_dot)])
        if sample.tau is not None:
            changed |= self._effort.add([abs(x) for x in sample.tau])
        if changed:
            self._limits()
        self._anchor = sample

    def _failure(self, a: _Sample, b: _Sample) -> Optional[Tuple[str, str]]:
        """Return ``(reason, why)`` when ``b`` cannot follow ``a``, else None."""
        dt = abs(b.t - a.t)
        speed = self._speed_limit
        for j, (x, y) in enumerate(zip(b.theta, a.theta)):
            if abs(x - y) > speed[j] * dt + JUMP_FLOOR:
                return 'implausible_jump', (f'θ of {self.names[j]} moved {abs(x - y):.6g} rad '
                                            f'in {dt:.6g} s (allowed: {speed[j]:.3g} rad/s '
                                            f'and {JUMP_FLOOR:g} rad)')
        if b.theta_dot is not None:
            before = a.theta_dot
            limit = self._acceleration_limit
            for j, v in enumerate(b.theta_dot):
                if abs(v) > 2.0 * speed[j] or (
                        before is not None and abs(v - before[j]) > limit[j] * dt
                        + VELOCITY_FLOOR):
                    after = '' if before is None else \
                        f' after {before[j]:.6g} rad/s {dt:.6g} s before'
                    return 'implausible_velocity', (f'θ̇ of {self.names[j]} is {v:.6g} '
                                                    f'rad/s{after}')
        if b.tau is not None and a.tau is not None:
            shown = max(self._effort_shown, max(abs(x) for x in a.tau))
            limit = FACTOR * shown + EFFORT_FLOOR
            for j, (x, y) in enumerate(zip(b.tau, a.tau)):
                if abs(x - y) > limit:
                    return 'implausible_effort', (f'τ of {self.names[j]} changed by '
                                                  f'{abs(x - y):.6g} N m (allowed: {limit:.3g} '
                                                  f'N m, {FACTOR:g} x the {shown:.3g} N m '
                                                  'shown)')
        return None

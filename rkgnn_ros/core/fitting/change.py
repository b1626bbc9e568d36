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
A change of the arm's dynamics, told from the residual of the model in use.

When the arm picks up a payload, swaps a tool or wears, the model that explained its
torque (or its closed loop's equation) stops explaining it, at once and on the joints that
carry the change. :class:`ChangeDetector` tests the model's residual on the newest filtered
samples against the residual's normal level per joint, measured where the model was fitted
(its held-out RMS residual, floored at :data:`~.policy.CHANGE_RELATIVE_FLOOR` of the
joint's torque spread: a model fitted to rounding would otherwise call any rounding a
change). The test is a generalised likelihood ratio for a jump of the residual's scale in a block
of new samples: the block's mean squared normalised residual (its statistic), about 1
while nothing changed. The new samples of a check are cut into blocks of
:data:`~.policy.CHANGE_BLOCK_S` (one check may judge seconds of them when it came late, and
a change in their last quarter second must not be averaged away by what came before it). A
block whose statistic reaches :data:`~.policy.CHANGE_ALARM` on a joint (over at least
:data:`~.policy.CHANGE_MIN_ROWS` samples) opens a suspect (:attr:`ChangeDetector.suspect`:
the model is not refitted meanwhile), a block below it on every joint closes it. The
evidence of a joint's run of passing blocks is the product of their statistics over the
alarm; the change is declared once a run of at least two blocks holds
:data:`~.policy.CHANGE_EVIDENCE` of it, or one block alone holds
:data:`~.policy.CHANGE_EVIDENCE_AT_ONCE`, at the suspect's onset. A model's residual is not
Gaussian: where it misses a little of the motion (friction at a reversal, a closed loop's
integral) it comes in bursts of up to a second at tens of times its normal square; a
payload's stays hundreds to thousands of times above it for as long as the payload is
carried. So a large change is declared on its second block, one thousands of times over
the alarm on its first, a burst never, a small lasting change (wear) after the blocks that
make up the evidence. The residual's normal
level is measured on the model's own held-out data, with the encoders' noise in it, and the
rigid-body model is global, so new motion does not raise it; an alarm this far above 1
keeps a model somewhat worse on motion it never saw from counting as a change. The time of
the change is where the stretch of large residuals begins, in the run's first block or the
one before it: the sample from which to the block's end the sum of the squared normalised
residual less :data:`~.policy.CHANGE_ONSET`² is largest (the change point of a CUSUM with
that drift).
"""

import math
from typing import NamedTuple, Optional, Sequence

import numpy as np

from .policy import (CHANGE_ALARM, CHANGE_BLOCK_S, CHANGE_EVIDENCE, CHANGE_EVIDENCE_AT_ONCE,
                     CHANGE_LEVEL_GROWTH, CHANGE_MIN_ROWS, CHANGE_ONSET, CHANGE_RELATIVE_FLOOR)

__all__ = ['Change', 'ChangeDetector']


class Change(NamedTuple):
    """A change of the dynamics: when (s, in the samples' time), on which joints, how large."""

    time: float
    joints: tuple            # indices of the joints whose statistic passed
    statistic: np.ndarray    # per joint: the largest block mean squared normalised residual


class ChangeDetector:
    """Judges blocks of a model's residual against its normal level (module docstring)."""

    def __init__(self):
        self.level: Optional[np.ndarray] = None
        self.last_time = -math.inf
        #: a run of blocks that passed, not yet enough evidence (its onset, joints, statistic)
        self.suspect: Optional[Change] = None
        self._evidence: Optional[np.ndarray] = None   # per joint: log evidence of its run
        self._blocks: Optional[np.ndarray] = None     # per joint: blocks in its run

    def set_normal(self, residual_rms, spread) -> None:
        """
        Take the model's normal residual (RMS per joint) and the torques' spread (n,).

        A level already held rises by at most :data:`~.policy.CHANGE_LEVEL_GROWTH` per call:
        a refit whose newest data hold the first samples of a change (too few to pass the
        test yet) would otherwise raise the level that is to show it.
        """
        residual_rms = np.asarray(residual_rms, dtype=float)
        floor = CHANGE_RELATIVE_FLOOR * np.maximum(np.asarray(spread, dtype=float), 1e-9)
        level = np.maximum(np.where(np.isfinite(residual_rms), residual_rms, np.inf), floor)
        if self.level is not None and self.level.shape == level.shape:
            level = np.minimum(level, CHANGE_LEVEL_GROWTH * self.level)
        self.level = level

    def check(self, residual: np.ndarray, times: Sequence[float]) -> Optional[Change]:
        """
        Judge the samples of ``residual`` (K, n) at ``times`` (K,) after the last judged one.

        Returns the :class:`Change` found, or None.
        """
        if self.level is None:
            return None
        times = np.asarray(times, dtype=float)
        new = times > self.last_time
        if int(new.sum()) < CHANGE_MIN_ROWS:
            return None
        self.last_time = float(times[new][-1])
        times = times[new]
        normalised = np.asarray(residual, dtype=float)[new] / self.level
        start = 0
        for rows in _blocks(times):
            with np.errstate(all='ignore'):
                statistic = np.mean(normalised[rows] ** 2, axis=0)
            statistic = np.where(np.isfinite(statistic), statistic, 0.0)
            change = self._judge(statistic, normalised[start:rows.stop], times[start:rows.stop])
            if change is not None:
                return change
            start = rows.start
        return None

    def _judge(self, statistic: np.ndarray, span: np.ndarray, times: np.ndarray):
        """
        Add one block's ``statistic`` (n,) to the runs; return the declared Change or None.

        ``span``, ``times``: the normalised residual of the block and the one before it (the
        onset of a new run is looked for there).
        """
        passing = statistic >= CHANGE_ALARM
        if not np.any(passing):
            self.suspect = self._evidence = self._blocks = None
            return None
        if self.suspect is None:
            joints = list(np.flatnonzero(passing))
            z2 = np.max(span[:, joints] ** 2, axis=1)
            gain = np.where(np.isfinite(z2), z2, CHANGE_ONSET ** 2) - CHANGE_ONSET ** 2
            first = int(np.argmax(np.cumsum(gain[::-1])[::-1]))
            self.suspect = Change(float(times[first]), (), np.zeros_like(statistic))
            self._evidence = np.zeros_like(statistic)
            self._blocks = np.zeros(statistic.shape, dtype=int)
        with np.errstate(divide='ignore'):
            gain = np.log(np.maximum(statistic, 1e-300) / CHANGE_ALARM)
        self._evidence = np.where(passing, self._evidence + gain, 0.0)
        self._blocks = np.where(passing, self._blocks + 1, 0)
        suspect = self.suspect
        joints = tuple(sorted(set(suspect.joints) | {int(j) for j in np.flatnonzero(passing)}))
        self.suspect = Change(suspect.time, joints, np.maximum(suspect.statistic, statistic))
        if np.any(((self._blocks >= 2) & (self._evidence >= math.log(CHANGE_EVIDENCE)))
                  | (self._evidence >= math.log(CHANGE_EVIDENCE_AT_ONCE))):
            found = self.suspect
            self.suspect = self._evidence = self._blocks = None
            return found
        return None


def _blocks(times: np.ndarray):
    """
    Yield index slices of ``times`` (s, ascending) in blocks of :data:`CHANGE_BLOCK_S`.

    A block of fewer than :data:`CHANGE_MIN_ROWS` samples joins the one before it (the
    first, short or not, is kept: the caller has at least that many in all).
    """
    count = min(int((times[-1] - times[0]) / CHANGE_BLOCK_S), times.size)   # no empty ones
    edges = np.searchsorted(times, times[0] + CHANGE_BLOCK_S * np.arange(1, count + 1))
    starts = [0]
    for edge in edges:
        if edge - starts[-1] >= CHANGE_MIN_ROWS and times.size - edge >= CHANGE_MIN_ROWS:
            starts.append(int(edge))
    ends = starts[1:] + [times.size]
    for a, b in zip(starts, ends):
        yield slice(a, b)

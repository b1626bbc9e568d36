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
A change of the dynamics of an arm without a robot description (case 1).

Where the planar trigonometric arm predicts (:meth:`.case_one.LawKeeper.fit_trig`), its
torque residual on the newest data is what :class:`.change.ChangeDetector` judges: the
measured torque against the arm's inverse dynamics at the measured states, θ̈ the centred
derivative of θ̇ as the torque gate takes it (:func:`~.torque_check.paired_torques`), so the
normal level (the residual's RMS on the held-out part of the fit, once the data span
:data:`~.policy.DETECT_MIN_S`) has the same noise in it. The newest data are judged
with the arm that level was taken from, kept while the keeper drops its loop (a change
makes the loop stop explaining the data, which is when it is dropped). A change is said
with its time; the policy then drops what the data before it built (:mod:`.online`). A check
falls due between two chunks of a generation too (:meth:`TrigChangeMonitor.meanwhile`).
"""

import math
from typing import List, Optional, Sequence

import numpy as np

from .change import Change, ChangeDetector
from .fitness import Interrupted
from .online_records import DynamicsChange, LogLine
from .policy import (CHECK_EVERY_S, CHECK_MAX_S, CHECK_S, DETECT_MIN_S, MIN_SEGMENT_SAMPLES,
                     TRIG_CHANGE_MARGIN_WINDOWS)
from .rigid_change import since
from .trig_loop import data_span
from .validation import split_validation
from ..data import Dataset
from ..differentiate import centred_derivative, CENTRED_ORDER, CENTRED_WINDOW

__all__ = ['ChangedMeanwhile', 'TrigChangeMonitor']


def _residual(arm, segments: Sequence[Dataset], origin: float):
    """Return (residual (K, n), reference torque (K, n), stamp times (K,)), or None."""
    parts = []
    half = CENTRED_WINDOW // 2
    for seg in segments:
        if seg.tau is None or seg.n_samples < max(CENTRED_ORDER + 2, 2 * half + 2):
            continue
        acc = centred_derivative(seg.theta_dot, seg.dt)
        keep = slice(half, seg.n_samples - half)
        with np.errstate(all='ignore'):
            predicted = arm.inverse_dynamics(seg.theta[keep], seg.theta_dot[keep], acc[keep])
        parts.append((predicted - seg.tau[keep], seg.tau[keep], origin + seg.t[keep]))
    if not parts:
        return None
    return tuple(np.concatenate([p[i] for p in parts]) for i in range(3))


class ChangedMeanwhile(Interrupted):
    """A check between two chunks of a generation found a change (``events`` say it)."""

    def __init__(self, events: List[object]):
        super().__init__('the dynamics changed')
        self.events = events


class TrigChangeMonitor:
    """Judges the trigonometric arm's residual (module docstring); keeps where data start."""

    def __init__(self):
        self.detector = ChangeDetector()
        self.since = -math.inf
        self._armed_by = None
        self._last_check = -math.inf

    def due(self, now: float) -> bool:
        """Return whether a check is due at clock ``now`` (it needs a capture)."""
        return self.detector.level is not None and now - self._last_check >= CHECK_EVERY_S

    def recent(self, segments: Sequence[Dataset], origin: float):
        """Return the parts of ``segments`` after the newest change."""
        return since(segments, origin, self.since) if self.since > -math.inf else segments

    def observe(self, capture, loop, fraction: float, now: float, joints):
        """
        Check the capture if due, then re-arm on ``loop``; return the events of a change.

        The newest data are judged before a new loop's level is taken: a loop refitted on
        data that already hold the change would otherwise set a level that hides it. A
        loop is armed on only after a check found the newest data normal (or when nothing
        is armed). Events: a :class:`~.online_records.DynamicsChange` and a log line; []
        if none.
        """
        origin = capture.time_origin
        segments = self.recent(capture.segments(MIN_SEGMENT_SAMPLES, True), origin)
        checked = False
        if self.due(now):
            self._last_check, checked = now, True
            # judged with the arm whose residual's level the detector holds, which may be
            # one the keeper has already dropped for no longer explaining the newest data
            change = self.check(self._armed_by, segments, origin)
            if change is not None:
                names = tuple(joints[j] for j in change.joints)
                statistic = tuple(float(v) for v in change.statistic)
                return [DynamicsChange(change.time, names, statistic),
                        LogLine('warning', f'the dynamics changed at {change.time:.3f} s '
                                           f'(joints {list(names)}: residual '
                                           f'{max(statistic):.3g} times its normal square): '
                                           'the data before it are dropped and the arm is '
                                           'fitted again on the data after it')]
        if (checked and self.detector.suspect is None) or self.detector.level is None:
            _, validation, _ = split_validation(segments, fraction, MIN_SEGMENT_SAMPLES)
            self.rearm(loop, validation, origin, data_span(segments))
        return []

    def meanwhile(self, obs, loop, now: float) -> None:
        """
        Between two chunks of a generation: check a new capture when a check is due.

        ``obs`` is the step's observation (its ``recapture`` takes the capture; case torque
        only). A change raises :class:`ChangedMeanwhile` with its events, which ends the
        generation: a change is said within a chunk of evaluation, not a generation.
        """
        if obs.recapture is None or obs.settings.case != 'torque' or not self.due(now):
            return
        events = self.observe(obs.recapture(), loop, obs.settings.validation_fraction, now,
                              obs.joints)
        if events:
            raise ChangedMeanwhile(events)

    def rearm(self, loop, validation: Sequence[Dataset], origin: float, span: float) -> None:
        """Take the normal level of ``loop``'s arm from ``validation`` (once per loop)."""
        if loop is None or loop is self._armed_by or span < DETECT_MIN_S:
            return
        found = _residual(loop.arm, validation, origin)
        if found is None or found[0].shape[0] < 10:
            return
        residual, reference, _ = found
        self.detector.set_normal(np.sqrt(np.mean(residual ** 2, axis=0)),
                                 np.std(reference, axis=0))
        self._armed_by = loop

    def check(self, loop, segments: Sequence[Dataset], origin: float) -> Optional[Change]:
        """
        Judge the samples of ``segments`` not judged yet with ``loop``'s arm.

        At least the newest :data:`CHECK_S` (the filter's edge needs what came before), at
        most the newest :data:`CHECK_MAX_S`: a check that came late behind a generation
        judges what came meanwhile, so the change's onset is where it was. The first check
        of a detector judges the newest :data:`CHECK_S` only (what came before is what the
        arm was fitted on).
        """
        if loop is None or self.detector.level is None or not segments:
            return None
        end = origin + float(segments[-1].t[-1])
        judged = self.detector.last_time if self.detector.last_time > -math.inf else end
        start = max(self.since, end - CHECK_MAX_S, min(end, judged) - CHECK_S)
        found = _residual(loop.arm, since(segments, origin, start), origin)
        if found is None:
            return None
        change = self.detector.check(found[0], found[2])
        if change is not None:
            margin = TRIG_CHANGE_MARGIN_WINDOWS * CENTRED_WINDOW * segments[-1].dt
            self.since = change.time + margin
            self.detector = ChangeDetector()
            self._armed_by = None
        return change

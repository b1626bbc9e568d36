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
Small rules of the online policy (:mod:`.online`), each a function of what it is shown.

Whether the streams are fresh (and what to say when they stop and return), which network
``network.basis: auto`` takes and whether it still waits for the trigonometric arm's first
verdict, and how the excitation memory is fed: kept apart so the policy's class holds the
sequence of decisions, not their details.
"""

import math
from typing import Dict, List, Optional, Tuple

import numpy as np

from .case_one import LawKeeper
from .case_three import ArmKeeper
from .global_fit import is_global
from .memory import MemoryFeed
from .online_records import AUTO_BASIS, LogLine, Observation, OnlineSettings
from .validation import MIN_SEGMENT_SAMPLES, split_validation

__all__ = ['Staleness', 'auto_untried', 'feed_memory', 'stale_stream', 'trig_holds']


def stale_stream(obs: Observation, now: float) -> Optional[Tuple[str, Optional[float]]]:
    """Return ``(stream, age)`` of the first stream not fresh (age None: never), else None."""
    streams = ['state'] if obs.settings.case == 'torque' else ['state', 'command']
    for key in streams:
        last = obs.received.get(key)
        if last is None:
            return key, None
        if now - last > obs.settings.stale_timeout:
            return key, now - last
    return None


class Staleness:
    """Whether the streams the case needs are fresh; says when they stop and return."""

    def __init__(self):
        self.warned = False

    def fresh(self, obs: Observation, now: float, log, set_status) -> bool:
        """Return True if fresh; else set the status (and warn once) and return False."""
        stale = stale_stream(obs, now)
        if stale is None:
            if self.warned:
                self.warned = False
                log('info', 'data is flowing again: the search resumes')
            return True
        key, age = stale
        topic = 'joint_states' if key == 'state' else 'joint_commands'
        if age is None:
            set_status('waiting for data', f'no {topic} accepted yet')
            return False
        if not self.warned:
            self.warned = True
            log('warning', f'{topic}: no data for {age:.1f} s: the search pauses until data '
                           'returns')
        set_status('stale', f'{topic} silent for {age:.1f} s')
        return False


def trig_holds(laws: LawKeeper, arm3: ArmKeeper, case: str, start=None) -> bool:
    """Return whether the arm on the planar trigonometric basis holds (or ``start`` is global)."""
    return ((laws.trig if case == 'torque' else arm3.loop) is not None
            or (start is not None and is_global(start.spec)))


def auto_untried(settings: OnlineSettings, law, laws: LawKeeper, arm3: ArmKeeper) -> bool:
    """
    Return whether ``network.basis: auto`` waits for the trigonometric arm's first verdict.

    Its network is chosen when the search is built and kept until the search restarts (a
    switch would restart it under whoever watches it). Case 1 without a law builds the
    open-loop search at once: it restarts anyway when the law comes, the arm tried by then.
    """
    if settings.network.get('basis') != AUTO_BASIS:
        return False
    if settings.case == 'torque':
        return law is not None and not laws.trig_tried
    return not arm3.tried


def feed_memory(memory: MemoryFeed, settings: OnlineSettings, segments, origin: float
                ) -> Optional[str]:
    """Offer the window's training part (never what validates) to ``memory``; say failures."""
    train = split_validation(segments, settings.validation_fraction, MIN_SEGMENT_SAMPLES)[0]
    try:
        memory.feed(train, origin, settings.case)
    except (ValueError, ArithmeticError, np.linalg.LinAlgError) as exc:
        memory.reset()
        return f'excitation memory cleared: {exc}'
    return None


class EventLog:
    """
    The events one policy step gives, log lines among them, taken at the step's end.

    :meth:`log_throttled` lets a repeating line through at most every ``throttle`` s of
    ``clock`` per key.
    """

    def __init__(self, clock, throttle: float = 1.0):
        self._clock, self._throttle = clock, float(throttle)
        self._events: List[object] = []
        self._times: Dict[str, float] = {}

    def append(self, event) -> None:
        """Queue an event."""
        self._events.append(event)

    def extend(self, events) -> None:
        """Queue events."""
        self._events.extend(events)

    def log(self, level: str, text: str) -> None:
        """Queue a log line ('info', 'warning' or 'error')."""
        self._events.append(LogLine(level, text))

    def log_throttled(self, key: str, level: str, text: str) -> None:
        """Queue a log line unless one of ``key`` was queued less than the throttle ago."""
        now = self._clock()
        if now - self._times.get(key, -math.inf) >= self._throttle:
            self._times[key] = now
            self.log(level, text)

    def take(self) -> List[object]:
        """Return the queued events and start a new list."""
        events, self._events = self._events, []
        return events

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
A wall-time budget shared by the stages of an offline fit.

The budget is wall time, so a stage is not handed a planned share of it: it gets what is
left when it starts (on a busy machine the earlier stages took longer), and the clock is
checked between stages and inside the long ones. :meth:`Budget.left` and
:meth:`Budget.deadline` serve the functions that take a deadline (a
``time.perf_counter()`` value: ``LinearDynamics.fit``, ``refine_lm``); inside
:meth:`Budget.interrupting`, every population evaluation of the thread
(:func:`.fitness.interrupt_on`: costs and rollouts, in chunks of about
:data:`.fitness.CHUNK_S` seconds) raises :class:`.fitness.Interrupted` once the budget is
spent. The clock is injected, so tests can run a budget on a fake one. A command's budget
counts from its process's start (:func:`process_age`: the interpreter and its imports are
part of the wall time its user waits).
"""

from contextlib import contextmanager
import math
import os
import time
from typing import Callable

from .fitness import interrupt_on

__all__ = ['Budget', 'process_age']


class _Either:
    """Set when either of two stop events is set; left: the least of their ``left()``."""

    def __init__(self, first, second):
        self.first, self.second = first, second

    def is_set(self) -> bool:
        return self.first.is_set() or self.second.is_set()

    def left(self) -> float:
        return min(event.left() for event in (self.first, self.second)
                   if hasattr(event, 'left'))


class Budget:
    """
    ``seconds`` of wall time on ``clock``, from the moment it is made.

    Parameters
    ----------
    seconds : float
        The budget (s); 0 spends it at once, inf never.
    clock : callable
        Returns the time in seconds (default ``time.perf_counter``).

    """

    def __init__(self, seconds: float, clock: Callable[[], float] = time.perf_counter):
        seconds = float(seconds)
        if math.isnan(seconds) or seconds < 0.0:
            raise ValueError(f'a time budget must be a number of seconds >= 0, got {seconds}')
        self.seconds = seconds
        self.clock = clock
        self.start = clock()
        self.end = self.start + seconds

    def elapsed(self) -> float:
        """Return the seconds since the budget started."""
        return self.clock() - self.start

    def left(self) -> float:
        """Return the seconds left: 0 once spent, inf for an endless budget."""
        return max(0.0, self.end - self.clock())

    def spent(self) -> bool:
        """Return True once the budget is spent."""
        return self.clock() >= self.end

    def is_set(self) -> bool:
        """Return :meth:`spent`: a budget is a stop event for :func:`.fitness.interrupt_on`."""
        return self.spent()

    def deadline(self, share: float = 1.0) -> float:
        """Return the ``time.perf_counter()`` value ``share`` of what is left from now."""
        left = self.left()
        return math.inf if math.isinf(left) else time.perf_counter() + share * left

    @contextmanager
    def interrupting(self):
        """Stop the thread's population evaluations once the budget is spent (or as before)."""
        previous = interrupt_on(None)
        interrupt_on(self if previous is None else _Either(previous, self))
        try:
            yield self
        finally:
            interrupt_on(previous)


def process_age() -> float:
    """Return the seconds this process has run (from Linux's /proc; 0 where unknown)."""
    try:
        with open('/proc/self/stat', encoding='ascii') as f:
            ticks = float(f.read().rsplit(')', 1)[1].split()[19])
        with open('/proc/uptime', encoding='ascii') as f:
            uptime = float(f.read().split()[0])
        return max(0.0, uptime - ticks / os.sysconf('SC_CLK_TCK'))
    except (OSError, ValueError, IndexError):
        return 0.0

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
A candidate after a change of the dynamics predicts again from the starts since the change.

:class:`Replay` keeps, one per ``every`` seconds of stamp time, the start of a scored
prediction and the inputs it had (the state x0 = [θ, θ̇] and the horizon: its offsets and the
plan over them); :meth:`Replay.again` rolls a new candidate out from those since the change
(:meth:`~rkgnn_ros.core.selfcheck.SelfCheck.replay_from`) and records each rollout as the
candidate's prediction from that start, so its trial is judged as soon as those targets are
measured instead of 2 s after it starts. Each replay costs the prediction thread up to
:data:`REPLAY_MAX` rollouts, and the worker that fits the arm shares the interpreter with it:
after a replay that took c seconds the next one waits :data:`REPLAY_REST` times c of stamp
time (a candidate offered meanwhile is predicted again once that has passed).
"""

from collections import deque
import time
from typing import Callable, Optional

from rkgnn_ros.core.selfcheck import SelfCheck

__all__ = ['REPLAY_MAX', 'REPLAY_REST', 'Replay']

#: A candidate predicts again from at most this many starts, the newest (one per 0.1 s: 4 s
#: of them, 2 s with their 2 s-ahead targets measured); a UR5 rigid-body loop made 28 in
#: 0.09 s of the prediction thread.
REPLAY_MAX = 40
#: After a replay that took c s, the next one waits at least this times c (s of stamp time):
#: replays take at most a quarter of the prediction thread.
REPLAY_REST = 3.0


class Replay:
    """The kept starts (see the module docstring); ``every``: their spacing (s)."""

    def __init__(self, every: float):
        self.every = float(every)
        self._starts: deque = deque()   # (t0, x0, horizon), oldest first
        self._last = None               # the candidate last predicted again
        self._rest_until = -float('inf')  # stamp time (s) before which none is made again

    def clear(self) -> None:
        """Forget the kept starts (the self-check was made anew)."""
        self._starts.clear()

    def keep(self, t0: float, x0, horizon, keep_for: float) -> None:
        """Keep a scored prediction's start and inputs, one per ``every`` s, ``keep_for`` s."""
        starts = self._starts
        if starts and not t0 - starts[-1][0] >= 0.75 * self.every:
            return
        starts.append((t0, x0, horizon))
        while starts and starts[0][0] < t0 - keep_for:
            starts.popleft()

    def again(self, candidate, check: SelfCheck, rollout: Callable,
              now: float) -> Optional[str]:
        """
        Predict with a new ``candidate`` from the starts since a change; return a log line.

        ``rollout(x0, horizon, t0)`` returns the candidate's (θ, θ̇), each (K, n), at the
        horizon's offsets, or None. ``now``: the stamp time (s). Nothing is done for a
        candidate already predicted again, while the last replay's rest lasts (module
        docstring), or when no change is recent (None is returned then, and when no
        prediction was made).
        """
        if candidate is None or candidate is self._last or now < self._rest_until:
            return None
        self._last = candidate
        since = check.replay_from()
        if since is None:
            return None
        clock, made = time.perf_counter(), 0
        for t0, x0, horizon in [s for s in self._starts if s[0] >= since - 1e-9][-REPLAY_MAX:]:
            out = rollout(x0, horizon, t0)
            if out is not None and check.set_candidate(t0, horizon.t, out[0]):
                made += 1
        cost = time.perf_counter() - clock
        self._rest_until = now + REPLAY_REST * cost
        if not made:
            return None
        return (f'predicted again from {made} states since the change at {since:.3f} s (in '
                f'{cost:.2f} s)')

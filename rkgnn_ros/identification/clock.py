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
The clock of the identifier's time rules: the node's clock, made safe to take differences of.

Every time rule of the node (a stream is stale after ``stale_timeout``, data is refreshed
every second, a model is published at most every ``model_publish_period``, log lines are
throttled) must follow the node's clock, so that under ``use_sim_time`` a recording
replayed faster, slower or paused is judged by its own time, not the wall's. Those rules
take differences of times; :class:`NodeSeconds` gives them seconds that advance exactly
as the node's clock does and never run backwards: when the clock jumps back (a recording
played in a loop) it continues from where it was, and before the first ``/clock`` message
(the clock reads zero) it stands still. The stream buffer sees the jump itself, through
the stamps, and clears (reliability item 13).
"""

import threading
from typing import Callable

__all__ = ['NodeSeconds']


class NodeSeconds:
    """
    Seconds elapsed on a node's clock, never decreasing; call it for the current value.

    Parameters
    ----------
    now_ns : callable
        The clock, in nanoseconds (``lambda: node.get_clock().now().nanoseconds``); zero
        means no time yet (``use_sim_time`` before ``/clock``).

    """

    def __init__(self, now_ns: Callable[[], int]):
        self._now_ns = now_ns
        self._lock = threading.Lock()
        self._last_ns = 0
        self._elapsed_ns = 0

    def __call__(self) -> float:
        """Return the seconds the node's clock advanced since it started, in total."""
        now = int(self._now_ns())
        with self._lock:
            if now > 0:
                if self._last_ns > 0 and now > self._last_ns:
                    self._elapsed_ns += now - self._last_ns
                self._last_ns = now   # a jump back: go on from the new reading
            return self._elapsed_ns * 1e-9

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
the stamps, and clears (reliability item 13); the node's clock itself jumping back by more
than :data:`CLOCK_JUMP_S` (``/clock`` reset under ``use_sim_time``) clears the buffer at
once (:func:`watch_clock_jumps`).
"""

import threading
from typing import Callable

from rclpy.clock import JumpThreshold
from rclpy.duration import Duration

__all__ = ['CLOCK_JUMP_S', 'NodeSeconds', 'watch_clock_jumps']

CLOCK_JUMP_S = 1.0  # a node clock jumping back by more clears the buffer


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


def watch_clock_jumps(node, ingestion, jump_s: float = CLOCK_JUMP_S):
    """
    Clear ``ingestion``'s buffer when ``node``'s clock jumps back by more than ``jump_s``.

    The buffered data belong to the old timeline (``Ingestion.clock_reset``). Returns the
    jump handle, to be kept as long as the node.
    """
    def on_jump(jump) -> None:
        try:
            ingestion.clock_reset(-jump.delta.nanoseconds * 1e-9)
        except Exception:  # noqa: B902 - a callback must never raise
            ingestion.drops.internal_error('clock')

    return node.get_clock().create_jump_callback(
        JumpThreshold(min_forward=None, min_backward=Duration(seconds=-jump_s),
                      on_clock_change=False),
        post_callback=on_jump)

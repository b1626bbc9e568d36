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
The identifier's drop accounting: a counter per reason, a throttled log line per reason.

Every part of the node that refuses something (a message, a prediction, a publish that
failed) says so here: :meth:`DropAccount.reject` counts the reason (shown in
``/diagnostics`` as ``drops.<reason>``) and logs it at most once per
:data:`LOG_THROTTLE_S` per topic and reason, naming both (rclpy's
``throttle_duration_sec`` throttles per call site, which would hide every reason but the
first one seen). Drops of the joint streams are counted in the live stream buffer, whose
counters are carried over when the buffer is replaced (:meth:`DropAccount.retire`); the
others here.
"""

import math
import threading
import time
import traceback
from typing import Callable, Dict, Optional, Tuple

from rkgnn_ros.identification.plausibility import PLAUSIBILITY_REASONS
from rkgnn_ros.streams.buffer import DROP_REASONS, StreamBuffer
from rkgnn_ros.wire.conversions import REJECTION_REASONS

__all__ = ['DropAccount', 'LOG_THROTTLE_S', 'NODE_REASONS']

#: Drop reasons the node adds to the buffer's and the conversions' own.
NODE_REASONS = ('no_joints', 'internal_error', 'prediction_non_finite',
                'worker_error') + PLAUSIBILITY_REASONS

#: At most one log line per topic and reason in this many seconds.
LOG_THROTTLE_S = 1.0


class DropAccount:
    """
    Counts every drop by reason and logs it, throttled per topic and reason.

    Parameters
    ----------
    log : callable
        ``log(level, text)``, level 'info' or 'warning'.
    buffer : callable
        Returns the live stream buffer (None while the joints are unknown): the streams'
        drops are counted there.
    alive : callable
        Returns False once the node shuts down: errors then are not counted.
    clock : callable
        Monotonic seconds (the throttle).

    """

    def __init__(self, log: Callable[[str, str], None],
                 buffer: Callable[[], Optional[StreamBuffer]],
                 alive: Callable[[], bool] = lambda: True,
                 clock: Callable[[], float] = time.monotonic):
        self._log = log
        self._buffer = buffer
        self._alive = alive
        self._clock = clock
        #: held while counters are read or carried over (and while the buffer is replaced)
        self.lock = threading.Lock()
        self._retired: Dict[str, int] = {}
        self._extra: Dict[str, int] = {}
        self._log_times: Dict[Tuple[str, str], float] = {}

    def retire(self, buffer: Optional[StreamBuffer]) -> None:
        """Keep the counters of a buffer being replaced; call with :attr:`lock` held."""
        if buffer is not None:
            for reason, count in buffer.counters.items():
                self._retired[reason] = self._retired.get(reason, 0) + count

    def count(self, stream: str, reason: str) -> None:
        """Count one drop of ``reason`` (shown in /diagnostics as ``drops.<reason>``)."""
        buffer = self._buffer()
        if buffer is not None:
            buffer.count_drop(stream, reason)
        else:
            with self.lock:
                self._extra[reason] = self._extra.get(reason, 0) + 1

    def counts(self) -> Dict[str, int]:
        """Return the drops per reason since start (every stream, every buffer)."""
        counts = dict.fromkeys(REJECTION_REASONS + DROP_REASONS + NODE_REASONS, 0)
        with self.lock:
            buffer = self._buffer()
            sources = (dict(self._retired), dict(self._extra))
        live = buffer.counters if buffer is not None else {}
        for source in sources + (live,):
            for reason, count in source.items():
                counts[reason] = counts.get(reason, 0) + count
        return counts

    def log_drop(self, topic: str, reason: str, text: str) -> None:
        """Log a drop at most once per :data:`LOG_THROTTLE_S` per topic and reason."""
        self.warn_throttled((topic, reason), f'{topic}: dropped a message ({reason}): {text}')

    def warn_throttled(self, key, text: str) -> None:
        """Log a warning unless one with the same ``key`` was logged in the last second."""
        now = self._clock()
        with self.lock:
            if now - self._log_times.get(key, -math.inf) < LOG_THROTTLE_S:
                return
            self._log_times[key] = now
        self._log('warning', text)

    def reject(self, topic: str, stream: str, reason: str, text: str) -> None:
        """Count a drop and log it (throttled)."""
        self.count(stream, reason)
        self.log_drop(topic, reason, text)

    def refused(self, topic: str, stream: str, sample) -> bool:
        """Return whether ``sample`` (a parse's result) is a rejection; count it if so."""
        if sample.ok:
            return False
        self.reject(topic, stream, sample.reason, sample.message)
        return True

    def internal_error(self, where: str) -> None:
        """Count and log the exception being handled (unless shutting down)."""
        if not self._alive():
            return  # shutting down (SIGINT): a publish that fails now is not an error
        self.count('node', 'internal_error')
        self.log_drop(where, 'internal_error',
                      f'unexpected error (counted as internal_error)\n{traceback.format_exc()}')

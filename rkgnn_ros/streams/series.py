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
One buffered stream: time-sorted samples in preallocated arrays, and its insertion rules.

What :class:`~rkgnn_ros.streams.buffer.StreamBuffer` keeps per stream (states, commands),
without the lock, the clock-jump rule or the pairing, which are the buffer's. Pure numpy.
"""

from typing import Optional, Tuple

import numpy as np

__all__ = ['SampleSeries']


class SampleSeries:
    """
    Time-sorted samples in preallocated arrays: bounded, amortised O(1) append.

    Rows live in ``[lo, hi)`` of arrays twice the capacity; when the end is reached the
    live rows move to the front. Not thread-safe (the buffer locks).
    """

    def __init__(self, capacity: int, width: int):
        self.capacity = capacity
        self._t = np.empty(2 * capacity)
        self._v = np.empty((2 * capacity, width))
        self._lo = 0
        self._hi = 0

    def __len__(self) -> int:
        return self._hi - self._lo

    @property
    def t(self) -> np.ndarray:
        return self._t[self._lo:self._hi]

    @property
    def values(self) -> np.ndarray:
        return self._v[self._lo:self._hi]

    def last_t(self) -> Optional[float]:
        return float(self._t[self._hi - 1]) if self._hi > self._lo else None

    def clear(self):
        self._lo = self._hi = 0

    def drop_before(self, t_min: float):
        """Evict samples older than ``t_min`` (relative time)."""
        # a stream in order evicts one or two samples per insert: step over them in Python
        # (np.searchsorted on the whole window releases and re-takes the GIL, which costs
        # the executor thread up to a GIL switch interval per message at 1 kHz)
        t = self._t
        for _ in range(8):
            if self._lo == self._hi or not t[self._lo] < t_min:
                return
            self._lo += 1
        self._lo += int(np.searchsorted(self.t, t_min, side='left'))

    def drop_oldest(self):
        self._lo += 1

    def insert(self, k: int, t: float, row: np.ndarray):
        """Insert at sorted position ``k`` (0..len); the caller keeps len < capacity."""
        if self._hi == self._t.size:
            n = len(self)
            self._t[:n] = self._t[self._lo:self._hi]
            self._v[:n] = self._v[self._lo:self._hi]
            self._lo, self._hi = 0, n
        at = self._lo + k
        if at < self._hi:  # numpy copes with the overlapping shift
            self._t[at + 1:self._hi + 1] = self._t[at:self._hi]
            self._v[at + 1:self._hi + 1] = self._v[at:self._hi]
        self._t[at] = t
        self._v[at] = row
        self._hi += 1

    def place(self, rel: float, row: np.ndarray, reorder_tolerance: float,
              min_spacing: float, keep: float) -> Tuple[bool, Optional[str]]:
        """
        Insert a sample at relative time ``rel`` unless a rule drops it.

        The order, duplicate, rate and window rules of :mod:`rkgnn_ros.streams.buffer`:
        ``keep`` seconds behind the newest stay. Returns ``(inserted, reason)``: the drop
        reason when not inserted, ``'overflow'`` also when inserted by evicting the oldest
        (the capacity reached), else None.
        """
        newest = self.last_t()
        if newest is not None and rel < newest - reorder_tolerance:
            return False, 'out_of_order'
        stamps = self.t
        size = stamps.size
        if size == 0 or rel > stamps[-1]:
            k = size
        else:
            k = int(np.searchsorted(stamps, rel, side='left'))
        if k < size and stamps[k] == rel:
            return False, 'duplicate_stamp'
        if (k > 0 and rel - stamps[k - 1] < min_spacing) or \
                (k < size and stamps[k] - rel < min_spacing):
            return False, 'rate_limited'
        horizon = max(rel, stamps[-1] if size else rel) - keep
        before = len(self)
        self.drop_before(horizon)
        k -= before - len(self)
        if k < 0:  # older than the window: nothing to keep
            return False, 'out_of_order'
        reason = None
        if len(self) >= self.capacity:
            if k == 0:
                return False, 'overflow'
            self.drop_oldest()
            reason = 'overflow'
            k -= 1
        self.insert(k, rel, row)
        return True, reason

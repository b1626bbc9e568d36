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

"""A bounded, time-ordered series of samples in contiguous arrays (the self-check's store)."""

import numpy as np

__all__ = ['Series']


class Series:
    """
    A bounded, time-ordered series of (t, row) samples in contiguous arrays.

    :attr:`t` and :attr:`rows` are views of the live samples; appending is amortised O(1)
    and pruning moves a start index, so scoring reads the series as arrays without copying
    it (at 1 kHz the window holds over 10,000 states: rebuilding arrays from Python objects
    on every prediction cost tens of milliseconds).
    """

    def __init__(self):
        self._t = np.empty(0)
        self._rows = None
        self._start = self._end = 0

    def __len__(self):
        return self._end - self._start

    @property
    def t(self) -> np.ndarray:
        """Return the sample times (N,), a view."""
        return self._t[self._start:self._end]

    @property
    def rows(self) -> np.ndarray:
        """Return the samples (N, n), a view."""
        return self._rows[self._start:self._end]

    def _reserve(self, extra: int, width: int) -> None:
        size = len(self)
        if self._rows is None:
            self._rows = np.empty((0, width))
        if self._end + extra <= self._t.size:
            return
        capacity = max(64, 2 * (size + extra))
        t, rows = np.empty(capacity), np.empty((capacity, self._rows.shape[1]))
        t[:size], rows[:size] = self.t, self.rows
        self._t, self._rows, self._start, self._end = t, rows, 0, size

    def append(self, t, row, strict: bool = True) -> bool:
        """Append a sample later than the newest (or as late, ``strict`` False)."""
        if len(self) and (t < self._t[self._end - 1] or strict and t == self._t[self._end - 1]):
            return False
        row = np.asarray(row, dtype=float)
        self._reserve(1, row.size)
        self._t[self._end] = t
        self._rows[self._end] = row
        self._end += 1
        return True

    def extend(self, times: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """
        Append the samples (K,), (K, n) later than every earlier one; return which were.

        A sample is taken when its time is after the newest taken before it (as
        :meth:`append` one by one).
        """
        last = self._t[self._end - 1] if len(self) else -np.inf
        before = np.maximum.accumulate(np.concatenate([[last], times[:-1]]))
        keep = times > before
        times, rows = times[keep], rows[keep]
        if times.size:
            self._reserve(times.size, rows.shape[1])
            self._t[self._end:self._end + times.size] = times
            self._rows[self._end:self._end + times.size] = rows
            self._end += times.size
        return keep

    def replace_from(self, times, rows):
        """Drop samples at or after ``times[0]``, then append (a newer plan overrides)."""
        self._end = self._start + int(np.searchsorted(self.t, times[0], side='left'))
        self.extend(np.asarray(times, dtype=float), np.asarray(rows, dtype=float))

    def prune(self, before, keep: int = 2):
        """
        Drop the samples before ``before``.

        ``keep`` > 0 keeps the last sample before it (for interpolation) and at least
        ``keep`` samples; 0 drops every one.
        """
        drop = int(np.searchsorted(self.t, before, side='left')) - (1 if keep else 0)
        self._start += max(0, min(drop, len(self) - keep))

    def interp(self, when: np.ndarray) -> np.ndarray:
        """Return rows at ``when`` (M,), shape (M, n); NaN outside the series."""
        t, rows = self.t, self.rows
        out = np.full((when.size, rows.shape[1]), np.nan)
        inside = (when >= t[0] - 1e-9) & (when <= t[-1] + 1e-9)
        for j in range(rows.shape[1]):
            out[inside, j] = np.interp(when[inside], t, rows[:, j])
        return out

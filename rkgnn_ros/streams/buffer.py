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
Sliding window of joint streams, paired and resampled into :class:`Dataset` segments.

Pure Python and numpy (no ROS imports), thread-safe: ROS callbacks add samples while the
optimizer thread takes snapshots. Every method takes absolute times in seconds (message
stamps); every add returns an :class:`AddResult` and counts what it drops, per stream and
per reason (:data:`DROP_REASONS`). Nothing raises on bad sample content.

Policies
--------
Time base
    Samples are stored relative to ``time_origin`` (the stamp of the first sample after
    construction or a clear), and the snapshot's ``Dataset.t`` uses that base: wall-clock
    stamps (~1.7e9 s) resolve only 0.24 µs in float64, too coarse for the uniform-grid check
    of ``Dataset``. The grid is ``k * model_step`` in that base, so the grids of successive
    snapshots line up, and a driver that stamps at a steady rate (a multiple of
    1 / model_step) has its samples on the grid itself. With the whole second below the
    first sample as the origin (before), the grid fell between samples wherever the driver
    started within its period, and every resampled θ, θ̇ and τ was interpolated linearly,
    off by up to h²/8 times its second derivative and not consistent with the others (the
    case-1 search on the paper's arm started from a closed-form fit of rollout cost J 0.0019
    in one run of ``bench/online.py``, 0.00076 with the samples themselves).
Validation
    A sample with a shape other than (n,) is ``'bad_shape'``; a non-finite stamp
    ``'bad_stamp'``; NaN/inf in a value ``'non_finite'``; a value beyond
    ``max_abs_value`` ``'out_of_range'`` (it would overflow the interpolation). When
    ``need_tau``, a state without τ (None or NaN) is ``'missing_tau'``; otherwise τ is
    ignored and not stored.
Order, duplicates, bursts
    Each stream is kept sorted. A stamp older than the stream's newest by at most
    ``reorder_tolerance`` is inserted in place; older than that, ``'out_of_order'``. An
    exactly repeated stamp keeps the first sample and counts ``'duplicate_stamp'``. A
    sample closer than ``1 / max_rate_hz`` to an accepted neighbour is decimated as
    ``'rate_limited'``, so stored samples are at least that far apart (never a zero or
    negative dt) and the stored count is bounded by ``(window + gap_threshold +
    reorder_tolerance) * max_rate_hz`` whatever the input rate. Set ``max_rate_hz``
    comfortably above the sensor rate (2x) so jitter does not decimate a normal stream.
    Samples older than the window (plus ``gap_threshold``) are evicted; ``'overflow'``
    (the hard cap ``max_samples`` reached inside the window) stays 0 unless that cap is
    set below the rate bound.
Clock jumps and stamp outliers
    A stamp more than ``clock_jump_threshold`` before its stream's newest, or after the
    newest of every stream, is an outlier: dropped and counted as ``'stamp_outlier'``, the
    buffer untouched. A publisher interleaving stamps from elsewhere with good data (one a
    second, or any number that do not follow each other) therefore clears nothing. Only
    when the stream itself moves, ``jump_samples`` consecutive samples of one stream each
    beyond the threshold and following each other (increasing, at most the threshold
    apart), is it a jump (a simulator reset, a bag replayed from its start). Those samples
    then start the new timeline (the earlier ones were counted as outliers when they came)
    and the result of the last has ``clock_jump=True`` so the caller logs one warning. A
    jump back clears every buffer and the reference, counted as ``'clock_jump'``; a jump
    forward clears the same way, counted as ``'clock_jump_forward'``, when the new
    timeline starts more than ``window + gap_threshold`` after everything buffered
    (nothing buffered could still be used), and is a gap otherwise.
    :meth:`StreamBuffer.clock_reset` clears at once, counted as ``'clock_jump'`` (the
    node's own clock jumped back: ``/clock`` reset under ``use_sim_time``).
Gaps
    Consecutive state samples farther apart than ``gap_threshold`` end a segment; no
    segment crosses a gap. Grid points the command stream does not cover (below) end a
    segment too.
Pairing (only when ``need_desired``)
    The command stream (θd, θ̇d) is interpolated linearly at each time it is needed, from
    the two command samples around it, provided they are at most ``gap_threshold`` apart.
    A time is *covered* when it lies in such an interval, or within ``pair_tolerance``
    (default ``model_step``) of a command sample (the nearest command is then held). A
    state sample newer than the newest command plus ``pair_tolerance`` *waits* (it stays
    buffered and is paired when the commands catch up;
    ``stats()['waiting_for_command']``). A state sample that can no longer be covered
    (older than the first command, or inside a command gap) is excluded from every
    snapshot and counted once as ``'no_command'``. Nothing is overwritten:
    unlike message_filters' ApproximateTimeSynchronizer, no pair replaces another.
Reading
    Readers get copies, never the buffer: :meth:`StreamBuffer.capture` (resampled into
    segments and paired on the grid as :mod:`rkgnn_ros.streams.capture` describes) and
    :meth:`StreamBuffer.reference`, the newest planned trajectory.
"""

from dataclasses import dataclass
import math
import threading
from typing import Dict, NamedTuple, Optional, Sequence, Tuple

import numpy as np
from rkgnn_ros.core.stamps import StampGrid
from rkgnn_ros.streams.capture import Capture, covered_by, PlannedReference, Snapshot
from rkgnn_ros.streams.series import SampleSeries

__all__ = ['DROP_REASONS', 'AddResult', 'Capture', 'PlannedReference', 'Snapshot',
           'StreamBuffer']

#: Counter keys of the buffer (callers add their own, e.g. conversions', by count_drop).
#: All are drops decided when a sample is added, except: 'clock_jump' and
#: 'clock_jump_forward' (events: the sample that triggers them is accepted), 'no_command'
#: (a buffered state the commands can no longer cover, counted once when that is known)
#: and 'resample_failed' (a segment a snapshot could not build; should stay 0).
DROP_REASONS = (
    'bad_stamp', 'bad_shape', 'non_finite', 'out_of_range', 'missing_tau', 'out_of_order',
    'duplicate_stamp', 'rate_limited', 'overflow', 'stamp_outlier', 'clock_jump',
    'clock_jump_forward', 'no_command', 'non_increasing_time', 'over_budget',
    'resample_failed',
)

STREAMS = ('state', 'command', 'reference')


@dataclass(frozen=True)
class AddResult:
    """
    What happened to one added sample.

    ``accepted`` (also the truth value), ``reason`` the drop reason when not accepted, and
    ``clock_jump`` True when this sample made the buffer clear itself (log a warning).
    """

    accepted: bool
    reason: Optional[str] = None
    clock_jump: bool = False

    def __bool__(self) -> bool:
        return self.accepted


_ACCEPTED = AddResult(True)


def _check_times(buffer) -> None:
    """Raise ValueError naming the first of the buffer's times and bounds that is invalid."""
    for name in ('model_step', 'window', 'gap_threshold', 'max_rate_hz',
                 'clock_jump_threshold', 'max_abs_value'):
        value = getattr(buffer, name)
        if not (math.isfinite(value) and value > 0.0):
            raise ValueError(f'{name} must be finite and > 0, got {value}')
    for name in ('reorder_tolerance', 'pair_tolerance'):
        value = getattr(buffer, name)
        if not (math.isfinite(value) and value >= 0.0):
            raise ValueError(f'{name} must be finite and >= 0, got {value}')
    if buffer.window < buffer.model_step:
        raise ValueError(f'window {buffer.window} s is shorter than model_step '
                         f'{buffer.model_step} s')
    if buffer.clock_jump_threshold <= buffer.reorder_tolerance:
        raise ValueError('clock_jump_threshold must exceed reorder_tolerance')


def _check_counts(buffer) -> None:
    """Raise ValueError when the buffer's sample cap or jump count is out of range."""
    if buffer.max_samples < 2:
        raise ValueError(f'max_samples must be >= 2, got {buffer.max_samples}')
    if not 1 <= buffer.jump_samples <= 100:
        raise ValueError(f'jump_samples must be in [1, 100], got {buffer.jump_samples}')


def _settle(buffer, states, commands, settled: float) -> Tuple[int, float]:
    """
    Return ``(uncovered, settled)`` of the states after ``settled``.

    ``uncovered``: how many the commands can no longer cover; ``settled``: the newest state
    time now paired or counted.
    """
    last = commands.last_t()
    if last is None or not len(states):
        return 0, settled
    limit = last - buffer.reorder_tolerance - buffer.pair_tolerance
    stamps = states.t
    a = int(np.searchsorted(stamps, settled, side='right'))
    b = int(np.searchsorted(stamps, limit, side='right'))
    if b <= a:
        return 0, settled
    covered = covered_by(stamps[a:b], commands.t, buffer.gap_threshold, buffer.pair_tolerance)
    return int((~covered).sum()), float(stamps[b - 1])


def _summed(drops: Dict[str, Dict[str, int]]) -> Dict[str, int]:
    """Return the drops per reason summed over the streams."""
    total: Dict[str, int] = {}
    for counts in drops.values():
        for reason, count in counts.items():
            total[reason] = total.get(reason, 0) + count
    return total


class BufferLimits(NamedTuple):
    """The limits of :class:`StreamBuffer` beyond its grid and what it pairs (see there)."""

    reorder_tolerance: float = 0.01
    clock_jump_threshold: float = 1.0
    pair_tolerance: Optional[float] = None
    max_abs_value: float = 1e6
    max_samples: Optional[int] = None
    jump_samples: int = 3
    max_reference_points: int = 10_000


class StreamBuffer:
    """
    Bounded, thread-safe window of joint states and commands for identification.

    Parameters
    ----------
    joints : sequence of str
        The n joint names, in column order.
    model_step : float
        Grid step (s) of the snapshot datasets.
    window : float
        Seconds of newest data a snapshot covers.
    gap_threshold : float
        Longer intervals between samples split segments.
    need_tau : bool
        States must carry τ ('torque' case); Datasets then have ``tau``.
    need_desired : bool
        Pair states with commands θd, θ̇d ('pd_gains', 'unknown'); Datasets then have
        ``theta_d`` and ``theta_d_dot``.
    max_rate_hz : float
        Samples closer than ``1 / max_rate_hz`` are decimated (default 2000).
    reorder_tolerance : float
        How late (s) a sample may arrive and still be inserted in order (default 0.01).
    clock_jump_threshold : float
        A stamp this much (s) older than the newest means the clock jumped back
        (default 1.0; must exceed ``reorder_tolerance``).
    pair_tolerance : float, optional
        How far (s) from a command sample a time counts as covered; default
        ``model_step``.
    max_abs_value : float
        Larger magnitudes are rejected as ``'out_of_range'`` (default 1e6).
    max_samples : int, optional
        Hard cap per stream; default from the rate bound above, at most 2**20.
    jump_samples : int
        Consecutive samples beyond ``clock_jump_threshold`` that make a clock jump
        (default 3; 1 declares a jump on any such sample).
    max_reference_points : int
        Longer references are dropped as ``'over_budget'`` (default 10,000), which bounds
        what is kept of the reference stream to ``max_reference_points * 2n`` floats.

    """

    def __init__(self, joints: Sequence[str], model_step: float, window: float,
                 gap_threshold: float, need_tau: bool, need_desired: bool,
                 max_rate_hz: float = 2000.0, **options):
        (reorder_tolerance, clock_jump_threshold, pair_tolerance, max_abs_value, max_samples,
         jump_samples, max_reference_points) = BufferLimits(**options)
        self.joints = tuple(str(joint) for joint in joints)
        if not self.joints or len(set(self.joints)) != len(self.joints):
            raise ValueError(f'joints must be non-empty and unique, got {self.joints}')
        self.model_step = float(model_step)
        self.window = float(window)
        self.gap_threshold = float(gap_threshold)
        self.max_rate_hz = float(max_rate_hz)
        self.reorder_tolerance = float(reorder_tolerance)
        self.clock_jump_threshold = float(clock_jump_threshold)
        self.pair_tolerance = self.model_step if pair_tolerance is None else float(
            pair_tolerance)
        self.max_abs_value = float(max_abs_value)
        _check_times(self)
        self.need_tau = bool(need_tau)
        self.need_desired = bool(need_desired)
        self.min_spacing = 1.0 / self.max_rate_hz
        span = self.window + self.gap_threshold + self.reorder_tolerance
        if max_samples is None:
            max_samples = min(int(math.ceil(span * self.max_rate_hz)) + 16, 2 ** 20)
        self.max_samples = int(max_samples)
        self.max_reference_points = int(max_reference_points)
        self.jump_samples = int(jump_samples)
        _check_counts(self)
        n = len(self.joints)
        self._n = n
        self._lock = threading.Lock()
        self._series = {
            'state': SampleSeries(self.max_samples, 3 * n if self.need_tau else 2 * n),
            'command': SampleSeries(self.max_samples, 2 * n),
        }
        self._drops = {stream: dict.fromkeys(DROP_REASONS, 0) for stream in STREAMS}
        self._accepted = dict.fromkeys(STREAMS, 0)
        self._origin: Optional[float] = None
        self._epoch = 0
        self._settled = -math.inf  # states up to this relative time are paired or counted
        self._reference = None
        # per stream: the outliers in a row that follow each other, (absolute stamp, row)
        self._outliers = {stream: [] for stream in self._series}
        # a steady driver's jittered stamps back on its grid (core/stamps.py)
        self._grids = {stream: StampGrid() for stream in self._series}

    # ------------------------------------------------------------------ adding samples

    def add_state(self, t: float, theta, theta_dot, tau=None) -> AddResult:
        """
        Add a measured state at stamp ``t`` (s): θ, θ̇ and τ, each shape (n,).

        Returns an :class:`AddResult`; never raises on bad content.
        """
        parts = [theta, theta_dot]
        if self.need_tau:
            if tau is None:
                return self._drop('state', 'missing_tau')
            parts.append(tau)
        row, reason = self._row(parts)
        if reason == 'non_finite' and self.need_tau and np.isfinite(row[:2 * self._n]).all() \
                and np.isnan(row[2 * self._n:]).any():
            reason = 'missing_tau'  # NaN effort means "not filled", as in conversions
        return self._add('state', t, row, reason)

    def add_command(self, t: float, theta_d, theta_d_dot) -> AddResult:
        """
        Add a desired sample at stamp ``t`` (s): θd and θ̇d, each shape (n,).

        Commands are stored (and their staleness tracked) whether or not ``need_desired``.
        """
        row, reason = self._row([theta_d, theta_d_dot])
        return self._add('command', t, row, reason)

    def count_drop(self, stream: str, reason: str):
        """Count a drop decided elsewhere (e.g. a conversions Rejection) with the others."""
        with self._lock:
            counts = self._drops.setdefault(str(stream), {})
            counts[str(reason)] = counts.get(str(reason), 0) + 1

    def _row(self, parts):
        """Return ``(row (len(parts) * n,), None)`` or ``(row or None, reason)``."""
        try:
            arrays = [np.asarray(part, dtype=float) for part in parts]
        except Exception:
            return None, 'bad_shape'
        if any(arr.shape != (self._n,) for arr in arrays):
            return None, 'bad_shape'
        row = np.concatenate(arrays)
        if not np.isfinite(row).all():
            return row, 'non_finite'
        if np.abs(row).max() > self.max_abs_value:
            return row, 'out_of_range'
        return row, None

    def _drop(self, stream: str, reason: str) -> AddResult:
        with self._lock:
            self._drops[stream][reason] += 1
        return AddResult(False, reason)

    def _add(self, stream: str, t, row, reason) -> AddResult:
        try:
            t = float(t)
        except Exception:
            t = math.nan
        if reason is None and not math.isfinite(t):
            reason = 'bad_stamp'
        if reason is not None:
            return self._drop(stream, reason)
        with self._lock:
            return self._insert_locked(stream, t, row)

    def _insert_locked(self, stream: str, t_abs: float, row: np.ndarray) -> AddResult:
        t_abs = self._grids[stream](t_abs)
        series = self._series[stream]
        if self._origin is None:
            self._origin = float(t_abs)
        rel = t_abs - self._origin
        newest, newest_any = series.last_t(), self._newest_locked()
        if (newest is not None and rel < newest - self.clock_jump_threshold) or \
                (newest_any is not None and rel > newest_any + self.clock_jump_threshold):
            return self._outlier_locked(stream, t_abs, row)
        self._outliers[stream].clear()
        jump = False
        if newest_any is not None and rel > newest_any + self.window + self.gap_threshold:
            self._restart_locked(t_abs, 'clock_jump_forward', stream)  # a window < threshold
            jump = True
        return self._place_locked(stream, t_abs, row, jump)

    def _outlier_locked(self, stream: str, t_abs: float, row: np.ndarray) -> AddResult:
        """Count an outlier, or declare the jump that ``jump_samples`` of them in a row make."""
        run = self._outliers[stream]
        if run and not 0.0 < t_abs - run[-1][0] <= self.clock_jump_threshold:
            run.clear()  # does not follow the previous outlier: a new run
        run.append((t_abs, row))
        if len(run) < self.jump_samples:
            self._drops[stream]['stamp_outlier'] += 1
            return AddResult(False, 'stamp_outlier')
        samples = list(run)
        run.clear()
        start = samples[0][0] - self._origin
        cleared = True
        newest = self._series[stream].last_t()
        if newest is not None and start < newest:
            self._restart_locked(samples[0][0], 'clock_jump', stream)
        elif start > self._newest_locked() + self.window + self.gap_threshold:
            self._restart_locked(samples[0][0], 'clock_jump_forward', stream)
        else:
            cleared = False  # forward within the window: a gap, the data kept
        result = _ACCEPTED
        for t, values in samples:  # the new timeline from its first sample
            result = self._place_locked(stream, t, values)
        return AddResult(result.accepted, result.reason, cleared)

    def _restart_locked(self, t_abs: float, reason: str, stream: str) -> None:
        """Clear everything and start the time base at ``t_abs``; count ``reason``."""
        self._clear_locked()
        self._drops[stream][reason] += 1
        self._origin = float(t_abs)

    def _place_locked(self, stream: str, t_abs: float, row: np.ndarray,
                      jump: bool = False) -> AddResult:
        """Insert a sample on the current timeline (order, duplicates, rate, window)."""
        inserted, reason = self._series[stream].place(
            t_abs - self._origin, row, self.reorder_tolerance, self.min_spacing,
            self.window + self.gap_threshold)
        if reason is not None:
            self._drops[stream][reason] += 1
        if not inserted:
            return AddResult(False, reason, jump)
        self._accepted[stream] += 1
        return AddResult(True, None, True) if jump else _ACCEPTED

    def _newest_locked(self) -> Optional[float]:
        stamps = [s.last_t() for s in self._series.values() if len(s)]
        return max(stamps) if stamps else None

    def _clear_locked(self):
        for series in self._series.values():
            series.clear()
        for run in self._outliers.values():
            run.clear()
        for grid in self._grids.values():
            grid.reset()
        self._reference = None
        self._origin = None
        self._settled = -math.inf
        self._epoch += 1

    def clear(self):
        """Forget every sample and the reference (counters are kept)."""
        with self._lock:
            self._clear_locked()

    def clock_reset(self) -> bool:
        """
        Clear as a jump back does, counted as ``'clock_jump'`` (the node's clock jumped).

        Returns whether anything was buffered.
        """
        with self._lock:
            had = any(len(series) for series in self._series.values())
            self._clear_locked()
            self._drops['state']['clock_jump'] += 1
            return had

    # ------------------------------------------------------------------ reference

    def add_reference(self, t0: float, times, positions, velocities=None) -> AddResult:
        """
        Keep a planned reference: ``t0 + times`` (K,), θd ``positions`` (K, n).

        ``velocities`` (K, n) θ̇d, or None to estimate them from the positions
        (``np.gradient``; zero for a single point). Replaces the previous reference.
        """
        reference, reason = PlannedReference.checked(t0, times, positions, velocities,
                                                     self._n, self.max_abs_value,
                                                     self.max_reference_points)
        if reference is None:
            return self._drop('reference', reason)
        with self._lock:
            self._reference = reference
            self._accepted['reference'] += 1
        return _ACCEPTED

    def reference(self) -> Optional[PlannedReference]:
        """Return the newest planned trajectory, immutable; None if none came since a clear."""
        with self._lock:
            return self._reference

    def reference_at(self, t) -> Optional[Tuple[np.ndarray, np.ndarray]]:
        """Return :meth:`PlannedReference.at` of the newest reference (None: none)."""
        reference = self.reference()
        return None if reference is None else reference.at(t)

    # ------------------------------------------------------------------ reading

    def latest_state(self) -> Optional[Tuple[float, np.ndarray, np.ndarray]]:
        """Return ``(t, θ (n,), θ̇ (n,))`` of the newest buffered state, or None."""
        with self._lock:
            series = self._series['state']
            if not len(series):
                return None
            row = series.values[-1].copy()
            t = series.last_t() + self._origin
        return t, row[:self._n], row[self._n:2 * self._n]

    def staleness(self, now: float, stream: str = 'command') -> Optional[float]:
        """
        Return the age (s) at ``now`` of the newest sample of a stream, or None.

        None means nothing arrived since construction or the last clear (waiting).
        """
        with self._lock:
            series = self._series.get(stream)
            if series is None:
                raise ValueError(f"stream must be 'state' or 'command', got {stream!r}")
            last = series.last_t()
            if last is None:
                return None
            return float(now) - (last + self._origin)

    def stream_status(self, now: float, stale_after: float, stream: str = 'command') -> str:
        """Return ``'waiting'`` (nothing yet), ``'stale'`` or ``'ok'`` for a stream."""
        age = self.staleness(now, stream)
        if age is None:
            return 'waiting'
        return 'stale' if age > stale_after else 'ok'

    @property
    def time_origin(self) -> Optional[float]:
        """Absolute time (s) of relative time zero (None while empty)."""
        with self._lock:
            return self._origin

    @property
    def counters(self) -> Dict[str, int]:
        """Return the drops per reason, summed over the streams (a copy)."""
        with self._lock:
            self._settle_locked()
            return _summed(self._drops)

    def stats(self) -> dict:
        """
        Return buffered sample counts and counters (copies).

        Keys: ``state_samples``, ``command_samples``, ``waiting_for_command`` (states newer
        than the command coverage), ``has_reference``, ``epoch``, ``time_origin``,
        ``accepted`` (per stream, since construction), ``drops`` (per stream and reason),
        ``counters`` (per reason, all streams).
        """
        with self._lock:
            self._settle_locked()
            states, commands = self._series['state'], self._series['command']
            waiting = 0
            if self.need_desired and len(states):
                last = commands.last_t()
                limit = -math.inf if last is None else last + self.pair_tolerance
                waiting = len(states) - int(np.searchsorted(states.t, limit, side='right'))
            return {
                'state_samples': len(states),
                'command_samples': len(commands),
                'waiting_for_command': waiting,
                'has_reference': self._reference is not None,
                'epoch': self._epoch,
                'time_origin': self._origin,
                'accepted': dict(self._accepted),
                'drops': {stream: dict(c) for stream, c in self._drops.items()},
                'counters': _summed(self._drops),
            }

    def _settle_locked(self):
        """Count, once, the states the command stream can no longer cover."""
        if self.need_desired:
            uncovered, self._settled = _settle(self, self._series['state'],
                                               self._series['command'], self._settled)
            self._drops['state']['no_command'] += uncovered

    def capture(self) -> Capture:
        """Return a consistent copy of the streams (see :class:`Capture`)."""
        with self._lock:
            self._settle_locked()
            states, commands = self._series['state'], self._series['command']
            return Capture(self, (states.t.copy(), states.values.copy()),
                           (commands.t.copy(), commands.values.copy()), self._origin,
                           self._epoch)

    def snapshot(self, min_samples: int = 2, pair_commands: bool = False) -> Snapshot:
        """
        Return the newest ``window`` seconds as uniformly resampled segments.

        A consistent copy taken under the lock and resampled outside it
        (:meth:`Capture.segments`): callbacks keep adding meanwhile, and changing the
        returned arrays never touches the buffer. A segment that cannot be built is counted
        as ``'resample_failed'``.
        """
        capture = self.capture()
        snapshot = capture.segments(min_samples, pair_commands)
        self.count_failures(capture)
        return snapshot

    def count_failures(self, capture: Capture) -> None:
        """Count the segments a capture of this buffer could not build (should be none)."""
        if capture.failures:
            with self._lock:
                self._drops['state']['resample_failed'] += capture.failures

    def controller_samples(self) -> Optional[Dict[str, np.ndarray]]:
        """Return :meth:`Capture.controller_samples` of the streams as they are now."""
        if not self.need_tau:
            return None
        return self.capture().controller_samples()

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
Predictions scored against what the arm then did: the error figures and the record.

A prediction made from the state at time t0 covers [t0, t0 + T]. Its k-ahead error is the
predicted θ at t0 + k minus the measured θ at that time (linear interpolation of the
measured stream). The figure users ask for is the RMSE of those errors divided by the range
of θ, averaged over the joints (:func:`ahead_errors`, :func:`range_normalised_rmse`).

:class:`PredictionRecord` keeps what continuous scoring needs, bounded to a rolling window:
the measured states, the commanded θd that followed, and per prediction its start and its
θ at each scored horizon for the model, a candidate model and what was published. It scores
per horizon, **on the same targets**, the model, the candidate and the two baselines:

- ``follow_reference``: θd at the target time (the arm will be where it was told to go), as
  the plan said at the start when it comes with the prediction (what could have been
  published), else the commanded θd recorded;
- ``hold_last``: θ at the start (the arm will stay where it is).

Predictions over a gap in the measured states are not scored.

What to publish from those scores is :mod:`rkgnn_ros.core.selfcheck`'s.
"""

import math
from typing import Dict, Optional, Sequence, Tuple

import numpy as np

from .series import Series as _Series

__all__ = ['HORIZONS', 'SOURCES', 'BASELINES', 'ahead_errors', 'nrmse', 'range_normalised_rmse',
           'rollout_spread', 'finite_rows', 'at_horizons', 'PredictionRecord']

#: Default horizons (s) scored.
HORIZONS = (0.5, 1.0, 2.0)

#: What can be published: the model and the two baselines.
SOURCES = ('model', 'follow_reference', 'hold_last')
BASELINES = SOURCES[1:]


def ahead_errors(stamps: Sequence[float], times: Sequence[np.ndarray],
                 thetas: Sequence[np.ndarray], meas_t, meas_theta, ahead):
    """
    Errors of every prediction ``ahead`` seconds after its start.

    Parameters
    ----------
    stamps : sequence of float, length M
        Start time t0 of each prediction.
    times : sequence of ndarray, shape (K_m,)
        Offsets from t0 of each prediction's points (``time_from_start``).
    thetas : sequence of ndarray, shape (K_m, n)
        Predicted θ at those points.
    meas_t : ndarray, shape (T,)
        Increasing times of the measured stream.
    meas_theta : ndarray, shape (T, n)
        Measured θ.
    ahead : float
        How far ahead to score (s); a prediction shorter than that is skipped.

    Returns
    -------
    t0 : ndarray, shape (M',)
        Start times of the scored predictions.
    errors : ndarray, shape (M', n)
        Predicted minus measured θ at t0 + ahead.

    """
    meas_t = np.asarray(meas_t, dtype=float)
    meas_theta = np.asarray(meas_theta, dtype=float)
    out_t, out_e = [], []
    if meas_t.size < 2:
        return np.empty(0), np.empty((0, meas_theta.shape[-1] if meas_theta.ndim == 2 else 0))
    for t0, off, th in zip(stamps, times, thetas):
        off = np.asarray(off, dtype=float)
        th = np.asarray(th, dtype=float)
        target = t0 + ahead
        if off.size < 2 or off[-1] < ahead - 1e-9 or target > meas_t[-1] or target < meas_t[0]:
            continue
        pred = np.array([np.interp(ahead, off, th[:, j]) for j in range(th.shape[1])])
        meas = np.array([np.interp(target, meas_t, meas_theta[:, j])
                         for j in range(meas_theta.shape[1])])
        out_t.append(t0)
        out_e.append(pred - meas)
    if not out_t:
        return np.empty(0), np.empty((0, meas_theta.shape[1]))
    return np.asarray(out_t), np.asarray(out_e)


def nrmse(predicted, measured) -> float:
    """θ-NRMSE: RMSE / std of the measured θ per joint, averaged over joints (inf if NaN)."""
    predicted = np.asarray(predicted, dtype=float)
    measured = np.asarray(measured, dtype=float)
    if not np.all(np.isfinite(predicted)):
        return float('inf')
    rmse = np.sqrt(np.mean(np.square(predicted - measured), axis=0))
    return float(np.mean(rmse / np.maximum(np.std(measured, axis=0), 1e-12)))


def range_normalised_rmse(errors, theta_range) -> float:
    """RMSE per joint divided by the θ range per joint, averaged over joints (NaN if empty)."""
    errors = np.asarray(errors, dtype=float)
    if errors.size == 0:
        return float('nan')
    rmse = np.sqrt(np.mean(np.square(errors), axis=0))
    return float(np.mean(rmse / np.maximum(np.asarray(theta_range, dtype=float), 1e-12)))


def rollout_spread(rollouts) -> np.ndarray:
    """
    Return the spread of several rollouts of one prediction: std over members, per time.

    Parameters
    ----------
    rollouts : array_like, shape (M, K, m)
        M rollouts (e.g. the optimizer's elite or an ensemble of models) from one start
        over the same K times; non-finite members are left out.

    Returns
    -------
    ndarray, shape (K, m)
        Standard deviation over the finite members (NaN with fewer than 2).

    """
    rollouts = np.asarray(rollouts, dtype=float)
    if rollouts.ndim != 3:
        raise ValueError(f'rollouts must have shape (M, K, m), got {rollouts.shape}')
    finite = np.all(np.isfinite(rollouts), axis=(1, 2))
    if finite.sum() < 2:
        return np.full(rollouts.shape[1:], np.nan)
    return np.std(rollouts[finite], axis=0, ddof=1)


class PredictionRecord:
    """
    The recent states, commands and predictions, and their scores per horizon.

    Feed it the measured states (:meth:`add_state`), the commanded θd as it becomes known
    (:meth:`add_reference`: ``joint_commands`` samples or the plan's points) and every
    prediction (:meth:`add_prediction`); ask :meth:`scores` and :meth:`rmse`. Times are the
    node's clock in seconds; nothing here reads a clock. Memory is bounded by the window.

    Parameters
    ----------
    n_joints : int
        Number of joints n.
    horizons : sequence of float
        Horizons (s) to score, increasing.
    window : float
        Rolling window (s): predictions whose target time lies in the last ``window``
        seconds of measured states are scored.
    max_gap : float
        A prediction over which the measured states have a gap longer than this (s) is not
        scored: what the arm did there is not known (a driver that stalled, a simulation
        that fell behind its clock and paused).
    rescore_every : float
        The scores are computed again after new data at most this often (s of the states'
        time; 0: on every question). At 1 kHz with a prediction every 10 ms, scoring on
        every prediction took more of the prediction thread than the rollouts.

    """

    def __init__(self, n_joints: int, horizons: Sequence[float] = HORIZONS,
                 window: float = 10.0, max_gap: float = 0.25, rescore_every: float = 0.0):
        horizons = tuple(float(h) for h in horizons)
        if not horizons or any(not (math.isfinite(h) and h > 0.0) for h in horizons) or \
                list(horizons) != sorted(set(horizons)):
            raise ValueError(f'horizons must be positive and increasing, got {horizons}')
        if not (math.isfinite(window) and window > 0.0):
            raise ValueError(f'window must be positive, got {window}')
        self.n = int(n_joints)
        self.horizons = horizons
        self.window = float(window)
        self.max_gap = float(max_gap)
        if not (math.isfinite(rescore_every) and rescore_every >= 0.0):
            raise ValueError(f'rescore_every must be >= 0, got {rescore_every}')
        self.rescore_every = float(rescore_every)
        self._states = _Series()
        self._reference = _Series()
        # per prediction (t: its start), one row: θ at each horizon (H, n) of the model, of
        # the candidate, of the plan and of what was published (NaN: none), and the index
        # in SOURCES of what was published; see _blocks
        self._predictions = _Series()
        self._low = np.full(self.n, np.inf)
        self._high = np.full(self.n, -np.inf)
        self._cache = None         # the table of the recorded data (None: compute it)
        self._memos = {}           # what was derived from that table (scores, rmse, ...)
        self._cache_at = -math.inf  # the newest state's time when it was computed
        self._stale = False        # data came since
        self.hold = False          # True: the scores as they are, not computed again
        self._range_at = np.full(self.n, np.nan)
        #: per-reason counts of samples that were not taken
        self.rejected = {'non_finite': 0, 'out_of_order': 0, 'wrong_shape': 0}

    # -- input ----------------------------------------------------------------------------

    def _row(self, value) -> Optional[np.ndarray]:
        row = np.asarray(value, dtype=float).reshape(-1)
        if row.size != self.n:
            self.rejected['wrong_shape'] += 1
            return None
        if not np.all(np.isfinite(row)):
            self.rejected['non_finite'] += 1
            return None
        return row

    def add_state(self, t: float, theta) -> None:
        """Record a measured θ (n,) at time ``t``; older or duplicate stamps are ignored."""
        row = self._row(theta)
        if row is None or not math.isfinite(t):
            return
        if not self._states.append(float(t), row):
            self.rejected['out_of_order'] += 1
            return
        self._stale = True
        self._low = np.minimum(self._low, row)
        self._high = np.maximum(self._high, row)
        self._prune(float(t))

    def add_states(self, t, theta) -> None:
        """
        Record measured θ in bulk: times (K,), θ (K, n); as :meth:`add_state` one by one.

        Samples with a non-finite value are counted as ``non_finite``, samples not later
        than the newest before them as ``out_of_order``.
        """
        times, rows = self._bulk(t, theta)
        if not times.size:
            return
        taken = self._states.extend(times, rows)
        self.rejected['out_of_order'] += int((~taken).sum())
        if not np.any(taken):
            return
        self._stale = True
        self._low = np.minimum(self._low, rows[taken].min(axis=0))
        self._high = np.maximum(self._high, rows[taken].max(axis=0))
        self._prune(float(self._states.t[-1]))

    def add_references(self, t, theta_d) -> None:
        """Record commanded θd samples in bulk, times (K,), (K, n): each as one sample."""
        times, rows = self._bulk(t, theta_d)
        if times.size:
            self._stale = True
            self.rejected['out_of_order'] += int((~self._reference.extend(times, rows)).sum())

    def _bulk(self, t, values):
        """Return the finite samples of a bulk input (counting the others), or none."""
        times = np.asarray(t, dtype=float).reshape(-1)
        rows = np.asarray(values, dtype=float).reshape(times.size, -1)
        if rows.shape[1] != self.n:
            self.rejected['wrong_shape'] += times.size
            return times[:0], rows[:0]
        good = np.isfinite(times) & np.all(np.isfinite(rows), axis=1)
        self.rejected['non_finite'] += int((~good).sum())
        return times[good], rows[good]

    def add_reference(self, t, theta_d) -> None:
        """
        Record commanded θd: one sample (t float, θd (n,)) or plan points (t (K,), (K, n)).

        Points at or after the first new time replace what was stored there (a new plan
        overrides the tail of the previous one).
        """
        times = np.atleast_1d(np.asarray(t, dtype=float))
        rows = np.asarray(theta_d, dtype=float).reshape(times.size, -1)
        if rows.shape[1] != self.n:
            self.rejected['wrong_shape'] += 1
            return
        good = np.isfinite(times) & np.all(np.isfinite(rows), axis=1)
        if not np.all(good):
            self.rejected['non_finite'] += int((~good).sum())
        times, rows = times[good], rows[good]
        if times.size == 0:
            return
        self._stale = True
        if np.any(np.diff(times) <= 0.0):
            self.rejected['out_of_order'] += 1
            return
        if times.size == 1:
            if not self._reference.append(float(times[0]), rows[0]):
                self.rejected['out_of_order'] += 1
            return
        self._reference.replace_from(times, rows)

    def add_prediction(self, t0: float, offsets, theta, source: str = 'model',
                       candidate=None, published=None, follow=None) -> None:
        """
        Record the predictions made from time ``t0``, each θ (K, n) at ``offsets`` (K,).

        Horizons past a prediction's end are not scored.

        Parameters
        ----------
        t0 : float
            The start (the measured state's time).
        offsets : array_like, shape (K,)
            Times after ``t0``, increasing, at least two.
        theta : array_like, shape (K, n), or None
            The model's prediction (None: the model made none).
        source : str
            What was published (one of :data:`SOURCES`), so the published stream is
            scored too.
        candidate : array_like, shape (K, n), optional
            A candidate model's prediction from the same start (see :meth:`trial`).
        published : array_like, shape (K, n), optional
            The baseline's θ as published (e.g. the plan's θd); default: the baseline is
            scored from the recorded states and commands.
        follow : array_like, shape (K, n), optional
            The plan's θd at ``offsets`` as known at ``t0``: following the reference is
            scored as it could have been published; default: by the recorded commands.

        """
        if source not in SOURCES:
            raise ValueError(f'source must be one of {SOURCES}, got {source!r}')
        offsets = np.asarray(offsets, dtype=float).reshape(-1)
        if offsets.size < 2 or not math.isfinite(t0):
            self.rejected['wrong_shape' if offsets.size < 2 else 'non_finite'] += 1
            return
        blocks = []   # the model's, the candidate's, the plan's, the published θ (H, n)
        for value in (theta, candidate, follow, None if source == 'model' else published):
            at, reason = at_horizons(self.horizons, self.n, offsets, value)
            if reason:
                self.rejected[reason] += 1
                return
            blocks.append(at)
        if source == 'model':
            blocks[3] = blocks[0]
        row = np.concatenate([b.ravel() for b in blocks] + [[SOURCES.index(source)]])
        if not self._predictions.append(float(t0), row, strict=False):
            self.rejected['out_of_order'] += 1
            return
        self._stale = True

    def _blocks(self) -> Dict[str, np.ndarray]:
        """Return the stored predictions' θ (M, H, n) per kind and 'source' (M,), views."""
        m, size = len(self._predictions), len(self.horizons) * self.n
        rows = self._predictions.rows if m else np.empty((0, 4 * size + 1))
        out = {kind: rows[:, k * size:(k + 1) * size].reshape(m, len(self.horizons), self.n)
               for k, kind in enumerate(('model', 'candidate', 'plan', 'shown'))}
        out['source'] = rows[:, -1]
        return out

    def _prune(self, now: float) -> None:
        keep_from = now - self.window - self.horizons[-1] - 1.0
        self._states.prune(keep_from)
        self._reference.prune(keep_from)
        self._predictions.prune(keep_from, keep=0)

    # -- scoring --------------------------------------------------------------------------

    @property
    def theta_range(self) -> np.ndarray:
        """Return the range of every measured θ so far (n,) (NaN before two states)."""
        span = self._high - self._low
        return np.where(np.isfinite(span), span, np.nan)

    def _table(self) -> Dict[float, Optional[Dict[str, np.ndarray]]]:
        """
        Return horizon -> predictor -> errors (M_h, n) on the scored targets, or None.

        The rows are the predictions whose target lies in the window and whose start and
        target the measured states cover; a predictor without a value for a row has NaN
        there (the model made none, no θd known, ...). While :attr:`hold` is set, the
        table there is (if any) is kept, whatever came since.
        """
        latest = self._states.t[-1] if len(self._states) else -math.inf
        if self._cache is None or self._stale and not self.hold and not (
                0.0 <= latest - self._cache_at < self.rescore_every):
            self._cache = self._compute_table()
            self._memos = {}
            self._cache_at, self._stale = latest, False
            self._range_at = self.theta_range      # the scores' scale, with the table
        return self._cache

    def _memo(self, key, compute):
        """Return ``compute()``, computed once per table (the scores change only with it)."""
        self._table()
        if key not in self._memos:
            self._memos[key] = compute()
        return self._memos[key]

    def _compute_table(self) -> Dict[float, Optional[Dict[str, np.ndarray]]]:
        out: Dict[float, Optional[Dict[str, np.ndarray]]] = dict.fromkeys(self.horizons)
        if len(self._states) < 2 or not len(self._predictions):
            return out
        latest = self._states.t[-1]
        t0 = self._predictions.t
        stacks = self._blocks()                                         # (M, H, n)
        published = stacks['source']
        start = self._states.interp(t0)                                  # (M, n)
        have_reference = len(self._reference) >= 2
        stamps = self._states.t
        gaps = np.flatnonzero(np.diff(stamps) > self.max_gap)
        for i, h in enumerate(self.horizons):
            target = t0 + h
            select = (target <= latest + 1e-9) & (target >= latest - self.window)
            for g in gaps:  # what the arm did over a gap is not known
                select &= ~((t0 < stamps[g + 1]) & (target > stamps[g]))
            if not np.any(select):
                continue
            truth = self._states.interp(target[select])
            valid = np.all(np.isfinite(truth), axis=1) & np.all(
                np.isfinite(start[select]), axis=1)
            truth = truth[valid]
            follow = stacks['plan'][select, i][valid]
            if have_reference:   # no plan given with a prediction: the recorded commands
                missing = ~np.all(np.isfinite(follow), axis=1)
                follow[missing] = self._reference.interp(target[select][valid][missing])
            errors = {'model': stacks['model'][select, i][valid] - truth,
                      'candidate': stacks['candidate'][select, i][valid] - truth,
                      'follow_reference': follow - truth,
                      'hold_last': start[select][valid] - truth}
            shown = stacks['shown'][select, i][valid] - truth
            chosen = published[select][valid]
            recorded = np.all(np.isfinite(shown), axis=1)
            for name in BASELINES:       # a baseline published without its θ: as recorded
                rows = (chosen == SOURCES.index(name)) & ~recorded
                shown[rows] = errors[name][rows]
            errors['published'] = shown
            errors['target'] = target[select][valid]
            out[h] = errors
        return out

    def _nrmse(self, errors: np.ndarray, rows: np.ndarray) -> float:
        return float(np.mean(self._per_joint(errors, rows)))

    def _per_joint(self, errors: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """Return the RMSE / θ range of each joint (n,) over ``rows`` (NaN: no rows)."""
        if not np.any(rows):
            return np.full(self.n, np.nan)
        rmse = np.sqrt(np.mean(np.square(errors[rows]), axis=0))
        return rmse / np.maximum(self._range_at, 1e-12)

    def scores(self) -> Dict[float, Dict[str, float]]:
        """
        Return horizon -> predictor -> windowed range-normalised RMSE, and the counts.

        Predictors are ``model``, ``follow_reference`` (when θd is known), ``hold_last``,
        ``published`` (what was actually published) and ``candidate`` (while one is
        scored); ``count`` and ``candidate_count`` are the numbers of scored predictions
        of the model and of the candidate at that horizon. The baselines are scored on the
        model's targets once it has some. Empty for a horizon with nothing scored yet. A
        predictor's score is the mean over the joints of :meth:`joint_scores`.
        The result is shared until the scores are computed again: do not change it.
        """
        return self._memo(('scores',), lambda: {
            h: {name: float(np.mean(v)) if isinstance(v, np.ndarray) else v
                for name, v in row.items()}
            for h, row in self.joint_scores().items()})

    def joint_scores(self) -> Dict[float, Dict[str, object]]:
        """
        Return horizon -> predictor -> windowed RMSE / θ range per joint, (n,) each.

        The predictors, targets and counts of :meth:`scores` (which averages these over the
        joints); shared until the scores are computed again: do not change it.
        """
        return self._memo(('joint_scores',), self._joint_scores)

    def _joint_scores(self) -> Dict[float, Dict[str, object]]:
        """See :meth:`joint_scores`."""
        out = {}
        for h, errors in self._table().items():
            if errors is None or not errors['hold_last'].shape[0]:
                out[h] = {}
                continue
            has_model = finite_rows(errors['model'])
            count = int(has_model.sum())
            base = has_model if count else np.ones(has_model.shape, dtype=bool)
            row = {'model': self._per_joint(errors['model'], has_model), 'count': count}
            for name in BASELINES:
                rows = base & finite_rows(errors[name])
                if np.any(rows):
                    row[name] = self._per_joint(errors[name], rows)
            row['published'] = self._per_joint(errors['published'],
                                               finite_rows(errors['published']))
            has_candidate = finite_rows(errors['candidate'])
            if np.any(has_candidate):
                row['candidate'] = self._per_joint(errors['candidate'], has_candidate)
                row['candidate_count'] = int(has_candidate.sum())
            out[h] = row
        return out

    def rmse(self, predictor: str = 'published') -> Dict[float, np.ndarray]:
        """Return horizon -> windowed RMSE per joint (rad) of one predictor (NaN if none)."""
        return self._memo(('rmse', predictor), lambda: self._rmse(predictor))

    def _rmse(self, predictor: str) -> Dict[float, np.ndarray]:
        out = {}
        for h, errors in self._table().items():
            e = None if errors is None else errors.get(predictor)
            if e is not None:
                e = e[finite_rows(e)]
            out[h] = (np.sqrt(np.mean(np.square(e), axis=0)) if e is not None and e.size
                      else np.full(self.n, np.nan))
        return out

    def _reached(self, kind: str) -> Tuple[float, ...]:
        """Return the horizons that a prediction of ``kind`` in the scores reaches."""
        return self._memo(('reached', kind), lambda: self._reaching(kind))

    def _reaching(self, kind: str) -> Tuple[float, ...]:
        if not len(self._predictions):
            return ()
        reach = np.any(np.all(np.isfinite(self._blocks()[kind]), axis=2), axis=0)   # (H,)
        return tuple(h for h, hit in zip(self.horizons, reach) if hit)

    def error_integral(self, t_from: float, t_to: float) -> Optional[np.ndarray]:
        """
        Return ∫ (θd − θ) dt (n,) from ``t_from`` to ``t_to`` over the recorded streams.

        What a servo's integral term accumulated; the trapezoid rule on the measured
        states' times, θd interpolated at them. None when the states do not reach back to
        ``t_from`` or no θd is recorded.
        """
        if len(self._states) < 2 or len(self._reference) < 2 or not t_to >= t_from:
            return None
        t = self._states.t
        if t_from < t[0] - 1e-9:
            return None
        inner = t[(t > t_from) & (t < t_to)]
        times = np.concatenate([[t_from], inner, [t_to]])
        e = self._reference.interp(times) - self._states.interp(times)
        if not np.all(np.isfinite(e)):
            return None
        return np.sum(0.5 * (e[1:] + e[:-1]) * np.diff(times)[:, None], axis=0)


def at_horizons(horizons, n: int, offsets: np.ndarray, theta):
    """
    Return a prediction's θ at the ``horizons``, (H, n), NaN past its end, and why not.

    ``theta`` (K, n) at ``offsets`` (K,), linear in between (np.interp's); None gives NaN
    throughout. Returns ``(None, reason)`` ('wrong_shape', 'non_finite') when unusable.
    """
    at = np.full((len(horizons), n), np.nan)
    if theta is None:
        return at, None
    theta = np.asarray(theta, dtype=float)
    if theta.shape != (offsets.size, n):
        return None, 'wrong_shape'
    if not np.all(np.isfinite(theta)):
        return None, 'non_finite'
    h = np.asarray(horizons)
    inside = (h >= offsets[0] - 1e-9) & (h <= offsets[-1] + 1e-9)
    if np.any(inside):
        h = np.clip(h[inside], offsets[0], offsets[-1])
        right = np.clip(np.searchsorted(offsets, h, side='right'), 1, offsets.size - 1)
        w = ((h - offsets[right - 1]) / (offsets[right] - offsets[right - 1]))[:, None]
        at[inside] = (1.0 - w) * theta[right - 1] + w * theta[right]
    return at, None


def finite_rows(errors: np.ndarray) -> np.ndarray:
    """Return which rows of ``errors`` (M, n) are finite in every column, (M,)."""
    return np.all(np.isfinite(errors), axis=1)

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
Scoring predictions against what the arm then did, and deciding what is fit to publish.

A prediction made from the state at time t0 covers [t0, t0 + T]. Its k-ahead error is the
predicted θ at t0 + k minus the measured θ at that time (linear interpolation of the
measured stream). The figure users ask for is the RMSE of those errors divided by the range
of θ, averaged over the joints (:func:`ahead_errors`, :func:`range_normalised_rmse`).

:class:`SelfCheck` does this continuously, without ROS: it keeps the recent predictions
(start, θ at each scored horizon, what was published), the measured states and the
commanded θd that followed, and scores per horizon, over a rolling window, three
predictors **on the same targets**:

- ``model``: the identified model's prediction;
- ``follow_reference``: θd at the target time (the arm will be where it was told to go);
- ``hold_last``: θ at the start (the arm will stay where it is).

:meth:`SelfCheck.decide` says what to publish, the model or the better baseline (marked,
with the reason). Trust is earned, never assumed, and lost at once:

- until the model has ``min_scored`` scored predictions at every horizon it reaches, the
  best-scoring baseline is published;
- the model is published once its error is at least ``margin`` below each baseline's at
  every horizon, over the window and over its last ``recent`` seconds;
- it is set aside as soon as it is worse than a baseline at any horizon, over either span.

A score can only come a horizon after the prediction, so a model that turns bad is
published for at least that long; the short span and the margin keep such stretches short
and rare, the band between the two thresholds keeps the choice from flapping.

Uncertainty. :meth:`SelfCheck.uncertainty` is the published predictor's recent RMSE per
horizon and joint, interpolated between the scored horizons (0 at the start, which is a
measured state): an error bar measured on this arm, lately, so it is calibrated by
construction. :func:`rollout_spread` (the spread of several rollouts, e.g. the
optimizer's elite or an ensemble) is available as a model-side signal, but it measures the
search's spread, which shrinks as the search converges whether the model is right or not;
the node should publish the self-check's figure and may use the spread before any score
exists.
"""

from collections import deque
from dataclasses import dataclass, field
import math
from typing import Dict, NamedTuple, Optional, Sequence, Tuple

import numpy as np

#: Default horizons (s) scored by :class:`SelfCheck`.
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


@dataclass(frozen=True)
class Decision:
    """
    What to publish, and why.

    Attributes
    ----------
    source : str
        One of :data:`SOURCES`.
    reason : str
        One sentence for logs and ``/diagnostics``.
    scored : bool
        Whether the model had enough scored predictions at every horizon.
    scores : dict
        Horizon (s) -> {predictor: windowed range-normalised RMSE}, as
        :meth:`SelfCheck.scores`.

    """

    source: str
    reason: str
    scored: bool
    scores: Dict[float, Dict[str, float]] = field(default_factory=dict)

    @property
    def is_baseline(self) -> bool:
        """Return whether a baseline is to be published instead of the model."""
        return self.source != 'model'


class _Series:
    """A bounded, time-ordered series of (t, row) samples."""

    def __init__(self):
        self.t: deque = deque()
        self.rows: deque = deque()

    def __len__(self):
        return len(self.t)

    def append(self, t, row) -> bool:
        if self.t and t <= self.t[-1]:
            return False
        self.t.append(t)
        self.rows.append(row)
        return True

    def replace_from(self, times, rows):
        """Drop samples at or after ``times[0]``, then append (a newer plan overrides)."""
        while self.t and self.t[-1] >= times[0]:
            self.t.pop()
            self.rows.pop()
        for t, row in zip(times, rows):
            self.append(t, row)

    def prune(self, before):
        while len(self.t) > 2 and self.t[1] < before:
            self.t.popleft()
            self.rows.popleft()

    def interp(self, when: np.ndarray) -> np.ndarray:
        """Return rows at ``when`` (M,), shape (M, n); NaN outside the series."""
        t = np.fromiter(self.t, float, len(self.t))
        rows = np.array(self.rows)
        out = np.full((when.size, rows.shape[1]), np.nan)
        inside = (when >= t[0] - 1e-9) & (when <= t[-1] + 1e-9)
        for j in range(rows.shape[1]):
            out[inside, j] = np.interp(when[inside], t, rows[:, j])
        return out


class Verdict(NamedTuple):
    """A candidate model's trial against the model in use, on the same targets."""

    better: bool        # the candidate's error is at most the model's
    candidate: float    # its windowed error, mean over the scored horizons
    model: float        # the model's on the same targets (NaN: there was none)


class SelfCheck:
    """
    Continuous scoring of predictions against the baselines, and the publish decision.

    Feed it the measured states (:meth:`add_state`), the commanded θd as it becomes known
    (:meth:`add_reference`: ``joint_commands`` samples or the plan's points) and every
    prediction (:meth:`add_prediction`); ask :meth:`scores`, :meth:`decide` and
    :meth:`uncertainty`. Times are the node's clock in seconds; nothing here reads a clock.

    A second model, the *candidate*, can be scored beside the model in use on the same
    starts (:meth:`add_prediction`'s ``candidate``): :meth:`trial` compares the two once the
    candidate has ``min_scored`` scored predictions at every horizon it reaches, and
    :meth:`promote` makes it the model (its scores come with it) or
    :meth:`discard_candidate` forgets it. So a new model is judged on what it predicted
    before anything it predicts is published.

    Parameters
    ----------
    n_joints : int
        Number of joints n.
    horizons : sequence of float
        Horizons (s) to score, increasing.
    window : float
        Rolling window (s): predictions whose target time lies in the last ``window``
        seconds of measured states are scored.
    margin : float
        How much better than each baseline (a share of its error) the model must be to be
        published; it is set aside when worse (see the module docstring).
    min_scored : int
        Scored predictions needed at every horizon a predictor reaches before it is judged
        (and in the last ``recent`` seconds, for that span to count).
    recent : float
        The short span (s) of the newest targets, judged beside the window.

    """

    def __init__(self, n_joints: int, horizons: Sequence[float] = HORIZONS,
                 window: float = 10.0, margin: float = 0.2, min_scored: int = 10,
                 recent: float = 2.0):
        horizons = tuple(float(h) for h in horizons)
        if not horizons or any(not (math.isfinite(h) and h > 0.0) for h in horizons) or \
                list(horizons) != sorted(set(horizons)):
            raise ValueError(f'horizons must be positive and increasing, got {horizons}')
        if not (math.isfinite(window) and window > 0.0):
            raise ValueError(f'window must be positive, got {window}')
        if not (math.isfinite(margin) and 0.0 <= margin < 1.0):
            raise ValueError(f'margin must be in [0, 1), got {margin}')
        if not (math.isfinite(recent) and 0.0 < recent <= window):
            raise ValueError(f'recent must be in (0, window], got {recent}')
        self.n = int(n_joints)
        self.horizons = horizons
        self.window = float(window)
        self.margin = float(margin)
        self.min_scored = max(1, int(min_scored))
        self.recent = float(recent)
        self._states = _Series()
        self._reference = _Series()
        # per prediction: start, θ at each horizon (H, n) of the model, of the candidate and
        # of what was published (NaN: none), and the published source
        self._t0: deque = deque()
        self._model: deque = deque()
        self._candidate: deque = deque()
        self._published_at: deque = deque()
        self._published: deque = deque()
        self._low = np.full(self.n, np.inf)
        self._high = np.full(self.n, -np.inf)
        self._on_model = False     # the model is published (it earned it and kept it)
        self._cache = None         # the table of the recorded data, until they change
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
        self._cache = None
        self._low = np.minimum(self._low, row)
        self._high = np.maximum(self._high, row)
        self._prune(float(t))

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
        self._cache = None
        if np.any(np.diff(times) <= 0.0):
            self.rejected['out_of_order'] += 1
            return
        if times.size == 1:
            if not self._reference.append(float(times[0]), rows[0]):
                self.rejected['out_of_order'] += 1
            return
        self._reference.replace_from(times, rows)

    def _at_horizons(self, offsets: np.ndarray, theta) -> Optional[np.ndarray]:
        """Return θ (K, n) at the horizons (H, n), NaN past its end; None if unusable."""
        if theta is None:
            return np.full((len(self.horizons), self.n), np.nan)
        theta = np.asarray(theta, dtype=float)
        if theta.shape != (offsets.size, self.n):
            self.rejected['wrong_shape'] += 1
            return None
        if not np.all(np.isfinite(theta)):
            self.rejected['non_finite'] += 1
            return None
        at = np.full((len(self.horizons), self.n), np.nan)
        for i, h in enumerate(self.horizons):
            if offsets[0] - 1e-9 <= h <= offsets[-1] + 1e-9:
                at[i] = [np.interp(h, offsets, theta[:, j]) for j in range(self.n)]
        return at

    def add_prediction(self, t0: float, offsets, theta, source: str = 'model',
                       candidate=None, published=None) -> None:
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

        """
        if source not in SOURCES:
            raise ValueError(f'source must be one of {SOURCES}, got {source!r}')
        offsets = np.asarray(offsets, dtype=float).reshape(-1)
        if offsets.size < 2 or not math.isfinite(t0):
            self.rejected['wrong_shape' if offsets.size < 2 else 'non_finite'] += 1
            return
        model = self._at_horizons(offsets, theta)
        other = None if model is None else self._at_horizons(offsets, candidate)
        shown = (model.copy() if source == 'model' and model is not None
                 else self._at_horizons(offsets, published))
        if model is None or other is None or shown is None:
            return
        self._cache = None
        self._t0.append(float(t0))
        self._model.append(model)
        self._candidate.append(other)
        self._published_at.append(shown)
        self._published.append(source)

    def _prune(self, now: float) -> None:
        keep_from = now - self.window - self.horizons[-1] - 1.0
        self._states.prune(keep_from)
        self._reference.prune(keep_from)
        while self._t0 and self._t0[0] < keep_from:
            for store in (self._t0, self._model, self._candidate, self._published_at,
                          self._published):
                store.popleft()

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
        there (the model made none, no θd known, ...).
        """
        if self._cache is None:
            self._cache = self._compute_table()
        return self._cache

    def _compute_table(self) -> Dict[float, Optional[Dict[str, np.ndarray]]]:
        out: Dict[float, Optional[Dict[str, np.ndarray]]] = dict.fromkeys(self.horizons)
        if len(self._states) < 2 or not self._t0:
            return out
        latest = self._states.t[-1]
        t0 = np.fromiter(self._t0, float, len(self._t0))
        stacks = {'model': np.array(self._model), 'candidate': np.array(self._candidate),
                  'shown': np.array(self._published_at)}                  # (M, H, n)
        published = np.array(self._published)
        start = self._states.interp(t0)                                  # (M, n)
        have_reference = len(self._reference) >= 2
        for i, h in enumerate(self.horizons):
            target = t0 + h
            select = (target <= latest + 1e-9) & (target >= latest - self.window)
            if not np.any(select):
                continue
            truth = self._states.interp(target[select])
            valid = np.all(np.isfinite(truth), axis=1) & np.all(
                np.isfinite(start[select]), axis=1)
            truth = truth[valid]
            follow = (self._reference.interp(target[select][valid]) if have_reference
                      else np.full(truth.shape, np.nan))
            errors = {'model': stacks['model'][select, i][valid] - truth,
                      'candidate': stacks['candidate'][select, i][valid] - truth,
                      'follow_reference': follow - truth,
                      'hold_last': start[select][valid] - truth}
            shown = stacks['shown'][select, i][valid] - truth
            chosen = published[select][valid]
            recorded = np.all(np.isfinite(shown), axis=1)
            for name in BASELINES:       # a baseline published without its θ: as recorded
                rows = (chosen == name) & ~recorded
                shown[rows] = errors[name][rows]
            errors['published'] = shown
            errors['target'] = target[select][valid]
            out[h] = errors
        return out

    def _nrmse(self, errors: np.ndarray, rows: np.ndarray) -> float:
        return range_normalised_rmse(errors[rows], self.theta_range) if np.any(rows) \
            else math.nan

    def scores(self) -> Dict[float, Dict[str, float]]:
        """
        Return horizon -> predictor -> windowed range-normalised RMSE, and the counts.

        Predictors are ``model``, ``follow_reference`` (when θd is known), ``hold_last``,
        ``published`` (what was actually published) and ``candidate`` (while one is
        scored); ``count`` and ``candidate_count`` are the numbers of scored predictions
        of the model and of the candidate at that horizon. The baselines are scored on the
        model's targets once it has some. Empty for a horizon with nothing scored yet.
        """
        out = {}
        for h, errors in self._table().items():
            if errors is None or not errors['hold_last'].shape[0]:
                out[h] = {}
                continue
            has_model = _finite_rows(errors['model'])
            count = int(has_model.sum())
            base = has_model if count else np.ones(has_model.shape, dtype=bool)
            row = {'model': self._nrmse(errors['model'], has_model), 'count': count}
            for name in BASELINES:
                rows = base & _finite_rows(errors[name])
                if np.any(rows):
                    row[name] = self._nrmse(errors[name], rows)
            shown = _finite_rows(errors['published'])
            row['published'] = self._nrmse(errors['published'], shown)
            has_candidate = _finite_rows(errors['candidate'])
            if np.any(has_candidate):
                row['candidate'] = self._nrmse(errors['candidate'], has_candidate)
                row['candidate_count'] = int(has_candidate.sum())
            out[h] = row
        return out

    def rmse(self, predictor: str = 'published') -> Dict[float, np.ndarray]:
        """Return horizon -> windowed RMSE per joint (rad) of one predictor (NaN if none)."""
        out = {}
        for h, errors in self._table().items():
            e = None if errors is None else errors.get(predictor)
            if e is not None:
                e = e[_finite_rows(e)]
            out[h] = (np.sqrt(np.mean(np.square(e), axis=0)) if e is not None and e.size
                      else np.full(self.n, np.nan))
        return out

    def _reached(self, store: deque) -> Tuple[float, ...]:
        """Return the horizons that at least one stored prediction of ``store`` reaches."""
        if not store:
            return ()
        reach = np.any(np.all(np.isfinite(np.array(store)), axis=2), axis=0)     # (H,)
        return tuple(h for h, hit in zip(self.horizons, reach) if hit)

    # -- decisions ------------------------------------------------------------------------

    def decide(self, publishable: Sequence[str] = BASELINES) -> Decision:
        """
        Return what to publish now, with the reason (see the module docstring).

        ``publishable`` are the baselines that can be published now (following the
        reference needs the plan over the horizon); holding the last state always can.
        """
        scores = self.scores()
        allowed = [b for b in BASELINES if b in publishable or b == 'hold_last']
        scored = [b for b in allowed if any(b in scores[h] for h in self.horizons)]
        reached = self._reached(self._model)
        counts = [scores[h].get('count', 0) for h in reached]
        if not reached or min(counts) < self.min_scored:
            if scored:
                best = min(scored, key=lambda b: _mean_score(scores, b, self.horizons))
            else:
                best = ('follow_reference' if 'follow_reference' in allowed
                        and len(self._reference) >= 2 else 'hold_last')
            have = min(counts) if counts else 0
            return Decision(best, f'the model has not been scored yet ({have} of '
                            f'{self.min_scored} predictions at every horizon it reaches): '
                            f'publishing {best}', False, scores)
        best = min(scored, key=lambda b: _mean_score(scores, b, reached))
        recent = self._recent_scores(reached)
        checks = [(h, b, row['model'], row[b], span)
                  for span, table in ((f'last {self.window:g} s', scores),
                                      (f'last {self.recent:g} s', recent))
                  for h, row in table.items() if h in reached
                  for b in scored if b in row and math.isfinite(row.get('model', math.nan))]
        was_on_model = self._on_model
        limit = 1.0 if was_on_model else 1.0 - self.margin
        worse = [c for c in checks if not c[2] <= limit * c[3]]
        if not worse:
            self._on_model = True
            why = ('the model is not worse than the baselines' if was_on_model else
                   f'the model is at least {self.margin:.0%} better than the baselines at '
                   'every horizon')
            return Decision('model', why, True, scores)
        self._on_model = False
        h, b, mine, theirs, span = max(worse, key=lambda c: c[2] / max(c[3], 1e-300))
        return Decision(
            best, f"the model's {h:g} s-ahead error over the {span} is {mine:.2%} of the "
            f'range against {theirs:.2%} for {b}'
            + ('' if was_on_model else f' (it must be {self.margin:.0%} better)')
            + f': publishing {best}', True, scores)

    def _recent_scores(self, horizons) -> Dict[float, Dict[str, float]]:
        """Return the model's and the baselines' errors on the targets of the last ``recent`` s."""
        out = {}
        if not len(self._states):
            return out
        since = self._states.t[-1] - self.recent
        for h in horizons:
            errors = self._table()[h]
            if errors is None:
                continue
            rows = _finite_rows(errors['model']) & (errors['target'] >= since - 1e-9)
            if rows.sum() < self.min_scored:
                continue
            out[h] = {'model': self._nrmse(errors['model'], rows)}
            for name in BASELINES:
                both = rows & _finite_rows(errors[name])
                if np.any(both):
                    out[h][name] = self._nrmse(errors[name], both)
        return out

    def trial(self) -> Optional[Verdict]:
        """
        Return the candidate's verdict, or None while it has too few scored predictions.

        The candidate is judged once it has ``min_scored`` scored predictions at every
        horizon it reaches: better when its error, averaged over those horizons, is at most
        the model's on the same targets (always, when the model made no prediction there).
        """
        reached = self._reached(self._candidate)
        if not reached:
            return None
        table = self._table()
        mine, theirs = [], []
        for h in reached:
            errors = table[h]
            if errors is None:
                return None
            has = _finite_rows(errors['candidate'])
            if has.sum() < self.min_scored:
                return None
            common = has & _finite_rows(errors['model'])
            mine.append(self._nrmse(errors['candidate'], common if np.any(common) else has))
            theirs.append(self._nrmse(errors['model'], common))
        candidate = float(np.mean(mine))
        model = float(np.mean(theirs)) if all(math.isfinite(v) for v in theirs) else math.nan
        return Verdict(not candidate > model or not math.isfinite(model), candidate, model)

    def promote(self) -> None:
        """Make the candidate the model: its recorded predictions replace the model's."""
        self._model = self._candidate
        self._candidate = deque(np.full((len(self.horizons), self.n), np.nan)
                                for _ in self._model)
        self._cache = None

    def discard_candidate(self) -> None:
        """Forget the candidate's predictions."""
        for at in self._candidate:
            at[:] = np.nan
        self._cache = None

    def forget_model(self) -> None:
        """Forget the model's predictions (a model that replaced it untried)."""
        for at in self._model:
            at[:] = np.nan
        self._on_model = False
        self._cache = None

    def uncertainty(self, offsets, predictor: str = 'published') -> np.ndarray:
        """
        Return the expected error (RMSE, rad) of a prediction at ``offsets`` (K,), (K, n).

        The recent RMSE of ``predictor`` at the scored horizons, 0 at offset 0 (a measured
        state), linear in between and, past the last horizon, continued with the slope of
        the last interval. NaN while a horizon has no score.
        """
        offsets = np.asarray(offsets, dtype=float).reshape(-1)
        table = self.rmse(predictor)
        knots = np.array((0.0,) + self.horizons)
        values = np.vstack([np.zeros(self.n)] + [table[h] for h in self.horizons])
        out = np.empty((offsets.size, self.n))
        for j in range(self.n):
            out[:, j] = np.interp(offsets, knots, values[:, j])
            past = offsets > knots[-1]
            slope = (values[-1, j] - values[-2, j]) / (knots[-1] - knots[-2])
            out[past, j] = values[-1, j] + max(slope, 0.0) * (offsets[past] - knots[-1])
        return out

    def error_integral(self, t_from: float, t_to: float) -> Optional[np.ndarray]:
        """
        Return ∫ (θd − θ) dt (n,) from ``t_from`` to ``t_to`` over the recorded streams.

        What a servo's integral term accumulated; the trapezoid rule on the measured
        states' times, θd interpolated at them. None when the states do not reach back to
        ``t_from`` or no θd is recorded.
        """
        if len(self._states) < 2 or len(self._reference) < 2 or not t_to >= t_from:
            return None
        t = np.fromiter(self._states.t, float, len(self._states))
        if t_from < t[0] - 1e-9:
            return None
        inner = t[(t > t_from) & (t < t_to)]
        times = np.concatenate([[t_from], inner, [t_to]])
        e = self._reference.interp(times) - self._states.interp(times)
        if not np.all(np.isfinite(e)):
            return None
        return np.sum(0.5 * (e[1:] + e[:-1]) * np.diff(times)[:, None], axis=0)


def _finite_rows(errors: np.ndarray) -> np.ndarray:
    return np.all(np.isfinite(errors), axis=1)


def _mean_score(scores, name: str, horizons) -> float:
    values = [scores[h][name] for h in horizons if name in scores[h]]
    return float(np.mean(values)) if values else math.inf


def baseline(source: str, offsets, theta0, theta_d=None,
             theta_d_dot=None) -> Tuple[np.ndarray, np.ndarray]:
    """
    Return a baseline's prediction θ, θ̇ at ``offsets`` (K,), each (K, n).

    ``hold_last``: θ0 (n,) throughout, θ̇ = 0. ``follow_reference``: the commanded
    ``theta_d``, ``theta_d_dot`` (K, n) at the same times (the plan), returned as they are.
    """
    offsets = np.asarray(offsets, dtype=float).reshape(-1)
    if source == 'hold_last':
        theta0 = np.asarray(theta0, dtype=float).reshape(-1)
        return (np.repeat(theta0[None], offsets.size, 0),
                np.zeros((offsets.size, theta0.size)))
    if source == 'follow_reference':
        if theta_d is None or theta_d_dot is None:
            raise ValueError('follow_reference needs theta_d and theta_d_dot at the offsets')
        return np.asarray(theta_d, dtype=float), np.asarray(theta_d_dot, dtype=float)
    raise ValueError(f'source must be one of {BASELINES}, got {source!r}')

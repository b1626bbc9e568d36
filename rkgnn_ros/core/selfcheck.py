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

:meth:`SelfCheck.decide` says what to publish: the model while its windowed error is not
worse than the better baseline's by more than ``margin`` at any horizon, else that
baseline, marked, with the reason. Once set aside for its score the model must be at least
as good as the baselines at every horizon to return (hysteresis, so the choice does not
flap).
Until the model has ``min_scored`` scored predictions at every horizon the best-scoring
baseline is published: trust is earned, never assumed.

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
from typing import Dict, Optional, Sequence, Tuple

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


class SelfCheck:
    """
    Continuous scoring of predictions against the baselines, and the publish decision.

    Feed it the measured states (:meth:`add_state`), the commanded θd as it becomes known
    (:meth:`add_reference`: ``joint_commands`` samples or the plan's points) and every
    prediction (:meth:`add_prediction`); ask :meth:`scores`, :meth:`decide` and
    :meth:`uncertainty`. Times are the node's clock in seconds; nothing here reads a clock.

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
        The model is published while its error is at most (1 + margin) × the better
        baseline's at every horizon.
    min_scored : int
        Scored predictions needed at every horizon before the model can be published.

    """

    def __init__(self, n_joints: int, horizons: Sequence[float] = HORIZONS,
                 window: float = 10.0, margin: float = 0.05, min_scored: int = 5):
        horizons = tuple(float(h) for h in horizons)
        if not horizons or any(not (math.isfinite(h) and h > 0.0) for h in horizons) or \
                list(horizons) != sorted(set(horizons)):
            raise ValueError(f'horizons must be positive and increasing, got {horizons}')
        if not (math.isfinite(window) and window > 0.0):
            raise ValueError(f'window must be positive, got {window}')
        if not (math.isfinite(margin) and margin >= 0.0):
            raise ValueError(f'margin must be >= 0, got {margin}')
        self.n = int(n_joints)
        self.horizons = horizons
        self.window = float(window)
        self.margin = float(margin)
        self.min_scored = max(1, int(min_scored))
        self._states = _Series()
        self._reference = _Series()
        # per prediction: start, predicted θ at each horizon (H, n), published source
        self._t0: deque = deque()
        self._pred: deque = deque()
        self._published: deque = deque()
        self._low = np.full(self.n, np.inf)
        self._high = np.full(self.n, -np.inf)
        self._demoted = False      # a baseline is published because the model scored worse
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
        if np.any(np.diff(times) <= 0.0):
            self.rejected['out_of_order'] += 1
            return
        if times.size == 1:
            if not self._reference.append(float(times[0]), rows[0]):
                self.rejected['out_of_order'] += 1
            return
        self._reference.replace_from(times, rows)

    def add_prediction(self, t0: float, offsets, theta, source: str = 'model') -> None:
        """
        Record a prediction from time ``t0``: θ (K, n) at ``offsets`` (K,) after it.

        ``source`` is what was published for it (one of :data:`SOURCES`), so that the
        published stream is scored too. Horizons past the prediction's end are not scored.
        """
        if source not in SOURCES:
            raise ValueError(f'source must be one of {SOURCES}, got {source!r}')
        offsets = np.asarray(offsets, dtype=float).reshape(-1)
        theta = np.asarray(theta, dtype=float)
        if theta.shape != (offsets.size, self.n) or offsets.size < 2:
            self.rejected['wrong_shape'] += 1
            return
        if not (math.isfinite(t0) and np.all(np.isfinite(theta))):
            self.rejected['non_finite'] += 1
            return
        at = np.full((len(self.horizons), self.n), np.nan)
        for i, h in enumerate(self.horizons):
            if offsets[0] - 1e-9 <= h <= offsets[-1] + 1e-9:
                at[i] = [np.interp(h, offsets, theta[:, j]) for j in range(self.n)]
        self._t0.append(float(t0))
        self._pred.append(at)
        self._published.append(source)

    def _prune(self, now: float) -> None:
        keep_from = now - self.window - self.horizons[-1] - 1.0
        self._states.prune(keep_from)
        self._reference.prune(keep_from)
        while self._t0 and self._t0[0] < keep_from:
            self._t0.popleft()
            self._pred.popleft()
            self._published.popleft()

    # -- scoring --------------------------------------------------------------------------

    @property
    def theta_range(self) -> np.ndarray:
        """Return the range of every measured θ so far (n,) (NaN before two states)."""
        span = self._high - self._low
        return np.where(np.isfinite(span), span, np.nan)

    def _errors(self) -> Dict[float, Dict[str, np.ndarray]]:
        """Return horizon -> predictor -> errors (M_h, n) on the common targets."""
        out = {h: {} for h in self.horizons}
        if len(self._states) < 2 or not self._t0:
            return out
        latest = self._states.t[-1]
        t0 = np.fromiter(self._t0, float, len(self._t0))
        pred = np.array(self._pred)                                      # (M, H, n)
        published = np.array(self._published)
        start = self._states.interp(t0)                                  # (M, n)
        have_reference = len(self._reference) >= 2
        for i, h in enumerate(self.horizons):
            target = t0 + h
            select = (target <= latest + 1e-9) & (target >= latest - self.window)
            if not np.any(select):
                continue
            truth = self._states.interp(target[select])
            predicted = pred[select, i]
            follow = (self._reference.interp(target[select]) if have_reference
                      else np.full(truth.shape, np.nan))
            candidates = {'model': predicted, 'hold_last': start[select],
                          'follow_reference': follow}
            common = np.all(np.isfinite(truth), axis=1)
            for name, value in candidates.items():
                if name == 'follow_reference' and not have_reference:
                    continue
                common &= np.all(np.isfinite(value), axis=1)
            errors = {name: value[common] - truth[common]
                      for name, value in candidates.items()
                      if name != 'follow_reference' or have_reference}
            chosen = published[select][common]
            pub = np.empty_like(errors['model'])
            for name in SOURCES:
                rows = chosen == name
                if np.any(rows) and name in errors:
                    pub[rows] = errors[name][rows]
            missing = ~np.isin(chosen, list(errors))
            errors['published'] = pub[~missing]
            out[h] = errors
        return out

    def scores(self) -> Dict[float, Dict[str, float]]:
        """
        Return horizon -> predictor -> windowed range-normalised RMSE, and the counts.

        Predictors are ``model``, ``follow_reference`` (when θd is known), ``hold_last``
        and ``published`` (what was actually published); ``count`` is the number of scored
        predictions at that horizon. Empty for a horizon with nothing scored yet.
        """
        theta_range = self.theta_range
        out = {}
        for h, errors in self._errors().items():
            if not errors:
                out[h] = {}
                continue
            row = {name: range_normalised_rmse(e, theta_range) for name, e in errors.items()}
            row['count'] = int(errors['model'].shape[0])
            out[h] = row
        return out

    def rmse(self, predictor: str = 'published') -> Dict[float, np.ndarray]:
        """Return horizon -> windowed RMSE per joint (rad) of one predictor (NaN if none)."""
        out = {}
        for h, errors in self._errors().items():
            e = errors.get(predictor)
            out[h] = (np.sqrt(np.mean(np.square(e), axis=0)) if e is not None and e.size
                      else np.full(self.n, np.nan))
        return out

    # -- decisions ------------------------------------------------------------------------

    def decide(self) -> Decision:
        """Return what to publish now, with the reason (see the module docstring)."""
        scores = self.scores()
        counts = [scores[h].get('count', 0) for h in self.horizons]
        baselines = [b for b in BASELINES
                     if all(b in scores[h] and math.isfinite(scores[h][b])
                            for h in self.horizons if scores[h])]
        if min(counts) < self.min_scored:
            if any(scores[h] for h in self.horizons) and baselines:
                best = min(baselines, key=lambda b: np.mean(
                    [scores[h][b] for h in self.horizons if scores[h]]))
            else:
                best = 'follow_reference' if len(self._reference) >= 2 else 'hold_last'
            return Decision(best, f'the model has not been scored yet ({min(counts)} of '
                            f'{self.min_scored} predictions at every horizon): publishing '
                            f'{best}', False, scores)
        best = min(baselines, key=lambda b: np.mean([scores[h][b] for h in self.horizons]))
        on_baseline = self._demoted
        limit = 1.0 if on_baseline else 1.0 + self.margin
        worse = [(h, b) for h in self.horizons for b in baselines
                 if scores[h]['model'] > limit * scores[h][b]]
        if not worse:
            self._demoted = False
            why = ('the model is at least as good as both baselines at every horizon again'
                   if on_baseline else 'the model is not worse than the baselines')
            return Decision('model', why, True, scores)
        h, b = max(worse, key=lambda hb: scores[hb[0]]['model']
                   / max(scores[hb[0]][hb[1]], 1e-300))
        self._demoted = True
        return Decision(
            best, f"the model's {h:g} s-ahead error over the last {self.window:g} s is "
            f"{scores[h]['model']:.2%} of the range against {scores[h][b]:.2%} for {b}"
            f'{"" if not on_baseline else " (it must match the baselines to return)"}: '
            f'publishing {best}', True, scores)

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

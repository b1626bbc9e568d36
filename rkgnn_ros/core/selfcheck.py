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
What is fit to publish: the model's prediction or a baseline's, decided on their scores.

:class:`SelfCheck` is a :class:`~rkgnn_ros.core.scoring.PredictionRecord` (the recent
states, commands and predictions, scored per horizon on the same targets: the model, a
candidate model, following the reference and holding the last state) that decides.

:meth:`SelfCheck.decide` says what to publish, the model or the better baseline (marked,
with the reason). Trust is earned, never assumed, and lost at once:

- until the model has ``min_scored`` scored predictions at every horizon it reaches, the
  best-scoring baseline is published (after a change of the dynamics, fewer, and a
  candidate's predictions from the states since the change can be made again and scored
  at once: :meth:`SelfCheck.dynamics_changed`, :meth:`SelfCheck.replay_from`);
- the model is published once, **on every joint**, its error is at least ``margin`` below
  the better baseline's on that joint at every horizon, over the window and over its last
  ``recent`` seconds (a model good on six joints and bad on the seventh is not published:
  an average over the joints would pass it);
- it is set aside as soon as it is worse than the better baseline on any joint at any
  horizon, over either span;
- the noise floor: on a joint where both the model's and the better baseline's errors are
  within :meth:`SelfCheck.noise_floor` (``FLOOR_FACTOR`` × the encoder noise the joint's
  measured θ shows, :mod:`rkgnn_ros.core.noise`), neither can be better, and that joint
  does not hold the model back (a joint that stays still under noisy encoders).

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

from dataclasses import dataclass, field
import math
from typing import Dict, NamedTuple, Optional, Sequence, Tuple

import numpy as np

from .band import band_width, Excursion, leaves_band
from .noise import encoder_noise
from .scoring import (ahead_errors, at_horizons, BASELINES, finite_rows, HORIZONS,
                      PredictionRecord, range_normalised_rmse, rollout_spread, SOURCES)

__all__ = ['HORIZONS', 'SOURCES', 'BASELINES', 'FLOOR_FACTOR', 'MIN_NOISE_RAD', 'QUICK_MIN',
           'QUICK_SHARE', 'Decision',
           'Verdict', 'SelfCheck', 'baseline', 'ahead_errors', 'range_normalised_rmse',
           'rollout_spread']

#: A joint's error within this many times the encoder noise its stream shows is noise.
FLOOR_FACTOR = 2.0
#: The least encoder noise assumed (rad): below any encoder's resolution (2^20 counts per
#: turn is 6e-6 rad), so exact data and rounding do not make a floor of zero.
MIN_NOISE_RAD = 1e-6
QUICK_SHARE = 0.5   # of min_scored, after a change of the dynamics (SelfCheck.dynamics_changed)
QUICK_MIN = 3       # scored predictions at every horizon, at least, then


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


class Verdict(NamedTuple):
    """A candidate model's trial against the model in use, on the same targets."""

    better: bool        # it earned the swap (:meth:`SelfCheck.trial`)
    candidate: float    # its windowed error, mean over the scored horizons and the joints
    model: float        # the model's on the same targets (NaN: there was none)
    why: str = ''       # why it did not earn the swap


class CheckLimits(NamedTuple):
    """What :class:`SelfCheck` judges on beyond its horizons and margin (see there)."""

    min_scored: int = 10
    recent: float = 2.0
    max_gap: float = 0.25
    rescore_every: float = 0.0
    joint_names: Optional[Sequence[str]] = None


class SelfCheck(PredictionRecord):
    """
    Continuous scoring of predictions against the baselines, and the publish decision.

    A :class:`~rkgnn_ros.core.scoring.PredictionRecord` (feed it states, commands and
    predictions) that also says what to publish (:meth:`decide`) and how uncertain that is
    (:meth:`uncertainty`).

    A second model, the *candidate*, can be scored beside the model in use on the same
    starts (:meth:`add_prediction`'s ``candidate``): :meth:`trial` compares the two once the
    candidate has ``min_scored`` scored predictions at every horizon it reaches, and
    :meth:`promote` makes it the model (its scores come with it) or
    :meth:`discard_candidate` forgets it. So a new model is judged on what it predicted
    before anything it predicts is published.

    Parameters
    ----------
    n_joints, horizons, window, max_gap, rescore_every
        As :class:`~rkgnn_ros.core.scoring.PredictionRecord`.
    margin : float
        How much better than each baseline (a share of its error) the model must be to be
        published; it is set aside when worse (see the module docstring).
    min_scored : int
        Scored predictions needed at every horizon a predictor reaches before it is judged
        (and in the last ``recent`` seconds, for that span to count).
    recent : float
        The short span (s) of the newest targets, judged beside the window.
    joint_names : sequence of str, optional
        The joints' names, for the reasons given (default 'joint 1', 'joint 2', ...).

    """

    def __init__(self, n_joints: int, horizons: Sequence[float] = HORIZONS, window: float = 10.0,
                 margin: float = 0.2, **options):
        min_scored, recent, max_gap, rescore_every, joint_names = CheckLimits(**options)
        super().__init__(n_joints, horizons, window, max_gap, rescore_every)
        if not (math.isfinite(margin) and 0.0 <= margin < 1.0):
            raise ValueError(f'margin must be in [0, 1), got {margin}')
        if not (math.isfinite(recent) and 0.0 < recent <= window):
            raise ValueError(f'recent must be in (0, window], got {recent}')
        names = tuple(f'joint {j + 1}' for j in range(self.n)) if joint_names is None \
            else tuple(str(name) for name in joint_names)
        if len(names) != self.n:
            raise ValueError(f'{len(names)} joint names for {self.n} joints')
        self.joint_names = names
        self.margin = float(margin)
        self.min_scored = max(1, int(min_scored))
        self.recent = float(recent)
        # after a change of the dynamics: '' (none), 'stale' (the model in use is the one
        # before it), 'new' (one after it is in use, not scored in full yet)
        self._quick = ''
        self._on_model = False     # the model is published (it earned it and kept it)
        self._withdrawn = (-math.inf, '')  # (held until this state time, why)
        self._changed_at = -math.inf       # the time of the newest change (s)

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
        reached = self._reached('model')
        counts = [scores[h].get('count', 0) for h in reached]
        self._end_quick()
        needed = self._needed()
        if not reached or min(counts) < needed:
            # the baselines' first scores are few and from the start of the motion, when
            # an arm at rest is briefly better held than following its plan: follow it
            best = 'follow_reference' if 'follow_reference' in allowed else 'hold_last'
            have = min(counts) if counts else 0
            return Decision(best, f'the model has not been scored yet ({have} of '
                            f'{needed} predictions at every horizon it reaches): '
                            f'publishing {best}', False, scores)
        best = _best_baseline(scores, allowed, reached)
        if self.withdrawn():
            self._on_model = False
            return Decision(best, f'the model was withdrawn: {self._withdrawn[1]}; it is judged '
                            'again once its predictions since are scored: publishing '
                            f'{best}', True, scores)
        was_on_model = self._on_model
        limit = 1.0 if was_on_model else 1.0 - self.margin
        worse = self._worse_joints(reached, scored, limit)
        if not worse:
            self._on_model = True
            why = ('the model is not worse than the baselines on any joint' if was_on_model
                   else f'the model is at least {self.margin:.0%} better than the baselines '
                   'on every joint at every horizon')
            return Decision('model', why, True, scores)
        self._on_model = False
        _, h, j, b, mine, theirs, span = max(worse)
        return Decision(
            best, f"on {self.joint_names[j]}, the model's {h:g} s-ahead error over the {span} "
            f'is {mine:.2%} of the range against {theirs:.2%} for {b}'
            + ('' if was_on_model else f' (it must be {self.margin:.0%} better)')
            + f': publishing {best}', True, scores)

    def excursion(self, offsets, theta, theta0, theta_d,
                  predictors: Sequence[str] = ('model',)) -> Optional[Excursion]:
        """
        Return where a prediction leaves the band the plan and the recent errors allow.

        ``theta`` (K, n) at ``offsets`` (K,) from the state θ0 (n,), ``theta_d`` (K, n)
        the plan there; the band (rad) is :mod:`rkgnn_ros.core.band`'s, with the recent
        RMSE of the first of ``predictors`` ('model' or 'candidate') that has
        ``min_scored`` scored predictions at every horizon it reaches (as the model needs
        to be published: a few scores at the shortest horizon say little of the longest).
        None: inside, or nothing scored enough to judge it by. Judged on the scores as they
        are (the prediction waits for it: they are not computed again here).
        """
        offsets = np.asarray(offsets, dtype=float).reshape(-1)
        grid = (offsets.size, float(offsets[0]), float(offsets[-1]))
        held, self.hold = self.hold, True
        try:
            for name in predictors:
                width = self._memo(('band', name) + grid, lambda: band_width(
                    offsets, self.horizons, self.rmse('follow_reference'), self.rmse(name),
                    self._noise_rad()) if self._scored_enough(name) else None)
                if width is not None:
                    return leaves_band(offsets, theta, theta0, theta_d, width)
            return None
        finally:
            self.hold = held

    def _scored_enough(self, kind: str) -> bool:
        """Return whether ``kind`` has ``min_scored`` scored predictions at every horizon."""
        count = 'count' if kind == 'model' else f'{kind}_count'
        reached = self._reached(kind)
        table = self.joint_scores()
        return bool(reached) and all(table[h].get(count, 0) >= self.min_scored
                                     for h in reached)

    def withdraw(self, now: float, why: str) -> bool:
        """
        Set the model aside on its own rollout's evidence, before any score of it comes.

        It is not published until the newest state is ``now`` + the longest horizon +
        ``recent`` (s): its predictions made since are scored by then, the short span's
        only; a withdrawal while withdrawn extends it. Return whether it is a new one.
        """
        new = not self.withdrawn()
        self._on_model = False
        self._withdrawn = (float(now) + self.horizons[-1] + self.recent, str(why))
        return new

    def withdrawn(self) -> bool:
        """Return whether the model is held back at the newest state by a withdrawal."""
        latest = self._states.t[-1] if len(self._states) else -math.inf
        return latest < self._withdrawn[0]

    def noise(self) -> np.ndarray:
        """
        Return the std of the measurement noise on each joint's θ in rad, (n,), NaN if unknown.

        :func:`~rkgnn_ros.core.noise.encoder_noise` over the newest recorded states, their
        gaps longer than ``max_gap`` left out; computed again with the scores.
        """
        return self._memo(('noise',), lambda: encoder_noise(
            self._states.t, self._states.rows, self.max_gap) if len(self._states) >= 2
            else np.full(self.n, np.nan))

    def _noise_rad(self) -> np.ndarray:
        noise = self.noise()
        return np.where(np.isfinite(noise), np.maximum(noise, MIN_NOISE_RAD), MIN_NOISE_RAD)

    def noise_floor(self) -> np.ndarray:
        """
        Return the score (RMSE / θ range) below which a joint's error is noise, (n,).

        ``FLOOR_FACTOR`` × the encoder noise the joint's measured θ shows
        (:meth:`~rkgnn_ros.core.scoring.PredictionRecord.noise`, at least
        ``MIN_NOISE_RAD``), over the joint's θ range: a prediction is scored against a
        noisy measurement, so two predictors within that are not told apart.
        """
        noise = self._noise_rad()
        self._table()
        return FLOOR_FACTOR * noise / np.maximum(self._range_at, 1e-12)

    def _worse_joints(self, reached, scored, limit: float):
        """
        Return where the model fails the bar (empty: it passes; see the module docstring).

        One tuple per failing joint, horizon and span (the window, the short span): the
        ratio of the model's error to the better baseline's, the horizon, the joint's
        index, that baseline, the two errors and the span's name.
        """
        floor = self.noise_floor()
        out = []
        for span, table in ((f'last {self.window:g} s', self.joint_scores()),
                            (f'last {self.recent:g} s', self._recent_scores(reached))):
            for h in reached:
                row = table.get(h) or {}
                mine = row.get('model')
                bases = [b for b in scored if b in row]
                if mine is None or not bases or not np.any(np.isfinite(mine)):
                    continue
                stack = np.vstack([row[b] for b in bases])                      # (B, n)
                pick = np.argmin(np.where(np.isnan(stack), np.inf, stack), axis=0)
                theirs = stack[pick, np.arange(self.n)]            # the better baseline
                ok = (mine <= limit * theirs) | ((mine <= floor) & (theirs <= floor))
                for j in np.flatnonzero(~ok):
                    out.append((mine[j] / max(theirs[j], 1e-300), h, int(j), bases[pick[j]],
                                float(mine[j]), float(theirs[j]), span))
        return out

    def _recent_scores(self, horizons) -> Dict[float, Dict[str, float]]:
        """Return the model's and the baselines' errors per joint (n,) on the last ``recent`` s."""
        return self._memo(('recent', tuple(horizons)), lambda: self._recent(horizons))

    def _recent(self, horizons) -> Dict[float, Dict[str, float]]:
        out = {}
        if not len(self._states):
            return out
        since = self._states.t[-1] - self.recent
        for h in horizons:
            errors = self._table()[h]
            if errors is None:
                continue
            rows = finite_rows(errors['model']) & (errors['target'] >= since - 1e-9)
            if rows.sum() < self.min_scored:
                continue
            out[h] = {'model': self._per_joint(errors['model'], rows)}
            for name in BASELINES:
                both = rows & finite_rows(errors[name])
                if np.any(both):
                    out[h][name] = self._per_joint(errors[name], both)
        return out

    def trial(self) -> Optional[Verdict]:
        """
        Return the candidate's verdict, or None while it has too few scored predictions.

        The candidate is judged once it has ``min_scored`` scored predictions at every
        horizon it reaches, on the same targets as the model in use, with the errors
        averaged over those horizons. It earns the swap when its error, averaged over the
        joints too, is at most the model's, and on no joint it is more than ``margin``
        worse than the model's (unless both are within the noise floor there); always when
        the model made no prediction there.
        """
        return self._memo(('trial',), self._trial)

    def _trial(self) -> Optional[Verdict]:
        reached = self._reached('candidate')
        if not reached:
            return None
        table = self._table()
        mine, theirs = [], []
        for h in reached:
            errors = table[h]
            if errors is None:
                return None
            has = finite_rows(errors['candidate'])
            if has.sum() < self._needed():
                return None
            common = has & finite_rows(errors['model'])
            mine.append(self._per_joint(errors['candidate'], common if np.any(common) else has))
            theirs.append(self._per_joint(errors['model'], common))
        mine, theirs = np.mean(mine, axis=0), np.mean(theirs, axis=0)            # (n,)
        candidate, model = float(np.mean(mine)), float(np.mean(theirs))
        if not math.isfinite(model):
            return Verdict(True, candidate, math.nan)
        if candidate > model:
            return Verdict(False, candidate, model, f'{candidate:.2%} of the range on the '
                           f'scored horizons against {model:.2%} for the model in use')
        floor = self.noise_floor()
        worse = (mine > (1.0 + self.margin) * theirs) & ~((mine <= floor) & (theirs <= floor))
        if np.any(worse):
            j = int(np.argmax(np.where(worse, mine / np.maximum(theirs, 1e-300), -np.inf)))
            return Verdict(False, candidate, model, f'on {self.joint_names[j]}, {mine[j]:.2%} '
                           f'of the range on the scored horizons against {theirs[j]:.2%} for '
                           f'the model in use (over the joints {candidate:.2%} against '
                           f'{model:.2%})')
        return Verdict(True, candidate, model)

    def dynamics_changed(self, since: Optional[float] = None) -> None:
        """
        Say that the arm's dynamics changed at ``since`` (s; None: the newest state's time).

        The model in use no longer holds: it is withdrawn at once (:meth:`withdraw`: a
        baseline is published until a model after the change earns its place). Until a
        model after it is in use with ``min_scored`` scored predictions at every horizon,
        a candidate's trial and the model's publication need :data:`QUICK_SHARE` of them
        (at least :data:`QUICK_MIN`): a change detector's evidence already judged the
        model in use, and each scored prediction 2 s ahead costs a prediction period of
        the time the arm is predicted by a model of the arm before the change. Meanwhile
        :meth:`replay_from` says from when a candidate's predictions can be made again.
        """
        self._quick = 'stale'
        latest = self._states.t[-1] if len(self._states) else -math.inf
        self._changed_at = latest if since is None or not math.isfinite(since) \
            else min(float(since), latest)
        self.withdraw(latest, 'the dynamics changed: it is the arm before the change')
        self._cache = None

    def replay_from(self) -> Optional[float]:
        """
        Return from when (s) a new candidate's predictions are made again, or None.

        After a change of the dynamics (:meth:`dynamics_changed`), until a model after it
        holds with ``min_scored`` scored predictions at every horizon and for ``window``
        seconds of states after it: the change's time. A candidate then is fitted on the
        arm since the change (refits come every second or so), and each prediction it
        made from a state since then (:meth:`set_candidate`) is scored as soon as its
        target is measured, instead of 2 s after its trial starts. Its fit saw those
        targets, so these scores are in-sample; they are the price of seconds while a
        baseline is published, and the model is judged on its new predictions as always
        once in use.
        """
        self._end_quick()
        latest = self._states.t[-1] if len(self._states) else -math.inf
        recent = latest - self._changed_at <= self.window
        return self._changed_at if self._quick or recent else None

    def _end_quick(self) -> None:
        """End the quick judging after a change once a model after it is scored in full."""
        if self._quick == 'new' and self._scored_enough('model'):
            self._quick = ''

    def _needed(self) -> int:
        """Return the scored predictions a trial or the model's publication needs now."""
        if not self._quick:
            return self.min_scored
        return min(self.min_scored, max(QUICK_MIN, int(math.ceil(QUICK_SHARE * self.min_scored))))

    def promote(self) -> None:
        """Make the candidate the model: its recorded predictions replace the model's."""
        blocks = self._blocks()
        blocks['model'][:] = blocks['candidate']
        blocks['candidate'][:] = np.nan
        self._withdrawn = (-math.inf, '')
        self._quick = 'new' if self._quick else ''
        self._cache = None

    def set_candidate(self, t0: float, offsets, theta) -> bool:
        """
        Record a candidate's prediction θ (K, n) at ``offsets`` (K,) from a start already made.

        For a prediction :meth:`add_prediction` recorded from ``t0`` (the same float): the
        candidate's block of that row is replaced. Return whether there was such a row.
        """
        offsets = np.asarray(offsets, dtype=float).reshape(-1)
        t = self._predictions.t
        i = int(np.searchsorted(t, t0, side='right')) - 1
        if offsets.size < 2 or i < 0 or t[i] != t0:
            return False
        at, reason = at_horizons(self.horizons, self.n, offsets, theta)
        if reason:
            self.rejected[reason] += 1
            return False
        self._blocks()['candidate'][i] = at
        self._stale = True
        self._cache = None
        return True

    def discard_candidate(self) -> None:
        """Forget the candidate's predictions."""
        self._blocks()['candidate'][:] = np.nan
        self._cache = None

    def forget_model(self) -> None:
        """Forget the model's predictions (a model that replaced it untried)."""
        self._blocks()['model'][:] = np.nan
        self._on_model = False
        self._withdrawn = (-math.inf, '')
        self._quick = 'new' if self._quick else ''
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


def _best_baseline(scores, allowed, horizons) -> str:
    """
    Return the publishable baseline with the smaller mean score over ``horizons``.

    Following the reference, when publishable and not scored yet (no command recorded),
    is preferred to holding the last state: an arm under a servo follows its plan.
    """
    if 'follow_reference' not in allowed:
        return 'hold_last'
    if not any('follow_reference' in scores[h] for h in horizons):
        return 'follow_reference'
    return min(allowed, key=lambda b: _mean_score(scores, b, horizons))


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

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
Online identification on a robot description: the rigid body refitted at each refresh.

With the kinematics known, the arm of every case is one consistent least squares of a
second or less (:mod:`.rigid_fit`), global, and needs no search. :class:`RigidKeeper` fits
it on the buffered window at each data refresh (the newest ``validation_fraction`` held
out to score it) and closes it with the servo's law for prediction:

- case 'torque': the law learned from torque and commands on the arm's own gravity
  regressor (:func:`.case_one.judge_law` with :class:`~.rigid_law.GravityFeatures`), the
  arm fitted on the torque. Until the newest half of the data gives the same gains, the
  newest fit is used provisionally (refitted at every refresh: the prediction's trial, not
  the gains, decides whether it is published); once confirmed, a law is replaced only by
  another confirmed one;
- case 'pd_gains': the closed loop with the known gains;
- case 'unknown': the closed loop with the servo's gains fitted too (scale from the
  description's masses).

A fit whose held-out error (worst joint) is above :data:`~.policy.RIGID_MAX_ERROR` is not
offered for prediction (the model is still published, with its error). The closed-loop form (a
gravity compensation, an integral) is chosen by held-out error again every
:data:`~.policy.FORMS_EVERY_S`, and whenever the data have grown by
:data:`~.policy.FORMS_DATA_GROWTH` since; in between only the chosen form is refitted.

Changes of the dynamics (:mod:`.change`) are judged with the fit whose held-out residual
gave the detector its normal level (:attr:`RigidKeeper.armed`), never a residual of one fit
against the level of another: a refit arms the detector when its held-out error is at most
:data:`~.policy.CHANGE_LEVEL_GROWTH` times the armed fit's on every joint. A refit that fits
worse (a closed loop whose integral gain the window determines poorly) leaves the better fit
judging, and a refit whose held-out data hold the first samples of a change cannot raise
the level that is to show it.
"""

import dataclasses
import math
from typing import List, NamedTuple, Optional, Sequence, Tuple

import numpy as np

from .case_one import judge_law
from .change import Change, ChangeDetector
from .online_records import (ClosedLoop, DynamicsChange, GenerationStats, LogLine,
                             model_update, PayloadEstimate)
from .online_rules import stale_stream
from .policy import (CHANGE_LEVEL_GROWTH, CHANGE_MARGIN_SIGMAS, CHECK_EVERY_S, CHECK_MAX_S,
                     CHECK_S, DETECT_MIN_S, FILTER_REACH_SIGMAS, FORMS_DATA_GROWTH,
                     FORMS_EVERY_S, FULL_REFIT_S,
                     MAX_LAW_FIT_RATIO, MIN_SEGMENT_SAMPLES, PAYLOAD_MIN_S, RIGID_MAX_ERROR,
                     RIGID_MIN_DATA_S, RIGID_REFRESH_S)
from .rigid_change import fit_last_body, newest_residual, payload_of, since
from .rigid_fit import fit_closed, fit_closed_forms, fit_torque, RigidFit
from .rigid_law import GravityFeatures
from .rigid_loop import RigidLoop
from .rigid_model import RigidModel
from .validation import split_validation
from ..data import Dataset
from ..rigid.structure import RigidStructure

__all__ = ['RigidKeeper', 'RigidPolicy', 'RigidUpdate', 'fit_rigid', 'refresh_events']


class RigidUpdate(NamedTuple):
    """What one refresh gave: the model to publish, its closed loop (None: none), log lines."""

    model: RigidModel
    loop: Optional[ClosedLoop]
    lines: List[Tuple[str, str]]
    #: the payload the first seconds after a change show (:func:`.rigid_change.payload_of`)
    payload: Optional[dict] = None


def _integral_to_end(law, segments: Sequence[Dataset]):
    """Return ``law`` with its integral term at the end of the newest segment."""
    if not np.any(law.ki != 0.0) or not segments:
        return law
    seg = segments[-1]
    e = seg.theta_d - seg.theta
    grown = np.sum(0.5 * (e[1:] + e[:-1]), axis=0) * seg.dt
    return dataclasses.replace(law, integral_term=law.ki * grown)


class RigidKeeper:
    """
    The rigid-body model of one robot description over the refreshes (module docstring).

    Parameters
    ----------
    structure : RigidStructure
        The arm's kinematics and the joints' order.

    """

    def __init__(self, structure: RigidStructure, case: str = ''):
        self.structure = structure
        self.case = case
        self.features = GravityFeatures(structure)
        self.law = None              # case 'torque': the law in use
        self._provisional = False    # the law in use is not confirmed by the data yet
        self.fit: Optional[RigidFit] = None
        self.form: Optional[Tuple[bool, Optional[str]]] = None   # (integral, gravity)
        self._form_time = -math.inf
        self._form_span = math.inf   # s of data the form was chosen on
        self.refits = 0
        self._predicting = False
        self.detector = ChangeDetector()
        self.armed: Optional[RigidFit] = None   # the fit the detector's level is from
        self.since = -math.inf       # stamp (s) from which on the data are the arm's now
        self.change: Optional[Change] = None   # the newest change (its stamp time)
        self.before = None           # the arm in use when it came
        self.payload: Optional[dict] = None

    def check(self, segments: Sequence[Dataset], origin: float) -> Optional[Change]:
        """
        Judge the samples of ``segments`` not judged yet with the model in use.

        At least the newest :data:`CHECK_S` (the filter's edge needs what came before), at
        most the newest :data:`CHECK_MAX_S`; a detector's first check, the newest
        :data:`CHECK_S` only (what came before is what the model was fitted on).

        A change (:mod:`.change`, its time in stamp seconds) is kept: the data before it are
        no longer fitted, the last body is re-identified first (:meth:`refresh`).
        """
        fit = self.armed
        if fit is None or self.detector.level is None or not segments:
            return None
        end = origin + float(segments[-1].t[-1])
        judged = self.detector.last_time if self.detector.last_time > -math.inf else end
        newest = since(segments, origin, max(self.since, end - CHECK_MAX_S,
                                             min(end, judged) - CHECK_S))
        law = None if self.case == 'torque' else fit.law
        found = newest_residual(fit.arm, law, newest, fit.arm.info.get('sigma') or 0.02)
        if found is None:
            return None
        residual, times = found
        change = self.detector.check(residual, origin + times)
        if change is None:
            return None
        sigma = fit.arm.info.get('sigma') or 0.02
        self.change, self.before, self.payload = change, fit.arm, None
        self._latest = fit.arm
        self.since = change.time + CHANGE_MARGIN_SIGMAS * sigma
        self.detector = ChangeDetector()       # re-armed by the first full refit after it
        self.armed = None
        return change

    def refresh(self, case: str, segments: Sequence[Dataset], validation_fraction: float,
                origin: float, now: float, kp=None, kd=None) -> Optional[RigidUpdate]:
        """
        Fit on ``segments`` (oldest first; ``origin``: the stamp time of their t = 0).

        ``kp``, ``kd``: the known gains of case 'pd_gains'. Returns None when there are
        too few data or the fit fails.
        """
        everything = segments
        segments = [seg for seg in since(segments, origin, self.since)
                    if seg.n_samples >= MIN_SEGMENT_SAMPLES]
        span = sum(seg.duration for seg in segments)
        if self.change is not None and span < FULL_REFIT_S:
            return self._after_change(case, everything, origin, span)
        if span < RIGID_MIN_DATA_S:
            return None
        train, validation, _ = split_validation(segments, validation_fraction,
                                                MIN_SEGMENT_SAMPLES)
        lines: List[Tuple[str, str]] = []
        prior = None if self.change is None else self._latest.parameters
        if case == 'torque':
            fit, law = self._torque(segments, train, validation, lines, prior)
        else:
            fit = self._closed(case, train, validation, now, kp, kd, prior, span)
            law = None if fit is None else _integral_to_end(fit.law, segments)
        if fit is None:
            return None
        if self.change is not None:
            lines.append(('info', f'the whole model refitted on the {span:.1f} s since the '
                                  'change'))
            self.change = None
        self.fit = fit
        info = fit.arm.info
        if 'residual_rms' in info and span >= DETECT_MIN_S and _arms(fit, self.armed):
            self.detector.set_normal(info['residual_rms'], info['torque_spread'])
            self.armed = fit
        self.refits += 1
        error = fit.error
        info = {'refits': self.refits, 'generation': self.refits, 'held_out_error': error,
                'held_out_errors': fit.errors.tolist(),
                'window_s': float(sum(seg.duration for seg in segments))}
        learned = getattr(self.structure, 'report', None)
        if learned is not None:      # no description: the chain learned from the data
            info['learned_chain'] = learned
        model = RigidModel(fit.arm, law, case, segments[-1].dt, info)
        loop = None
        if law is not None and error <= RIGID_MAX_ERROR:
            rigid = RigidLoop(fit.arm, law)
            rigid.torque_error = error
            loop = ClosedLoop(model, rigid, origin + float(segments[-1].t[-1]))
        if (loop is not None) != self._predicting:
            self._predicting = loop is not None
            what = 'torque error' if case == 'torque' else 'closed-loop equation error'
            of = 'the learned chain' if learned is not None else 'the robot description'
            lines.append(('info', f'the rigid-body model of {of} predicts '
                                  f'(held-out {what} {error:.2%}, {law.describe()})')
                         if loop is not None else
                         ('warning', f'the rigid-body model does not predict: held-out '
                                     f'{what} {error:.2%} (bar {RIGID_MAX_ERROR:.0%})'
                                     if law is not None else
                                     'the rigid-body model does not predict: the servo law '
                                     'is not determined by the data yet'))
        return RigidUpdate(model, loop, lines)

    def _after_change(self, case, segments, origin, span) -> Optional[RigidUpdate]:
        """Refit only the last body in the first seconds after a change (module docstring)."""
        if span < PAYLOAD_MIN_S or self.before is None:
            return None
        law = self.law if case == 'torque' else self.fit.law
        sigma = self.before.info.get('sigma') or 0.02
        # the filter's support reaches back before the data since the change (rows after)
        reach = self.since - FILTER_REACH_SIGMAS * sigma
        support = [seg for seg in since(segments, origin, reach)
                   if seg.n_samples >= MIN_SEGMENT_SAMPLES]
        arm = fit_last_body(self.before, None if case == 'torque' else law, support, sigma,
                            self.since - origin)
        segments = [seg for seg in since(segments, origin, self.since)
                    if seg.n_samples >= MIN_SEGMENT_SAMPLES]
        if arm is None:
            return None
        self.payload = dict(payload_of(self.before, arm), time=self.change.time,
                            seconds=span)
        self.refits += 1
        self._latest = arm
        model = RigidModel(arm, law, case, segments[-1].dt,
                           {'refits': self.refits, 'generation': self.refits,
                            'held_out_error': math.nan, 'window_s': span,
                            'payload': self.payload,
                            'phase': 'last body refitted after a change'})
        loop = None
        if law is not None:
            if case == 'torque':
                law = _integral_to_end(law, segments)
            loop = ClosedLoop(model, RigidLoop(arm, law), origin + float(segments[-1].t[-1]))
        p = self.payload
        com = np.round(p['com'], 4).tolist()
        line = ('info', f'payload after the change at {self.change.time:.3f} s: '
                        f"{p['mass']:.3f} kg at {com} m in the frame of {p['frame']} "
                        f'({span:.1f} s of data)')
        return RigidUpdate(model, loop, [line], self.payload)

    def _torque(self, segments, train, validation, lines, prior=None):
        fit = fit_torque(self.structure, train, validation, prior=prior)
        if fit is None:              # nothing is published: the law waits for the next refit
            return None, self.law
        paired = [seg for seg in segments if seg.tau is not None and seg.theta_d is not None]
        law, determined = judge_law(paired, features=self.features) if paired else (None, False)
        usable = law is not None and law.usable(MAX_LAW_FIT_RATIO)
        if usable and (determined or self.law is None or self._provisional):
            if determined and (self.law is None or self._provisional
                               or not law.close_to(self.law)):
                lines.append(('info', f'servo law learned on the gravity regressor: '
                                      f'{law.describe()}, Kp {np.round(law.kp, 2).tolist()}, '
                                      f'Kd {np.round(law.kd, 2).tolist()}'))
            elif not determined and self.law is None:
                lines.append(('info', f'servo law fitted on the gravity regressor, not yet '
                                      f'confirmed by the newest half of the data: '
                                      f'{law.describe()}, Kp {np.round(law.kp, 2).tolist()}; '
                                      'its predictions are judged before any is published'))
            self._provisional = not determined
            self.law = _integral_to_end(law, paired)
        elif self.law is not None:
            self.law = _integral_to_end(self.law, paired) if paired else self.law
        return fit, self.law

    def _closed(self, case, train, validation, now, kp, kd, prior=None,
                span=math.inf) -> Optional[RigidFit]:
        if case == 'pd_gains':
            kp, kd = np.asarray(kp, dtype=float), np.asarray(kd, dtype=float)
        else:
            kp = kd = None
        if (self.form is None or now - self._form_time >= FORMS_EVERY_S
                or span >= FORMS_DATA_GROWTH * self._form_span):
            fit = fit_closed_forms(self.structure, train, validation, kp, kd, self.features,
                                   prior=prior)
            if fit is not None:
                self._form_time, self._form_span = now, span
                law = fit.law
                self.form = (bool(np.any(law.ki != 0.0)),
                             law.theta_input if law.theta_weights.size else None)
            return fit
        integral, gravity = self.form
        return fit_closed(self.structure, train, validation, kp, kd, integral, gravity,
                          features=self.features, prior=prior)


def _arms(fit: RigidFit, armed: Optional[RigidFit]) -> bool:
    """Return whether ``fit`` arms the detector instead of ``armed`` (module docstring)."""
    if armed is None:
        return True
    new, old = np.asarray(fit.errors, dtype=float), np.asarray(armed.errors, dtype=float)
    if new.shape != old.shape or not np.all(np.isfinite(new)):
        return new.shape != old.shape
    return bool(np.all(new <= CHANGE_LEVEL_GROWTH * np.where(np.isfinite(old), old, np.inf)))


def refresh_events(keeper: RigidKeeper, settings, capture, now: float, publish: bool):
    """
    Return ``(events, update)`` of one refresh of ``keeper`` on a buffer ``capture``.

    ``settings`` (:class:`~.online_records.OnlineSettings`) give the case, the gains and
    the held-out share; ``publish``: the model may go out on ``~/model`` now (else only its
    statistics and log lines are events). ``update`` is None when nothing was fitted.
    """
    case = settings.case
    segments = capture.segments(MIN_SEGMENT_SAMPLES, True)
    if case == 'torque' and not any(seg.theta_d is not None for seg in segments):
        segments = capture.segments(MIN_SEGMENT_SAMPLES, False)   # no commands: the arm only
    update = keeper.refresh(case, segments, settings.validation_fraction, capture.time_origin,
                            now, settings.kp, settings.kd)
    if update is None:
        return [], None
    events: List[object] = [LogLine(level, text) for level, text in update.lines]
    error = float(update.model.info['held_out_error'])
    events.append(GenerationStats(keeper.refits, error, error, 0.0, keeper.refits, error, 0.0))
    if publish:
        gains = update.model.implied_gains()
        events.append(model_update(update.model, update.loop, gains))
    return events, update


class RigidPolicy:
    """
    The online policy's part for an arm with a robot description (module docstring).

    :class:`~.online.OnlineIdentification` hands it every step whose observation carries a
    structure: it refits at most every :data:`RIGID_REFRESH_S` and publishes the model at most
    every ``model_publish_period`` (after a change of the dynamics, each refit of the last
    body at once, its refit tried at every check until the data since the change suffice;
    the first fit too is
    tried at every check until the data suffice); a reset, another
    structure or another case starts it afresh. ``emit`` takes events,
    ``set_status(state, detail, **numbers)`` the status, ``staleness`` is the policy's
    :class:`~.online_rules.Staleness`.
    """

    def __init__(self, clock, emit, set_status, staleness):
        self._clock, self._emit, self._set_status = clock, emit, set_status
        self._staleness = staleness
        self.keeper: Optional[RigidKeeper] = None
        self.model: Optional[RigidModel] = None
        self._last_refresh = -math.inf
        self._last_publish = -math.inf
        self._last_check = -math.inf
        #: stamp time (s) of the newest change of the dynamics seen before this policy took
        #: over (the search's, for a learned chain): a new keeper fits only the data after it
        self.since = -math.inf

    def data_due(self, obs, now: float) -> bool:
        """Return whether the next :meth:`step` refits or checks (it then wants a capture)."""
        return stale_stream(obs, now) is None and (
            now - self._last_refresh >= RIGID_REFRESH_S or now - self._last_check >= CHECK_EVERY_S)

    def step(self, obs) -> bool:
        """Refit if due; return False (no generation of a search ran)."""
        keeper, settings = self.keeper, obs.settings
        if (obs.reset or keeper is None or keeper.structure is not obs.structure
                or keeper.case != settings.case):
            self._emit(LogLine('info', f'identifying the rigid body of '
                                       f'{obs.structure.describe()}, case {settings.case}'))
            self.keeper = keeper = RigidKeeper(obs.structure, settings.case)
            keeper.since = self.since
            self._last_refresh = -math.inf
        now = self._clock()
        if obs.paused or obs.joints is None:
            self._set_status('paused' if obs.paused else 'waiting for data',
                             'paused' if obs.paused else 'no joint_states yet')
            return False
        if (not self._staleness.fresh(obs, now, lambda level, text: self._emit(
                LogLine(level, text)), self._set_status) or obs.data is None):
            return False
        refresh = now - self._last_refresh >= RIGID_REFRESH_S
        if refresh or now - self._last_check >= CHECK_EVERY_S:
            self._last_check = now       # before a refit, always: it must not absorb a change
            refresh = self._check(keeper, obs) or refresh   # a change: its refit at once
        if keeper.detector.suspect is not None:
            return False     # a refit now would take in the samples the next check confirms
        if not refresh:
            return False
        self._last_refresh = now
        # after a change, each refit of the last body goes out: the predictor judges it on
        # the motion since the change before it predicts
        publish = (now - self._last_publish >= settings.model_publish_period
                   or keeper.change is not None)
        events, update = refresh_events(keeper, settings, obs.data, now, publish)
        for event in events:
            self._emit(event)
        if update is None:
            if keeper.change is not None or keeper.fit is None:   # again at the next check
                self._last_refresh = now - RIGID_REFRESH_S + CHECK_EVERY_S
            self._set_status('waiting for data', 'too few data for the rigid-body fit yet')
            return False
        if publish:
            self.model, self._last_publish = update.model, now
        if update.payload is not None:
            self._emit(PayloadEstimate(**{k: update.payload[k] for k in PayloadEstimate._fields}))
        error = float(update.model.info['held_out_error'])
        self._set_status('identifying', f'rigid-body fit {keeper.refits}, held-out error '
                                        f'{error:.3g}', generation=keeper.refits,
                         best_cost=error)
        return False

    def _check(self, keeper: RigidKeeper, obs) -> bool:
        """Judge the newest data with the model in use; say a change; return whether one."""
        capture = obs.data
        change = keeper.check(capture.segments(MIN_SEGMENT_SAMPLES, keeper.case != 'torque'),
                              capture.time_origin)
        if change is None:
            return False
        self._last_publish = -math.inf       # the first model after it goes out at once
        names = tuple(keeper.structure.joint_names[j] for j in change.joints)
        statistic = tuple(float(v) for v in change.statistic)
        self._emit(DynamicsChange(change.time, names, statistic))
        self._emit(LogLine('warning', f'the dynamics changed at {change.time:.3f} s (joints '
                                      f'{list(names)}: residual {max(statistic):.3g} times its '
                                      'normal square): the data before it are dropped, the '
                                      'last body is refitted first'))
        return True


def fit_rigid(datasets, case: str, structure: RigidStructure, kp=None, kd=None,
              validation_fraction: float = 0.2) -> RigidModel:
    """
    Return the rigid body of ``structure`` fitted on ``datasets`` once (offline).

    What one refresh of :class:`RigidKeeper` does on them (module docstring); raises
    ValueError with too few data or a fit that fails.
    """
    datasets = [datasets] if isinstance(datasets, Dataset) else list(datasets)
    update = RigidKeeper(structure, case).refresh(case, datasets, validation_fraction, 0.0,
                                                  0.0, kp, kd)
    if update is None:
        raise ValueError(f'the rigid body could not be fitted in case {case!r}: too few '
                         f'data ({sum(seg.duration for seg in datasets):.1f} s, at least '
                         f'{RIGID_MIN_DATA_S} s) or what the case needs is missing')
    return update.model

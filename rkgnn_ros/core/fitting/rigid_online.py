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
  regressor (:func:`.case_one.fit_law` with :class:`~.rigid_law.GravityFeatures`; used only
  when the newest half of the data gives the same gains), the arm fitted on the torque;
- case 'pd_gains': the closed loop with the known gains;
- case 'unknown': the closed loop with the servo's gains fitted too (scale from the
  description's masses).

A fit whose held-out error (worst joint) is above :data:`MAX_ERROR` is not offered for
prediction (the model is still published, with its error). The closed-loop form (a
gravity compensation, an integral) is chosen by held-out error again every
:data:`FORMS_EVERY_S`; in between only the chosen form is refitted.
"""

import dataclasses
import math
from typing import List, NamedTuple, Optional, Sequence, Tuple

import numpy as np

from .case_one import fit_law, MAX_LAW_FIT_RATIO
from .online_records import ClosedLoop, GenerationStats, LogLine, model_update
from .online_rules import stale_stream
from .rigid_fit import fit_closed, fit_closed_forms, fit_torque, RigidFit
from .rigid_law import GravityFeatures
from .rigid_loop import RigidLoop
from .rigid_model import RigidModel
from .validation import MIN_SEGMENT_SAMPLES, split_validation
from ..data import Dataset
from ..rigid.structure import RigidStructure

__all__ = ['FORMS_EVERY_S', 'MAX_ERROR', 'MIN_DATA_S', 'REFRESH_S', 'RigidKeeper', 'RigidPolicy',
           'RigidUpdate', 'fit_rigid', 'refresh_events']

#: A fit predicts while its held-out error (worst joint) is at most this.
MAX_ERROR = 0.5

#: Seconds of data (gaps left out) before the first fit.
MIN_DATA_S = 2.0

#: Seconds between two choices of the closed loop's form.
FORMS_EVERY_S = 10.0

#: Seconds between two refits (at most).
REFRESH_S = 1.0


class RigidUpdate(NamedTuple):
    """What one refresh gave: the model to publish, its closed loop (None: none), log lines."""

    model: RigidModel
    loop: Optional[ClosedLoop]
    lines: List[Tuple[str, str]]


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
        self.fit: Optional[RigidFit] = None
        self.form: Optional[Tuple[bool, Optional[str]]] = None   # (integral, gravity)
        self._form_time = -math.inf
        self.refits = 0
        self._predicting = False

    def refresh(self, case: str, segments: Sequence[Dataset], validation_fraction: float,
                origin: float, now: float, kp=None, kd=None) -> Optional[RigidUpdate]:
        """
        Fit on ``segments`` (oldest first; ``origin``: the stamp time of their t = 0).

        ``kp``, ``kd``: the known gains of case 'pd_gains'. Returns None when there are
        too few data or the fit fails.
        """
        segments = [seg for seg in segments if seg.n_samples >= MIN_SEGMENT_SAMPLES]
        if sum(seg.duration for seg in segments) < MIN_DATA_S:
            return None
        train, validation, _ = split_validation(segments, validation_fraction,
                                                MIN_SEGMENT_SAMPLES)
        lines: List[Tuple[str, str]] = []
        if case == 'torque':
            fit, law = self._torque(segments, train, validation, lines)
        else:
            fit = self._closed(case, train, validation, now, kp, kd)
            law = None if fit is None else _integral_to_end(fit.law, segments)
        if fit is None:
            return None
        self.fit = fit
        self.refits += 1
        error = fit.error
        model = RigidModel(fit.arm, law, case, segments[-1].dt,
                           {'refits': self.refits, 'generation': self.refits,
                            'held_out_error': error,
                            'held_out_errors': fit.errors.tolist(),
                            'window_s': float(sum(seg.duration for seg in segments))})
        loop = None
        if law is not None and error <= MAX_ERROR:
            rigid = RigidLoop(fit.arm, law)
            rigid.torque_error = error
            loop = ClosedLoop(model, rigid, origin + float(segments[-1].t[-1]))
        if (loop is not None) != self._predicting:
            self._predicting = loop is not None
            what = 'torque error' if case == 'torque' else 'closed-loop equation error'
            lines.append(('info', f'the rigid-body model of the robot description predicts '
                                  f'(held-out {what} {error:.2%}, {law.describe()})')
                         if loop is not None else
                         ('warning', f'the rigid-body model does not predict: held-out '
                                     f'{what} {error:.2%} (bar {MAX_ERROR:.0%})'
                                     if law is not None else
                                     'the rigid-body model does not predict: the servo law '
                                     'is not determined by the data yet'))
        return RigidUpdate(model, loop, lines)

    def _torque(self, segments, train, validation, lines):
        paired = [seg for seg in segments if seg.tau is not None and seg.theta_d is not None]
        law = fit_law(paired, features=self.features) if paired else None
        if law is not None and law.usable(MAX_LAW_FIT_RATIO):
            if self.law is None or not law.close_to(self.law):
                lines.append(('info', f'servo law learned on the gravity regressor: '
                                      f'{law.describe()}, Kp {np.round(law.kp, 2).tolist()}, '
                                      f'Kd {np.round(law.kd, 2).tolist()}'))
            self.law = _integral_to_end(law, paired)
        elif self.law is not None:
            self.law = _integral_to_end(self.law, paired) if paired else self.law
        fit = fit_torque(self.structure, train, validation)
        return fit, self.law

    def _closed(self, case, train, validation, now, kp, kd) -> Optional[RigidFit]:
        if case == 'pd_gains':
            kp, kd = np.asarray(kp, dtype=float), np.asarray(kd, dtype=float)
        else:
            kp = kd = None
        if self.form is None or now - self._form_time >= FORMS_EVERY_S:
            fit = fit_closed_forms(self.structure, train, validation, kp, kd, self.features)
            if fit is not None:
                self._form_time = now
                law = fit.law
                self.form = (bool(np.any(law.ki != 0.0)),
                             law.theta_input if law.theta_weights.size else None)
            return fit
        integral, gravity = self.form
        return fit_closed(self.structure, train, validation, kp, kd, integral, gravity,
                          self.features)


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
    structure: it refits at most every :data:`REFRESH_S` and publishes the model at most
    every ``model_publish_period``; a reset, another structure or another case starts it
    afresh. ``emit`` takes events, ``set_status(state, detail, **numbers)`` the status,
    ``staleness`` is the policy's :class:`~.online_rules.Staleness`.
    """

    def __init__(self, clock, emit, set_status, staleness):
        self._clock, self._emit, self._set_status = clock, emit, set_status
        self._staleness = staleness
        self.keeper: Optional[RigidKeeper] = None
        self.model: Optional[RigidModel] = None
        self._last_refresh = -math.inf
        self._last_publish = -math.inf

    def data_due(self, obs, now: float) -> bool:
        """Return whether the next :meth:`step` refits (it then wants a capture)."""
        return stale_stream(obs, now) is None and now - self._last_refresh >= REFRESH_S

    def step(self, obs) -> bool:
        """Refit if due; return False (no generation of a search ran)."""
        keeper, settings = self.keeper, obs.settings
        if (obs.reset or keeper is None or keeper.structure is not obs.structure
                or keeper.case != settings.case):
            self._emit(LogLine('info', f'identifying the rigid body of '
                                       f'{obs.structure.describe()}, case {settings.case}'))
            self.keeper = keeper = RigidKeeper(obs.structure, settings.case)
            self._last_refresh = -math.inf
        now = self._clock()
        if obs.paused or obs.joints is None:
            self._set_status('paused' if obs.paused else 'waiting for data',
                             'paused' if obs.paused else 'no joint_states yet')
            return False
        if (not self._staleness.fresh(obs, now, lambda level, text: self._emit(
                LogLine(level, text)), self._set_status)
                or obs.data is None or now - self._last_refresh < REFRESH_S):
            return False
        self._last_refresh = now
        publish = now - self._last_publish >= settings.model_publish_period
        events, update = refresh_events(keeper, settings, obs.data, now, publish)
        for event in events:
            self._emit(event)
        if update is None:
            self._set_status('waiting for data', 'too few data for the rigid-body fit yet')
            return False
        if publish:
            self.model, self._last_publish = update.model, now
        error = float(update.model.info['held_out_error'])
        self._set_status('identifying', f'rigid-body fit {keeper.refits}, held-out error '
                                        f'{error:.3g}', generation=keeper.refits,
                         best_cost=error)
        return False


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
                         f'{MIN_DATA_S} s) or what the case needs is missing')
    return update.model

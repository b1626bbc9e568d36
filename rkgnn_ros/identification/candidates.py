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
Which model predicts: the one in use, the candidate on trial, and the offers waiting.

Every change of what a prediction rolls out is an *offer*: a new model from the search
(``ModelUpdate``), a loop fitted again or a new learned law (``LoopUpdate``: the servo law
of case 1, case 3's linear closed loop, any loop the policy closes), a loop withdrawn.
A loop is anything with ``simulate(x0, t, theta_d, theta_d_dot, integral)`` and a ``law``
(its ``integral_term`` and ``ki``), wrapped in a
:class:`~rkgnn_ros.core.fitting.online.ClosedLoop` with the model it closes.

The executor thread offers (:meth:`Models.offer_model`, :meth:`Models.offer_loop`); the
prediction thread, the only one that touches the self-check, takes the offers before each
prediction (:meth:`Models.take`):

- with nothing in use that predicts, an offer is taken into use at once: nothing of it is
  published before it has its scored predictions and passes the self-check;
- an offer that rolls out exactly what the slot in use rolls out (the same loop from the
  same integral time: a new search model while the trigonometric loop predicts) replaces
  it in place, with its scores;
- a loop withdrawn (an offer that predicts nothing) is taken at once: a baseline is
  published, which never needed a trial;
- any other offer is a candidate: it predicts beside the one in use, on the same targets,
  and replaces it only once its scored predictions earned it
  (:meth:`~rkgnn_ros.core.selfcheck.SelfCheck.trial`, :meth:`Models.judge`). The
  candidate's trial is never restarted: the newest offer waits for it to end (replacing
  an older one waiting), so refits that come faster than a trial takes (a loop fitted at
  every data refresh, 1 s, against about 3 s for 10 predictions scored 2 s ahead) still
  reach use, one trial after another; a candidate that cannot predict (a case-1 model
  whose law has not come with it) gives way to an offer waiting that can;
- a change of the arm's dynamics (:meth:`Models.dynamics_changed`, in the order of the
  offers) drops the candidate and the offer waiting: both were fitted on the arm before
  it, and the first offer after it starts its trial at once, judged on fewer scored
  predictions until a model holds again (:meth:`SelfCheck.dynamics_changed`); the
  predictor makes each new candidate's predictions again from the states since the change
  (:meth:`SelfCheck.replay_from`), so its trial need not wait 2 s for scores of its own,
  and the newest offer then takes the place of a candidate on trial for :data:`REPLACE_S`.

A loop with an integral term (a PID) predicts from its integral at each prediction's start
(:meth:`Models.integral`): the law's term at the data it was fitted on, carried on with the
recorded ∫ (θd − θ) dt from one prediction to the next, so a loop in use for longer than
the self-check keeps states (its window) still starts from the servo's integral.
"""

from collections import deque
import math
import threading
from typing import List, NamedTuple, Optional, Tuple

import numpy as np
from rkgnn_ros.core.fitting.online import ClosedLoop
from rkgnn_ros.core.model.model import RKGNNModel
from rkgnn_ros.core.selfcheck import SelfCheck

__all__ = ['REPLACE_S', 'Slot', 'Models', 'same_rollout', 'predicts', 'describe']

OFFER_LIMIT = 64  # offers kept between two predictions (older ones are superseded anyway)
#: After a change, the newest offer takes the place of a candidate on trial this long (s of
#: stamp time) at least: each takes a replay of up to 40 rollouts (0.3 s of the prediction
#: thread for the paper arm's trigonometric loop, whose refits came every 0.3-0.4 s).
REPLACE_S = 1.0


class Slot(NamedTuple):
    """What predicts: a model, closed with ``loop`` when the loop is the model's."""

    model: Optional[RKGNNModel]    # None: a closed loop predicts before any model (case 3)
    loop: Optional[ClosedLoop]


def _rollout(slot: Slot):
    """Return what ``slot`` rolls out: (the loop or the model, the loop's integral time)."""
    if slot.loop is not None and slot.loop.model is slot.model:
        return slot.loop.loop, slot.loop.integral_time
    return slot.model, None


def same_rollout(a: Optional[Slot], b: Optional[Slot]) -> bool:
    """Return whether two slots roll out exactly the same thing."""
    if a is None or b is None:
        return False
    (what, since), (other, other_since) = _rollout(a), _rollout(b)
    return what is not None and what is other and since == other_since


def predicts(slot: Optional[Slot]) -> bool:
    """
    Return whether ``slot`` can make a prediction at all.

    Case 1's model needs its law, a rigid body's any case its loop (a rigid body published
    while its fit does not predict comes without one).
    """
    if slot is None:
        return False
    what, _ = _rollout(slot)
    if what is None:
        return False
    return what is not slot.model or (slot.model.case != 'torque'
                                      and getattr(slot.model, 'kind', '') != 'rigid_body')


def describe(slot: Slot) -> str:
    """Return what ``slot`` is, for log lines."""
    model = slot.model
    name = ('the closed loop' if model is None else
            f"the model of generation {model.info.get('generation', '?')}")
    if model is not None and slot.loop is not None and slot.loop.model is model:
        name += ' with its loop'
    return name


class Models:
    """The slot in use, the candidate on trial and the offers (see the module docstring)."""

    def __init__(self):
        self._lock = threading.Lock()
        self._offers: deque = deque(maxlen=OFFER_LIMIT)
        self.in_use: Optional[Slot] = None
        self.candidate: Optional[Slot] = None
        self._waiting: Optional[Slot] = None
        self._trial_start = math.nan
        self._carried: dict = {}    # id(closed loop) -> (it, stamp time, integral term)

    # -- offers (any thread) ----------------------------------------------------------------

    def offer_model(self, model: RKGNNModel, loop: Optional[ClosedLoop] = None) -> None:
        """Offer a new model (``loop``: closed with a fitted servo law or a linear loop)."""
        with self._lock:
            self._offers.append(('model', Slot(model, loop)))

    def offer_loop(self, model: Optional[RKGNNModel], loop: Optional[ClosedLoop]) -> None:
        """
        Offer ``model`` with a new ``loop`` (None: the loop withdrawn).

        ``model`` None: ``loop`` predicts while no model is held (case 3's linear closed
        loop needs no searched model). A loop for a model no longer held is ignored.
        """
        with self._lock:
            self._offers.append(('loop', Slot(model, loop)))

    def dynamics_changed(self, since: Optional[float] = None) -> None:
        """Say that the arm's dynamics changed at ``since`` (s): what waits is stale (module)."""
        with self._lock:
            self._offers.append(('change', since))

    # -- the prediction thread --------------------------------------------------------------

    def take(self, check: SelfCheck, now: float) -> Tuple[Optional[Slot], Optional[Slot]]:
        """Take the offers (see the module); return the slot in use and the candidate."""
        with self._lock:
            offers = list(self._offers)
            self._offers.clear()
        for kind, slot in offers:
            self._place(kind, slot, check)
        if self.candidate is not None and self._waiting is not None and (
                not predicts(self.candidate) and predicts(self._waiting)
                or check.replay_from() is not None and not now - self._trial_start < REPLACE_S):
            # it cannot predict: it would hold the trial for nothing; or after a change,
            # where the newest offer's predictions are made again from the change on
            self.candidate = None
            check.discard_candidate()
        if self.candidate is None and self._waiting is not None:
            self.candidate, self._waiting = self._waiting, None
            self._trial_start = now
            check.discard_candidate()
        kept = {id(slot.loop) for slot in (self.in_use, self.candidate) if slot is not None}
        self._carried = {key: value for key, value in self._carried.items() if key in kept}
        return self.in_use, self.candidate

    def integral(self, closed: ClosedLoop, t0: float, check: SelfCheck,
                 carry: bool = True) -> np.ndarray:
        """
        Return ``closed``'s integral term (N m, (n,)) at stamp time ``t0`` (module docstring).

        Carried from the last time it was asked (or the loop's ``integral_time``) with the
        law's Ki times ∫ (θd − θ) dt the self-check recorded since; where the record does
        not reach back that far, the term is left where it was. ``carry`` False: from the
        loop's own time, before or after ``t0``, and not kept (a prediction made again from
        a past state).
        """
        law = closed.loop.law
        held = self._carried.get(id(closed)) if carry else None
        since, integral = ((held[1], held[2]) if held is not None and held[0] is closed
                           and held[1] <= t0 else (closed.integral_time, law.integral_term))
        if np.any(law.ki != 0.0):
            if t0 >= since:
                grown = check.error_integral(since, t0)
            else:
                grown = check.error_integral(t0, since)
                grown = None if grown is None else -grown
            if grown is not None:
                since, integral = t0, integral + law.ki * grown
        if carry:
            self._carried[id(closed)] = (closed, since, integral)
        return integral

    def restart_trial(self, now: float) -> None:
        """Start the candidate's trial again (the self-check was made anew)."""
        self._trial_start = now

    def _held(self, model) -> bool:
        return any(slot is not None and slot.model is model
                   for slot in (self.in_use, self.candidate, self._waiting))

    def _place(self, kind: str, slot: Optional[Slot], check: SelfCheck) -> None:
        if kind == 'change':
            check.dynamics_changed(slot)
            if self.candidate is not None:
                self.candidate = None
                check.discard_candidate()
            self._waiting = None
            return
        if kind == 'loop':
            if slot.model is None:
                if self.in_use is not None and self.in_use.model is not None:
                    return  # a model predicts now: a model-less loop comes too late
            elif not self._held(slot.model):
                return
        if not predicts(self.in_use) or kind == 'loop' and not predicts(slot) and (
                self.in_use.model is slot.model):
            self.in_use = slot
            check.forget_model()
            return
        if same_rollout(slot, self.in_use):
            self.in_use = slot
            return
        if same_rollout(slot, self.candidate):
            self.candidate = slot
            return
        self._waiting = slot   # the newest waits; the candidate's trial goes on

    def drop_candidate(self, check: SelfCheck) -> Optional[Slot]:
        """Drop the candidate (its rollout left the band); return it."""
        dropped, self.candidate = self.candidate, None
        check.discard_candidate()
        return dropped

    def judge(self, check: SelfCheck, now: float, window: float) -> Optional[str]:
        """
        Promote or drop the candidate once its trial has an answer; return the log line.

        A candidate not scored at every horizon within ``window`` seconds (the plan too
        short for its horizons?) is dropped.
        """
        candidate = self.candidate
        if candidate is None:
            return None
        verdict = check.trial()
        if verdict is None:
            if not now - self._trial_start > window:
                return None
            check.discard_candidate()
            self.candidate = None
            return (f'{describe(candidate)} is not used: it was not scored at every horizon '
                    f'within {window:g} s (a plan shorter than the horizon?)')
        if verdict.better:
            check.promote()
            self.in_use, self.candidate = candidate, None
        else:
            check.discard_candidate()
            self.candidate = None
        return (f'{describe(candidate)} ' + ('now predicts' if verdict.better else 'is not used')
                + ': ' + (verdict.why or f'{verdict.candidate:.2%} of the range on the scored '
                          f'horizons against {verdict.model:.2%} for the model in use'))

    def pending(self) -> List[Slot]:
        """Return the candidate and the offer waiting for a trial (for diagnostics)."""
        return [slot for slot in (self.candidate, self._waiting) if slot is not None]

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
Identification of a recording: the online policy run on data that is all there at once.

A recording should be identified the way the running node identifies the live streams, so
that a model fitted offline means what a model of the node means. :func:`identify_offline`
therefore drives the node's own policy (:class:`~.online.OnlineIdentification`, with its
warm start, controller law, held-out validation and publication rules) with a clock of its
own: the data are handed over once, every stream is always fresh, and the clock moves one
``model_publish_period`` per generation so each better model is published at once. It
stops at a wall-time budget or a generation count; the last published model is the result.

The budget is wall time: the warm start gets at most :data:`WARM_START_SHARE` of it, no
step starts that the last one's duration says would end past it, and once a model is
published every population evaluation stops at its end (:meth:`.budget.Budget.interrupting`).

:func:`heldout_prediction` scores a model on data it never saw the way the node predicts:
case 1 with a fitted controller law in closed loop along the recorded θd, otherwise
open loop (recorded torque in case 1, recorded θd in cases 2 and 3), each segment from its
first state. :func:`heldout_baselines` scores what needs no model on the same segments
(holding the first state; following the recorded reference), and :func:`judge` says
whether the model did better.
"""

from contextlib import contextmanager
from dataclasses import replace
import math
import time
from typing import Callable, Dict, List, NamedTuple, Optional, Sequence, Tuple

import numpy as np

from .budget import Budget
from .chain_online import ChainLearner
from .fitness import Interrupted
from .identify import nrmse, RKGNNModel
from .online import OnlineIdentification
from .online_records import (ClosedLoop, GenerationStats, LogLine, ModelUpdate, Observation,
                             OnlineSettings, Status)
from .policy import WARM_START_S
from ..data import Dataset

__all__ = ['OfflineResult', 'Verdict', 'heldout_baselines', 'heldout_prediction',
           'identify_offline', 'judge', 'WARM_START_SHARE']

#: Share of the budget the search's warm start (an equation-error fit) may take at most.
WARM_START_SHARE = 0.25


class OfflineResult(NamedTuple):
    """What :func:`identify_offline` found."""

    model: Optional[RKGNNModel]  # the last published model (None: no finite model)
    loop: Optional[ClosedLoop]   # case 1 with a fitted law: the model closed with it
    update: Optional[ModelUpdate]
    history: List[GenerationStats]
    log: List[LogLine]
    generations: int
    seconds: float
    status: Status


class OfflineOptions(NamedTuple):
    """The progress, clock and description options of :func:`identify_offline` (see there)."""

    progress_period_s: float = 2.0
    wall: Callable[[], float] = time.monotonic
    structure: object = None


def identify_offline(settings: OnlineSettings, capture, joints: Sequence[str],
                     budget_s: float = 90.0, max_generations: int = 0,
                     progress: Optional[Callable[[Status, float], None]] = None, **options
                     ) -> OfflineResult:
    """
    Run the online policy on a capture of recorded streams until the budget is spent.

    Parameters
    ----------
    settings : OnlineSettings
        The node's settings (from its parameters file).
    capture : StreamCapture
        The recorded streams (``segments()``, ``controller_samples()``), e.g. a
        ``StreamBuffer.capture()`` of the recording's training part.
    joints : sequence of str
        The joint names.
    budget_s : float
        Wall-time budget (s) for the whole search, warm start included.
    max_generations : int
        Stop after this many generations as well (0: only the budget).
    progress : callable, optional
        Called with the status and the elapsed seconds every ``progress_period_s``.
    progress_period_s : float
        Seconds between two calls of ``progress``.
    wall : callable
        The wall clock of the budget (tests pass a fake one).
    structure : RigidStructure, optional
        A robot description's structure of ``joints``: its rigid body is fitted in closed
        form instead of a search (:mod:`.rigid_online`), once, on the whole capture.

    Returns
    -------
    OfflineResult

    """
    progress_period_s, wall, structure = OfflineOptions(**options)
    clock = [0.0]
    status = [Status()]
    budget = Budget(budget_s, wall)
    # the data come once: a chain is learned before (chain_online.learn_chain), not here
    policy = OnlineIdentification(clock=lambda: clock[0],
                                  on_status=lambda new: status.__setitem__(0, new),
                                  warm_start_seconds=min(WARM_START_S,
                                                         WARM_START_SHARE * budget.seconds),
                                  chain_learner=ChainLearner(enabled=False))
    joints = tuple(joints)
    settings = replace(settings, max_generations=int(max_generations))
    history: List[GenerationStats] = []
    log: List[LogLine] = []
    update: Optional[ModelUpdate] = None
    loop: Optional[ClosedLoop] = None
    last_progress = -math.inf
    data = capture
    steps_without_generation = 0
    step_s = 0.0
    while True:
        received = {'state': clock[0], 'command': clock[0]}
        began = wall()
        try:  # once a model is published, the budget's end interrupts a generation
            with budget.interrupting() if update is not None else _nothing():
                result = policy.step(Observation(settings, joints, received, data=data,
                                                 structure=structure))
        except Interrupted:
            break
        step_s = wall() - began
        data = None  # the recording is handed over once
        for event in result.events:
            if isinstance(event, GenerationStats):
                history.append(event)
            elif isinstance(event, LogLine):
                log.append(event)
            elif isinstance(event, ModelUpdate):
                update, loop = event, event.loop
        clock[0] += max(settings.model_publish_period, 1.0) + 1e-3
        elapsed = budget.elapsed()
        if progress is not None and elapsed - last_progress >= progress_period_s:
            last_progress = elapsed
            progress(status[0], elapsed)
        steps_without_generation = 0 if result.ran else steps_without_generation + 1
        if budget.left() <= step_s or steps_without_generation >= 3:
            break
        if max_generations and policy.generation >= max_generations:
            # one more step publishes the best of the last generation
            result = policy.step(Observation(settings, joints, received,
                                             structure=structure))
            for event in result.events:
                if isinstance(event, ModelUpdate):
                    update, loop = event, event.loop
            break
    return OfflineResult(None if update is None else update.model, loop, update, history, log,
                         policy.generation, budget.elapsed(), status[0])


@contextmanager
def _nothing():
    yield


def heldout_prediction(model: RKGNNModel, segments: Sequence[Dataset],
                       loop: Optional[ClosedLoop] = None
                       ) -> Tuple[float, List[np.ndarray], str]:
    """
    Predict each held-out segment from its first state, as the node predicts.

    Parameters
    ----------
    model : RKGNNModel
        The published model.
    segments : sequence of Dataset
        Held-out data (with θd, θ̇d for a closed loop or cases 2 and 3; τ for case 1 open
        loop).
    loop : ClosedLoop, optional
        Case 1 with a fitted law: the model closed with it (``loop.loop``, the law's
        integral term as fitted held over the segment's start).

    Returns
    -------
    nrmse : float
        θ-NRMSE over every segment (NaN if none could be predicted).
    predicted : list of ndarray, shape (N_i, n)
        Predicted θ per segment.
    how : str
        What drove the prediction.

    """
    n = model.n_joints
    predicted, measured = [], []
    how = 'open loop, recorded torque' if model.case == 'torque' else 'recorded θd'
    for seg in segments:
        if loop is not None and seg.theta_d is not None:
            how = 'closed loop with the fitted controller law, recorded θd'
            states = loop.loop.simulate(seg.state[0], seg.t, seg.theta_d, seg.theta_d_dot)
        elif hasattr(model, 'predict'):
            states = model.predict(seg)
        else:    # a rigid-body model predicts only closed with its servo law
            return math.nan, [], 'no servo law to close the loop with'
        predicted.append(np.asarray(states)[:, :n])
        measured.append(seg.theta)
    if not predicted:
        return math.nan, [], how
    return float(nrmse(np.vstack(predicted), np.vstack(measured))), predicted, how


def heldout_baselines(segments: Sequence[Dataset]) -> Dict[str, float]:
    """
    Return the θ-NRMSE of predictions that need no model, on ``segments`` (as predicted).

    ``'hold_last_state'``: θ stays at each segment's first sample; ``'follow_reference'``
    (when every segment has θd): θ is the recorded reference. Both scored by the same
    :func:`~..scoring.nrmse` over all segments as :func:`heldout_prediction`. Empty
    without segments.
    """
    segments = list(segments)
    if not segments:
        return {}
    measured = np.vstack([seg.theta for seg in segments])
    held = np.vstack([np.repeat(seg.theta[:1], seg.n_samples, axis=0) for seg in segments])
    out = {'hold_last_state': float(nrmse(held, measured))}
    if all(seg.theta_d is not None for seg in segments):
        out['follow_reference'] = float(nrmse(np.vstack([seg.theta_d for seg in segments]),
                                              measured))
    return out


class Verdict(NamedTuple):
    """Whether a model beat the baselines on held-out data, and the line that says so."""

    judged: bool     # False: nothing held out, or no baseline
    worse: bool      # its θ-NRMSE is above the best baseline's (or not finite)
    baseline: str    # the best baseline ('' when not judged)
    text: str


def judge(model_nrmse: float, baselines: Dict[str, float]) -> Verdict:
    """Compare a model's held-out θ-NRMSE with the best of ``baselines``."""
    finite = {name: value for name, value in baselines.items() if math.isfinite(value)}
    if not finite or (model_nrmse is not None and math.isnan(model_nrmse)):
        return Verdict(False, False, '', 'not judged: no held-out part to predict')
    name = min(finite, key=finite.get)
    best = finite[name]
    shown = name.replace('_', ' ')
    if not model_nrmse <= best:
        return Verdict(True, True, name, f'the model is worse than {shown} on the held-out '
                       f'part: θ-NRMSE {model_nrmse:.4g} against {best:.4g}')
    return Verdict(True, False, name, f'the model beats {shown} on the held-out part: '
                   f'θ-NRMSE {model_nrmse:.4g} against {best:.4g}')

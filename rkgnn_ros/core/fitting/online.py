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
The online identification policy: when to search, warm-start, re-fit, validate and publish.

:class:`OnlineIdentification` decides what an identifier does between two generations,
and nothing else: no thread, lock, publisher or middleware handle, so its decisions are
tested with a fake clock and no ROS. In: one :class:`Observation` per
:meth:`~OnlineIdentification.step` (settings, joints, when each stream last delivered, the
pause and reset requests, and a capture of the buffered streams when
:meth:`~OnlineIdentification.data_due` asks for one). Out: events (:mod:`.online_records`)
for whoever owns the outputs, and the state shown to users through ``on_status``.

The rules (the node's documentation states them for users):

- A search is built when ``min_window`` seconds of training data are buffered, from a
  loaded model that fits the settings, else the equation-error fit (no rollout, a few
  seconds; case 3 first tries the servo's gains from a linear fit of the closed loop,
  :mod:`.case_three`); a start whose rollout diverges is not taken.
- The data are refreshed at most every :data:`DATA_REFRESH_S` (``Evolution.set_data``: the
  optimizer is kept); when the window has grown 1.5x since the last equation-error fit (an
  RBF case-3 search: or 10 s have passed; :class:`.search_starts.RewarmSchedule`), the fit
  runs again and replaces the best genome only if it is better.
- The newest ``validation_fraction`` of the data is held out (:func:`split_validation`);
  a changed best is validated every :data:`VALIDATION_EVERY` generations and before every
  publication (θ-NRMSE of the open-loop prediction from each segment's first state).
- The best changed model is published, at most every ``model_publish_period``.
- Case 'torque': the servo law is learned from effort and commands at each refresh
  (:mod:`.case_one`, :class:`.case_one.LawKeeper`). With a law the search runs in closed
  loop (a case-2 search with its gains, θd shifted by its other terms), the published model
  is the arm's (the law in ``info``), predictions roll the searched loop out; the search
  restarts when the law appears or goes, and goes on from its best genome when the gains
  move. Without a law it runs on the measured torque, and no model prediction is made.
  Where the planar trigonometric basis holds the arm, predictions roll that global arm out
  closed with the law instead (:meth:`.case_one.LawKeeper.fit_trig`).
- Cases 'unknown' and 'pd_gains': the arm and its servo fitted together by linear least
  squares on the trigonometric basis (:class:`.case_three.ArmKeeper`) predict while they
  explain held-out data; the search's model is published and predicts otherwise. (With
  known gains too: the closed loop's prediction does not depend on the common scale the
  fit leaves open, and the fit checks the servo's form on held-out data.)
- Without a robot description, in case 'torque' on 3 to 7 joints where the planar
  trigonometric arm does not hold, the arm's chain is learned in the background
  (:mod:`.chain_online`); no generation runs while its fit does (the fit takes the
  search's core; the published model and loops stay in use). An accepted chain is then
  used as a description's structure: the rigid-body policy takes over, the search ends.
- θ̇ of the buffered data is the centred derivative of θ when the observation says so.
- A stream silent for ``stale_timeout`` pauses the search (one warning); a reset, a change
  of the settings' ``version`` or of the case (``case: auto`` follows the streams) restarts
  it; ``max_generations`` ends it.
"""

from collections import deque
from dataclasses import replace
import math
import time
from typing import Callable, List, Optional, Tuple

import numpy as np

from . import case_three
from .case_one import LawKeeper, search_segments
from .case_three import ArmKeeper
from .chain_online import ChainLearner, ChainSteps
from .controller import ControllerLaw
from .fitness import between_chunks
from .identify import Evolution
from .memory import MemoryFeed
from .online_records import (AUTO_BASIS, ClosedLoop, GenerationStats, LogLine, LoopUpdate,
                             model_update, ModelUpdate, Observation, OnlineSettings, Status,
                             StepResult, StreamCapture)
from .online_rules import (auto_untried, EventLog, feed_memory, stale_stream, Staleness,
                           trig_holds)
from .policy import (DATA_REFRESH_S, EVOLUTION_MIN_PERIOD, LOG_THROTTLE_S,
                     MAX_CONSECUTIVE_ERRORS, MIN_SEGMENT_SAMPLES, VALIDATION_EVERY,
                     WAITING_REFRESH_S, WARM_START_NFEV, WARM_START_S, YOUNG_DATA_S,
                     YOUNG_WARM_START_S)
from .rigid_online import RigidPolicy
from .search_starts import (hand_over_settings, restart_around, rewarm, RewarmSchedule,
                            warm_start)
from .trig_change import ChangedMeanwhile, TrigChangeMonitor
from .validation import split_validation, validation_nrmse
from ..data import Dataset
from ..differentiate import centred_derivative
from ..model.model import RKGNNModel

__all__ = ['AUTO_BASIS', 'OnlineIdentification', 'OnlineSettings', 'Observation',
           'StreamCapture', 'Status', 'ClosedLoop', 'ModelUpdate', 'LoopUpdate',
           'GenerationStats', 'LogLine', 'StepResult', 'model_update', 'split_validation']

#: Cases whose predictions use the linear closed-loop fit on the trigonometric basis
#: (:class:`.case_three.ArmKeeper`): it needs neither torque nor the gains.
_CLOSED_FIT_CASES = ('unknown', 'pd_gains')


def _warm_budget(budget: float, seconds: float) -> float:
    """Return the real seconds one equation-error fit on ``seconds`` of data may take."""
    return min(budget, YOUNG_WARM_START_S) if seconds < YOUNG_DATA_S else budget


def _with_velocity(segments, estimate: bool) -> List[Dataset]:
    """Return ``segments``, θ̇ recomputed from θ by the centred derivative if ``estimate``."""
    return [replace(seg, theta_dot=centred_derivative(seg.theta, seg.dt)) if estimate
            else seg for seg in segments]


def _fits(model: Optional[RKGNNModel], joints, spec, case: str) -> bool:
    """Return whether a loaded ``model`` can start a search for ``spec`` in ``case``."""
    return (model is not None and model.joint_names == tuple(joints)
            and replace(model.spec, case=spec.case) == spec
            and (model.case == spec.case or model.case == case))


def _finished(settings: OnlineSettings, searching: bool, generation: int) -> bool:
    """Return whether a running search has reached ``es.max_generations``."""
    limit = settings.max_generations
    return bool(searching and limit and generation >= limit)


def _search_structure(settings: OnlineSettings, law: Optional[ControllerLaw], joints,
                      trig_holds: bool = False):
    """
    Return ``(spec, kp, kd)`` of a new search.

    Case 'torque' with a usable fitted law searches in closed loop: a case-2 search with the
    fitted gains. Case 'pd_gains' takes the known gains, one per joint. ``trig_holds``: the
    planar trigonometric arm explains held-out data (``network.basis: auto`` then searches
    the global network).
    """
    n = len(joints)
    spec = settings.spec(n, trig_holds)
    if spec.case == 'torque' and law is not None:
        return replace(spec, case='pd_gains'), law.kp, law.kd
    if spec.case == 'pd_gains':
        kp, kd = np.array(settings.kp), np.array(settings.kd)
        if kp.size != n or kd.size != n:
            raise ValueError(f"case 'pd_gains': kp has {kp.size} and kd {kd.size} values for "
                             f'the {n} joints {list(joints)}')
        return spec, kp, kd
    return spec, None, None


class _Publishing:
    """What :class:`OnlineIdentification` sends out: its models, their statistics."""

    def _best_model(self, joints) -> RKGNNModel:
        return self._evo.best_model(joints, {
            'generation': self._generation, 'evaluations': self._evaluations,
            'algorithm': self._algorithm})

    def _maybe_publish_model(self, settings: OnlineSettings, joints) -> None:
        """Publish the best model if it changed, at most every model_publish_period."""
        optimizer = self._evo.optimizer
        if not math.isfinite(optimizer.best_cost) or joints is None:
            return
        if self._published_genome is not None and np.array_equal(optimizer.best_x,
                                                                 self._published_genome):
            return
        if self._clock() - self._last_model_pub < settings.model_publish_period:
            return
        model = self._best_model(joints)
        key = (self._data_version, optimizer.best_x.tobytes())
        if key != self._val_key:
            self._val_nrmse = validation_nrmse(model, self._validation)
            self._val_key = key
            self._last_val_generation = self._generation
        model.info['validation_nrmse'] = (self._val_nrmse if math.isfinite(self._val_nrmse)
                                          else math.nan)
        if not math.isfinite(self._val_nrmse) and self._validation:
            self._out.log_throttled(
                'validation', 'warning',
                'the new best model diverges on the validation segment; publishing it anyway '
                '(its training cost is the best)')
        self._publish(model, settings)

    def _publish(self, model: RKGNNModel, settings: OnlineSettings) -> None:
        law = self._laws.law
        model, closed = self._laws.published(model, settings.case)
        gains = model.implied_gains()
        loop = self._arm3.close(model) if model.case in _CLOSED_FIT_CASES else None
        if model.case == 'torque' and law is not None:
            gains = (law.kp, law.kd)
            loop = self._laws.close(model, closed)
        self._model, self._loop = model, loop
        self._laws.after_change = False     # a model of the arm as it is now
        self._published_genome = (closed or model).genome.copy()
        self._last_model_pub = self._clock()
        self._out.append(model_update(model, loop, gains))


class OnlineIdentification(ChainSteps, _Publishing):
    """
    The identification policy, advanced by :meth:`step` between generations.

    Parameters
    ----------
    clock : callable
        Returns the time in seconds (monotonic); every rule but the warm start's
        computation budget uses it, so tests pass a fake clock.
    published : RKGNNModel, optional
        A model already published (loaded from a file): it starts the first search when it
        fits the settings.
    on_status : callable, optional
        Called with each new :class:`Status`.
    warm_start_seconds, warm_start_nfev : float, int
        Budget of one equation-error fit (real seconds, function evaluations); at most
        :data:`YOUNG_WARM_START_S` seconds while the data span less than :data:`YOUNG_DATA_S`.
    chain_learner : ChainLearner, optional
        Learns the chain of a spatial arm without a robot description (default one that
        fits in a background thread; tests pass their own).

    """

    def __init__(self, clock: Callable[[], float] = time.monotonic,
                 published: Optional[RKGNNModel] = None,
                 on_status: Optional[Callable[[Status], None]] = None,
                 warm_start_seconds: float = WARM_START_S,
                 warm_start_nfev: int = WARM_START_NFEV,
                 chain_learner: Optional[ChainLearner] = None):
        self._clock = clock
        self._on_status = on_status or (lambda status: None)
        self._warm_start_seconds = float(warm_start_seconds)
        self._warm_start_nfev = int(warm_start_nfev)
        self._status = Status()
        self._out = EventLog(clock, LOG_THROTTLE_S)  # the events of the current step
        self._model = published
        self._published_genome = None if published is None else published.genome.copy()
        self._last_model_pub = -math.inf if published is None else clock()
        self._start_model = published
        self._resume = None  # (genome, scales) a rebuilt search goes on from
        self._laws = LawKeeper()  # case 'torque': the law learned from torque and commands
        self._arm3 = ArmKeeper()  # case 'unknown': the linear closed loop on the trig basis
        self._loop: Optional[ClosedLoop] = None  # what the published model predicts with
        self._evo: Optional[Evolution] = None
        self._evo_version = -1
        self._evo_case = ''
        self._evo_law: Optional[ControllerLaw] = None  # the law a closed-loop search runs with
        self._rewarm = RewarmSchedule()  # when the equation-error fit runs again
        self._algorithm = ''
        self._generation = 0
        self._evaluations = 0
        self._gen_times: deque = deque(maxlen=20)
        self._validation: List[Dataset] = []
        self._data_version = 0
        self._last_refresh = -math.inf
        self._val_nrmse = math.nan
        self._val_key = None
        self._last_val_generation = -VALIDATION_EVERY
        self._last_stats = -math.inf
        self._staleness = Staleness()
        self._rigid = RigidPolicy(clock, self._out.append, self._set_status, self._staleness)
        self._chain = ChainLearner() if chain_learner is None else chain_learner
        self._changes = TrigChangeMonitor()  # a change of the dynamics, without a description
        self._memory = MemoryFeed()  # samples that keep the linear fit's regressor rich
        self._had_finite = False
        self._failures = None  # (optimizer, its numerical failures) last seen

    @property
    def generation(self) -> int:
        """Return the generations run by the current search."""
        return self._generation

    def data_due(self, obs: Observation) -> bool:
        """Return whether the next :meth:`step` with ``obs`` refreshes the data (wants it)."""
        searching = self._searching(obs)
        if (obs.paused or obs.joints is None
                or _finished(obs.settings, searching, self._generation)):
            return False
        now = self._clock()
        obs = self._with_learned(obs)
        if obs.structure is not None:   # the rigid body is refitted instead of searched
            return self._rigid.data_due(obs, now)
        if obs.settings.case == 'torque' and self._changes.due(now):
            return True
        if stale_stream(obs, now) is not None:
            return False
        since = now - self._last_refresh if searching or self._evo is None else math.inf
        return since >= DATA_REFRESH_S or (not searching and since >= WAITING_REFRESH_S)

    def step(self, obs: Observation) -> StepResult:
        """
        Run one generation if the observation allows it; return what happened.

        Before the generation the search is restarted (reset, restarting settings),
        paused (pause, stale streams), built or given new data (refresh due and
        ``obs.data`` given), and handed new optimizer settings. With a robot description
        (``obs.structure``) no search runs: :class:`.rigid_online.RigidPolicy` refits.
        """
        ran = self._step(obs)
        return StepResult(ran, self._out.take())

    def report_error(self, error: BaseException, in_a_row: int) -> List[object]:
        """
        Record that a step raised ``error`` (the ``in_a_row``-th failure in a row).

        The state becomes 'error'; after :data:`MAX_CONSECUTIVE_ERRORS` in a row the search
        restarts. Returns the events (log lines) this causes.
        """
        if in_a_row >= MAX_CONSECUTIVE_ERRORS:
            self._drop_search(f'{in_a_row} errors in a row')
        self._set_status('error', f'{type(error).__name__}: {error}')
        return self._out.take()

    def _step(self, obs: Observation) -> bool:
        settings = obs.settings
        obs = self._chain_step(obs)
        if obs.structure is not None:   # a robot description: its rigid body, no search
            if self._evo is not None:
                self._drop_search('the robot description gives the model'
                                  if obs.structure is not self._chain.structure else
                                  'the learned chain gives the model')
            # a learned chain's rigid body starts after the newest change the search saw
            self._rigid.since = self._changes.since if obs.structure is self._chain.structure \
                else -math.inf
            return self._rigid.step(obs)
        if obs.reset:
            self._drop_search('~/reset')
            self._start_model = None
            self._memory.reset()
        if self._evo is not None and self._evo_version != settings.version:
            self._drop_search('structural parameters changed')
        if self._evo is not None and self._evo_case != settings.case:
            self._drop_search(f'the case is now {settings.case} (the streams changed)')
        if self._evo is not None:
            self._maybe_publish_model(settings, obs.joints)
        if obs.paused:
            self._set_status('paused', f'paused at generation {self._generation}')
            return False
        if _finished(settings, self._evo is not None, self._generation):
            self._set_status('finished',
                             f'es.max_generations ({settings.max_generations}) reached')
            return False
        if obs.joints is None:
            self._set_status('waiting for data', 'no joint_states yet (joints unknown)')
            return False
        if not self._staleness.fresh(obs, self._clock(), self._out.log, self._set_status):
            return False
        events = [] if obs.data is None or settings.case != 'torque' else \
            self._changes.observe(obs.data, self._laws.trig, settings.validation_fraction,
                                  self._clock(), obs.joints)
        if events:
            self._changed(events)
        since = self._clock() - self._last_refresh
        due = since >= DATA_REFRESH_S or (self._evo is None and since >= WAITING_REFRESH_S)
        if due and obs.data is not None:
            if not self._refresh_data(settings, obs.data, obs.joints, obs.estimate_velocity):
                return False
        elif self._evo is None:  # waiting for enough data: look again in a moment
            return False
        if self._chain.running:  # the chain's fit has the search's core meanwhile
            return False
        line = hand_over_settings(self._evo, self._algorithm, settings, self._generation + 1)
        self._algorithm = settings.optimizer
        if line:
            self._out.log('info', line)
        # a change is looked for between the chunks of a generation too (it takes seconds)
        previous = between_chunks(lambda: self._changes.meanwhile(obs, self._laws.trig,
                                                                  self._clock()))
        try:
            stats = self._evo.step()
        except ChangedMeanwhile as changed:
            self._changed(changed.events)
            return True
        finally:
            between_chunks(previous)
        self._after_generation(settings, stats, obs.joints)
        return True

    def _changed(self, events: List[object]) -> None:
        """Say the change; drop what the data before it built; restart the search."""
        self._out.extend(events)
        self._laws.changed()
        self._memory = MemoryFeed()
        self._chain.changed(self._changes.since)
        if self._evo is not None:
            self._drop_search('the dynamics changed')

    def _searching(self, obs: Observation) -> bool:
        """Return whether a search will be running after the restarts of ``obs``."""
        return (self._evo is not None and not obs.reset
                and self._evo_version == obs.settings.version
                and self._evo_case == obs.settings.case)

    def _refresh_data(self, settings: OnlineSettings, capture, joints,
                      estimate_velocity: bool = False) -> bool:
        """Take the captured data; build the search or hand it the new data."""
        self._last_refresh = self._clock()
        law = None
        fraction, fitted = settings.validation_fraction, (False, None)
        if settings.case == 'torque':     # after a change of the dynamics: its data only
            paired = _with_velocity(self._changes.recent(capture.segments(
                MIN_SEGMENT_SAMPLES, True), capture.time_origin), estimate_velocity)
            self._feed_memory(settings, paired, capture.time_origin)
            law = self._update_law(paired, capture.time_origin) or self._laws.law
        if law is not None:  # the closed-loop search: θd shifted by the law's other terms
            segments = search_segments(paired, law)
            fitted = self._laws.fit_trig(paired, fraction, self._clock(), self._memory.samples)
        else:
            segments = _with_velocity(capture.segments(MIN_SEGMENT_SAMPLES, False),
                                      estimate_velocity)
            if settings.case != 'torque':   # the closed loop's samples, θ̇ from θ as it fits
                self._feed_memory(settings, _with_velocity(segments, True),
                                  capture.time_origin)
            if settings.case in _CLOSED_FIT_CASES:
                fitted = self._arm3.fit(segments, fraction, capture.time_origin, self._clock(),
                                        self._memory.samples)
        self._chain_feed(settings, joints, paired if law is not None else segments, capture)
        if fitted[0]:  # a global arm on the trigonometric basis predicts where it holds
            self._reclose(fitted[1], settings.case)
        train, validation, seconds = split_validation(
            segments, settings.validation_fraction, MIN_SEGMENT_SAMPLES)
        untried = self._evo is None and auto_untried(settings, law, self._laws, self._arm3)
        if seconds < settings.min_window or not train or untried:
            self._set_status('waiting for data', 'the arm on the trigonometric basis is tried '
                             'first' if untried and train else
                             f'{seconds:.1f} s of {settings.min_window} s buffered')
            return False
        if self._evo is None:
            self._build_search(settings, train, joints, seconds)
            self._rewarm.placed(seconds, self._clock())
        else:
            self._evo.set_data(train)
            # no equation-error fit either while the chain's fit runs (it has the core)
            if not self._chain.running and self._rewarm.due(self._evo.spec, seconds,
                                                            self._clock()):
                self._rewarm.placed(seconds, self._clock())
                self._out.log('info', rewarm(self._evo, train, seconds, _warm_budget(
                    self._warm_start_seconds, seconds), self._warm_start_nfev))
            if self._had_finite and not math.isfinite(self._evo.optimizer.best_cost):
                self._out.log_throttled(
                    'diverges', 'warning',
                    'the best model diverges on the new data window: the last good model '
                    'stays published until a finite one is found')
        self._validation = validation
        self._data_version += 1
        return True

    def _feed_memory(self, settings: OnlineSettings, segments, origin: float) -> None:
        warning = feed_memory(self._memory, settings, segments, origin)
        if warning:
            self._out.log_throttled('memory', 'warning', warning)
        self._set_status(self._status.state, self._status.detail,
                         condition_number=self._memory.condition_number(),
                         memory_samples=self._memory.size)

    def _reclose(self, line: Optional[Tuple[str, str]], case: str) -> None:
        """Log ``line``; close the published model (``case`` if none yet) for prediction."""
        if line is not None:
            self._out.log(*line)
        model = self._model  # None: a global loop may predict before any model
        if model is None or model.case in ('torque',) + _CLOSED_FIT_CASES:
            torque = (case if model is None else model.case) == 'torque'
            self._loop = (self._laws if torque else self._arm3).close(model)
            self._out.append(LoopUpdate(model, self._loop))

    def _update_law(self, segments: List[Dataset], origin: float) -> Optional[ControllerLaw]:
        """
        Case 'torque': learn the servo law again; return the law the search runs with.

        ``segments`` carry the commands paired with the states (``origin``: the stamp time
        of their t = 0); :meth:`.case_one.LawKeeper.refit` says what the refit means. A law
        that moved rebuilds the search from its best genome (an arm model whatever the
        gains), one that appeared or went restarts it.
        """
        searching = self._evo is not None
        refit = self._laws.refit(segments, origin, self._evo_law if searching else None,
                                 self._changes.since > -math.inf)
        if refit.kind == 'keep':
            if searching:
                self._evo_law = refit.law
            return refit.law
        if searching and refit.kind == 'moved':
            resume = (self._evo.optimizer.best_x.copy(), self._evo.scales)
            self._drop_search(f'the controller law moved (Kp '
                              f'{np.round(refit.law.kp, 2).tolist()}, Kd '
                              f'{np.round(refit.law.kd, 2).tolist()}); it goes on from its '
                              'best genome')
            self._resume = resume
        elif searching:
            self._drop_search('the controller law changed')
        self._reclose(refit.line, 'torque')
        return refit.law

    def _build_search(self, settings: OnlineSettings, train, joints, seconds: float) -> None:
        law = self._laws.law
        holds = trig_holds(self._laws, self._arm3, settings.case, self._start_model)
        spec, kp, kd = _search_structure(settings, law, joints, holds)
        algorithm = settings.optimizer
        x0 = scales = None
        origin = 'the default genome'
        if _fits(self._start_model, joints, spec, settings.case):
            x0, scales, origin = self._start_model.genome, self._start_model.scales, \
                'the loaded model'
        elif self._resume is not None and self._resume[0].size == spec.genome_size:
            (x0, scales), origin = self._resume, 'the best genome before the law moved'
        self._resume = None
        self._evo_law = law if spec.case != settings.case else None
        self._evo_case = settings.case
        self._evo = Evolution(spec, train, optimizer=algorithm,
                              settings=dict(settings.optimizer_settings), seed=settings.seed,
                              kp=kp, kd=kd, substeps=settings.substeps or None, scales=scales,
                              x0=x0)
        if x0 is None:
            self._set_status('evolving', 'warm start: equation-error fit')
            budget = _warm_budget(self._warm_start_seconds, seconds)
            placed = case_three.start_genome(self._evo, train, budget, self._warm_start_nfev)
            if placed is not None:
                restart_around(self._evo.optimizer, placed.genome, placed.cost)
            origin = (placed.origin if placed is not None else
                      warm_start(self._evo, train, kp, kd, budget, self._warm_start_nfev)
                      or origin)
        elif origin.startswith('the best genome'):
            optimizer = self._evo.optimizer
            restart_around(optimizer, x0, float(self._evo.problem.cost(x0[None])[0]))
        self._start_model = None
        self._evo_version = settings.version
        self._algorithm = algorithm
        self._generation = 0
        self._evaluations = 0
        self._had_finite = False
        self._out.log('info',
                      f'search started from {origin}: case {spec.case}, joints {list(joints)}, '
                      f'{spec.genome_size} genome elements, {algorithm} with population '
                      f'{self._evo.optimizer.population_size}, {self._evo.substeps} substeps, '
                      f'{seconds:.1f} s of data')

    def _drop_search(self, why: str) -> None:
        if self._evo is not None:
            self._out.log('info', f'restarting the search after generation '
                                  f'{self._generation}: {why}')
        self._evo = None
        self._resume = None
        self._generation = 0
        self._evaluations = 0
        self._gen_times.clear()
        self._val_nrmse = math.nan
        self._val_key = None
        self._last_refresh = -math.inf
        self._status = Status()
        self._set_status('waiting for data', f'search restarts: {why}')

    def _after_generation(self, settings: OnlineSettings, stats: dict, joints) -> None:
        self._generation += 1
        self._evaluations += int(stats['population'])
        now = self._clock()
        self._gen_times.append(now)
        span = self._gen_times[-1] - self._gen_times[0]
        rate = (len(self._gen_times) - 1) / span if span > 0 else 0.0
        optimizer = self._evo.optimizer
        if math.isfinite(optimizer.best_cost):
            self._had_finite = True
        failures = (id(optimizer), optimizer.failures)
        if optimizer.failures and failures != self._failures:
            self._out.log_throttled(
                'optimizer', 'warning',
                f'{self._algorithm} failed numerically ({optimizer.last_failure}): restarted '
                f'around the best genome (J {optimizer.best_cost:.4g}; {optimizer.failures} '
                'time(s) in this search)')
        self._failures = failures
        key = (self._data_version, optimizer.best_x.tobytes())
        if (self._validation and key != self._val_key and math.isfinite(optimizer.best_cost)
                and self._generation - self._last_val_generation >= VALIDATION_EVERY):
            self._val_nrmse = validation_nrmse(self._best_model(joints), self._validation)
            self._val_key = key
            self._last_val_generation = self._generation
        self._maybe_publish_model(settings, joints)
        if now - self._last_stats >= EVOLUTION_MIN_PERIOD:
            self._last_stats = now
            self._out.append(GenerationStats(
                self._generation, stats['best_cost'], stats['mean_cost'], stats['spread'],
                self._evaluations, self._val_nrmse, stats['population'],
                self._status.condition_number, self._memory.size))
        self._set_status('evolving', f'generation {self._generation}',
                         generation=self._generation, best_cost=stats['best_cost'],
                         validation_nrmse=self._val_nrmse, generations_per_s=rate,
                         population_size=int(stats['population']))

    def _set_status(self, state: str, detail: str, **numbers) -> None:
        self._status = self._status._replace(state=state, detail=detail, **numbers)
        self._on_status(self._status)

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
The prediction service: the model rolled out from the newest state, checked as it goes.

:class:`Predictor` owns the prediction thread. A request (the ``prediction.rate`` timer, or
an accepted state with ``prediction.on_state``) wakes it; requests that arrive while a
prediction runs collapse into one, which starts from the newest state. The compiled rollout
releases the GIL, so the 1 kHz ingestion never waits behind it. Inputs over the horizon are
snapshots, never live buffers: the newest plan (:class:`~rkgnn_ros.streams.buffer.
PlannedReference`, immutable), else the newest command held.

What is published (:mod:`rkgnn_ros.core.selfcheck` keeps the score):

- Every prediction is scored against what the arm then did, beside following the reference
  (the plan) and holding the last state, per horizon (a quarter, half and all of
  ``prediction.horizon``) and per joint, over the last ``selfcheck.window`` seconds. Until
  the model is ``selfcheck.margin`` better than the better baseline on every joint, and as
  soon as it is worse on one, the better baseline is published instead, and the switch is
  logged with its reason.
- Every change of what rolls out (a new model from the search, a loop fitted again, a new
  learned law) is a *candidate* (:mod:`rkgnn_ros.identification.candidates`): it predicts
  beside the model in use, and replaces it only once its own scored predictions earned it
  on the same targets (:meth:`~rkgnn_ros.core.selfcheck.SelfCheck.trial`). Nothing
  reaches ``~/prediction`` unjudged. After a change of the dynamics a new candidate also
  predicts again from the starts since it (:mod:`rkgnn_ros.identification.replay`).
- A rollout that leaves the band the plan and the recent errors allow
  (:mod:`rkgnn_ros.core.band`) is not believed: the model in use is withdrawn at once (a
  baseline goes out instead of that very prediction) until its predictions since are
  scored; a candidate is dropped.
- Horizons: with ``prediction.beyond_plan: stop`` a prediction ends where the plan ends
  (no plan, no prediction); with 'hold' it goes on with the plan's last point (or the
  newest command) held, and says from where.
- ``header.frame_id`` says what a prediction is: ``model``, ``baseline:follow_reference`` or
  ``baseline:hold_last``, followed by ``;beyond_plan_from=<s>`` when points past the
  plan's end are included. ``~/prediction_uncertainty`` (same stamp, joints and times)
  carries, as positions, the expected θ error (rad): the published predictor's RMSE per
  horizon over the window, measured on this arm lately (NaN until scored), linear in
  between (0 at the start, a measured state). ``~/predicted_state`` is the published
  prediction's state ``prediction.lookahead`` ahead, stamped at that time, same frame_id.

Case 1 closes the learned servo law around the arm model
(:class:`~rkgnn_ros.core.fitting.online_records.ClosedLoop`): its integral term is the
law's at the data it was fitted on, carried on to the start with the errors since
(:meth:`~rkgnn_ros.identification.candidates.Models.integral`). A
prediction is checked finite (else counted ``prediction_non_finite`` and a baseline
goes out), serialized straight to CDR and handed over as a :class:`Prediction` to
``publish``: the identifier queues it for its executor thread, which publishes it and calls
:meth:`Predictor.published`, so the latency kept for ``/diagnostics`` runs from the
middleware's receipt of the state to the actual publish.
"""

from collections import deque
import math
import threading
import time
from typing import Callable, NamedTuple, Optional, Tuple

from builtin_interfaces.msg import Time
import numpy as np
from rkgnn_ros.core.fitting.online import ClosedLoop, LogLine
from rkgnn_ros.core.model.model import RKGNNModel
from rkgnn_ros.core.selfcheck import SelfCheck
from rkgnn_ros.identification.candidates import describe, Models, predicts, Slot
from rkgnn_ros.identification.horizon import FromReference, HeldCommand, Horizon
from rkgnn_ros.identification.replay import Replay
from rkgnn_ros.identification.threads import ThreadPart
from rkgnn_ros.wire.conversions import make_joint_state, serialize_joint_trajectory
from sensor_msgs.msg import JointState

__all__ = ['LATENCY_WINDOW', 'JOINT_SCORE_COLUMNS', 'SCORE_LABELS', 'Prediction', 'Predictor',
           'ScoreReport', 'score_labels']

LATENCY_WINDOW = 1000  # predictions whose latency the diagnostics summarise
MAX_SUBSTEPS = 64  # RKG steps per model_step at most (the substeps parameter's bound)
DECIDE_EVERY_S = 0.1   # the publish decision is taken again at most this often (stamp time)
RESCORE_EVERY_S = 0.1  # the self-check's scores are computed again at most this often
#: A candidate model predicts beside the model about this often (stamp time, s): its
#: trial compares the two on the same targets, and at 1 kHz with prediction.on_state a
#: second rollout per prediction took half of the prediction thread.
CANDIDATE_EVERY_S = 0.1
#: Predictions closer than this (stamp time, s) to the last scored one are published but not
#: scored: at 1 kHz with prediction.on_state the scoring after each prediction took 40 % of
#: the prediction thread, and a new state waited for it (bench/latency.py's p99). The
#: self-check still gets 50 scored predictions a second; at prediction.rate 10 Hz it gets
#: every one.
SCORE_EVERY_S = 0.02
REPORT_EVERY_S = 1.0   # scores handed to the executor this often (stamp time)
CLOCK_JUMP_S = 1.0     # a state this much older than the last restarts the self-check
MIN_GAP_S = 0.25       # states further apart: the predictions over them are not scored

#: The first columns of ``~/prediction_scores`` (one row per scored horizon): the scores
#: averaged over the joints, and the model's count of scored predictions.
SCORE_LABELS = ('horizon_s', 'model', 'follow_reference', 'hold_last', 'published', 'count')
#: Then, per joint, these columns labelled ``<column>:<joint>`` (see :func:`score_labels`).
JOINT_SCORE_COLUMNS = ('model', 'follow_reference', 'hold_last', 'published', 'noise_floor')


def score_labels(joints) -> Tuple[str, ...]:
    """
    Return the column labels of ``~/prediction_scores`` for ``joints``.

    :data:`SCORE_LABELS` (the scores averaged over the joints), then for each joint in turn
    :data:`JOINT_SCORE_COLUMNS` as ``model:<joint>``, ... ``noise_floor:<joint>``: the
    windowed RMSE / that joint's θ range of each predictor, and the score below which an
    error is that joint's encoder noise (``SelfCheck.noise_floor``). A comma in a joint's
    name becomes ';' (the layout's label is comma-separated).
    """
    return SCORE_LABELS + tuple(f"{column}:{str(joint).replace(',', ';')}"
                                for joint in joints for column in JOINT_SCORE_COLUMNS)


def _due(now: float, last: float, every: float) -> bool:
    """Return whether ``every`` s passed since ``last`` (or the clock went back)."""
    return not 0.0 <= now - last < every


def _on_schedule(now: float, due: float, every: float) -> bool:
    """Return whether a task run every ``every`` s is due at ``now``: from ``due`` - every/4."""
    return not -2.0 * every <= now - due < -0.25 * every


def _next_due(now: float, due: float, every: float) -> float:
    """Return when the task of :func:`_on_schedule` run at ``now`` is due next (s)."""
    return due + every if -0.25 * every <= now - due <= 0.75 * every else now + every


class Prediction(NamedTuple):
    """A prediction to publish: its CDR bytes, its state's receipt (ns) if new, and more."""

    data: bytes
    received_ns: Optional[int]  # None: predicted again from the same state
    uncertainty: Optional[bytes] = None  # ~/prediction_uncertainty, CDR
    state: Optional[JointState] = None  # ~/predicted_state: the state prediction.lookahead on


def _state_ahead(stamp, joints, t, positions, velocities, lookahead: float, frame: str):
    """
    Return the predicted JointState ``lookahead`` s after the state stamped ``stamp``.

    Interpolated linearly between the prediction's points (its last one where it ends
    sooner, at the plan's end), stamped at the time it predicts, effort NaN,
    ``header.frame_id`` the prediction's; None when ``lookahead`` is 0.
    """
    if lookahead <= 0.0:
        return None
    ahead = min(float(lookahead), float(t[-1]))
    position = [float(np.interp(ahead, t, positions[:, j])) for j in range(len(joints))]
    velocity = [float(np.interp(ahead, t, velocities[:, j])) for j in range(len(joints))]
    sec, nanosec = divmod(stamp[0] * 1_000_000_000 + stamp[1] + int(round(ahead * 1e9)),
                          1_000_000_000)
    state = make_joint_state(Time(sec=int(sec), nanosec=int(nanosec)), list(joints), position,
                             velocity, None)
    state.header.frame_id = frame
    return state


class ScoreReport(NamedTuple):
    """The self-check's state: what is published and why, and the scores per horizon."""

    source: str
    reason: str
    table: np.ndarray  # (H, len(labels))
    labels: Tuple[str, ...] = SCORE_LABELS  # the columns (:func:`score_labels`)


class Predictor(ThreadPart):
    """
    Predictions from the newest state, scored and chosen, in a thread of their own.

    Parameters
    ----------
    ingestion : Ingestion
        Where the newest state, command, plan and the self-check's feed come from, and
        where a non-finite prediction or an internal error is counted.
    publish : callable
        Called with each :class:`Prediction`, :class:`ScoreReport` and log line (from the
        prediction thread).
    config : callable
        Returns the current parameters.

    """

    thread_name = 'rkgnn_prediction'

    def __init__(self, ingestion, publish: Callable[[object], None], config: Callable):
        self._ingestion = ingestion
        self._publish = publish
        self._config = config
        self._models = Models()  # in use, on trial, offered
        self._check: Optional[SelfCheck] = None
        self._check_key = None
        self._fed = -math.inf  # stamp of the newest state fed to the self-check
        self._decision = None
        self._decided_at = -math.inf
        self._sigma = None  # (source, K, last offset, the uncertainty (K, n)) in use
        self._reported_at = -math.inf
        self._candidate_due = -math.inf  # stamp time the candidate's next rollout is due
        self._scored_at = -math.inf  # stamp time of the last prediction scored
        self._replay = Replay(CANDIDATE_EVERY_S)  # starts a candidate after a change redoes
        self._ready = threading.Event()  # the rollout kernels ran once (compiled)
        self._wanted = threading.Event()
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._latencies: deque = deque(maxlen=LATENCY_WINDOW)  # ms, newest predictions
        self._last_predicted_ns = None  # receipt time of the state last predicted from
        self._thread: Optional[threading.Thread] = None
        #: what the inputs over the horizon of the last prediction were (for diagnostics)
        self.inputs = 'none yet'
        #: the newest ScoreReport (for diagnostics)
        self.report: Optional[ScoreReport] = None

    # ------------------------------------------------------------------ models

    def set_model(self, model: RKGNNModel, loop: Optional[ClosedLoop] = None) -> None:
        """
        Offer a new model (any thread): a candidate, or in use at once if nothing predicts.

        ``loop``: the model closed with a fitted servo law (case 1 predicts only so; case 3
        with the linear closed loop where it holds). See
        :mod:`rkgnn_ros.identification.candidates`.
        """
        self._models.offer_model(model, loop)

    def update_loop(self, model: Optional[RKGNNModel], loop: Optional[ClosedLoop]) -> None:
        """
        Offer ``model`` with ``loop`` (a loop fitted again, a new learned law): a candidate.

        ``model`` None: ``loop`` predicts until the first model arrives (case 3's linear
        closed loop needs no searched model); ``loop`` None withdraws the loop at once.
        """
        self._models.offer_loop(model, loop)

    def dynamics_changed(self, since: Optional[float] = None) -> None:
        """Drop the candidate and the offer waiting: the arm changed at ``since`` (s)."""
        self._models.dynamics_changed(since)

    # ------------------------------------------------------------------ latency

    def request(self) -> None:
        """Ask for a prediction from the newest state (requests collapse while one runs)."""
        self._wanted.set()

    def published(self, prediction: Prediction) -> None:
        """Record that ``prediction`` was published now (its state's latency, if new)."""
        if prediction.received_ns is not None:
            latency = 1e-6 * (time.time_ns() - prediction.received_ns)  # ms, receipt -> publish
            with self._lock:
                self._latencies.append(latency)

    def latencies(self) -> np.ndarray:
        """Return the newest state-to-publish times (ms), oldest first."""
        with self._lock:
            return np.array(self._latencies)

    def warm_up(self, model: RKGNNModel) -> None:
        """Run the compiled rollout once in the calling thread, so predictions never compile."""
        if self._ready.is_set():
            return
        if hasattr(model, 'warm_up'):      # a rigid-body model compiles its own rollout
            model.warm_up()
            self._ready.set()
            return
        n = model.n_joints
        t = np.arange(3) * model.dt
        zeros = np.zeros((t.size, n))
        x0 = np.concatenate([model.scales.theta_center, np.zeros(n)])
        if model.case == 'torque':
            model.simulate(x0, t, tau=zeros)
        else:
            model.simulate(x0, t, theta_d=zeros, theta_d_dot=zeros)
        self._ready.set()

    # ------------------------------------------------------------------ predicting

    def predict(self) -> bool:
        """Publish one prediction from the newest state, then score it; return if one was."""
        latest, joints = self._ingestion.latest_state, self._ingestion.joints
        if latest is None or joints is None:
            return False
        cfg = self._config()
        check = self._self_check(cfg, joints)
        horizon = self._horizon(cfg, latest.t)
        if horizon is None:
            return False
        t = horizon.t
        model, candidate = self._models.take(check, latest.t)
        x0 = np.concatenate([latest.theta, latest.theta_dot])
        mine = self._rollout(model, joints, x0, horizon, latest.t, check)
        publishable = ('follow_reference',) if horizon.theta_d is not None else ()
        decision = self._decision
        if (mine is not None and self._outside(check, latest, horizon, mine[0], joints)
                or decision is not None and decision.source == 'model' and check.withdrawn()):
            self._decided_at = -math.inf   # withdrawn: this prediction is a baseline
            decision = None
        if decision is None:
            decision = self._decide(check, latest.t, publishable)
        source = decision.source
        if source == 'model' and mine is None or \
                source == 'follow_reference' and not publishable:
            source = publishable[0] if publishable else 'hold_last'
        positions, velocities = self._published(source, mine, horizon, latest)
        frame = 'model' if source == 'model' else f'baseline:{source}'
        if horizon.beyond is not None:
            frame += f';beyond_plan_from={horizon.beyond:.3f}'
        sec, nanosec = latest.stamp
        stamp = Time(sec=sec, nanosec=nanosec)
        sigma = self._uncertainty(check, t, source)
        new = latest.received_ns != self._last_predicted_ns  # not again from the same state
        self._last_predicted_ns = latest.received_ns
        self._publish(Prediction(
            serialize_joint_trajectory(stamp, joints, t, positions, velocities, frame),
            latest.received_ns if new else None,
            serialize_joint_trajectory(stamp, joints, t, sigma, None, f'rmse:{source}'),
            _state_ahead(latest.stamp, joints, t, positions, velocities,
                         cfg['prediction.lookahead'], frame)))
        self.inputs = horizon.what
        # -- after the prediction is out: its scoring and what the next ones use
        candidate_due = candidate is not None and _on_schedule(latest.t, self._candidate_due,
                                                               CANDIDATE_EVERY_S)
        if not candidate_due and not _due(latest.t, self._scored_at, SCORE_EVERY_S):
            return True
        self._scored_at = latest.t
        theirs = None
        if candidate_due:
            theirs = self._rollout(candidate, joints, x0, horizon, latest.t, check)
            self._candidate_due = (_next_due(latest.t, self._candidate_due, CANDIDATE_EVERY_S)
                                   if theirs is not None else -math.inf)
            if theirs is not None and self._outside(check, latest, horizon, theirs[0], joints,
                                                    candidate=True):
                theirs = None
        check.add_prediction(latest.t, t, None if mine is None else mine[0], source,
                             None if theirs is None else theirs[0],
                             None if source == 'model' else positions, horizon.theta_d)
        self._replay.keep(latest.t, x0, horizon,
                          cfg['selfcheck.window'] + cfg['prediction.horizon'])
        again = self._replay.again(candidate, check, lambda x, h, t0: self._rollout(
            candidate, joints, x, h, t0, check, carry=False), latest.t)
        if again is not None:
            self._publish(LogLine('info', f'{describe(candidate)} {again}'))
        line = self._models.judge(check, latest.t, cfg['selfcheck.window'])
        if line is not None:
            self._decided_at = -math.inf
            self._publish(LogLine('info', line))
        if self._decide(check, latest.t, publishable) is not decision or \
                self._sigma is None or self._sigma[0] != source:
            self._sigma = None  # the uncertainty with the new scores, for the next ones
            self._uncertainty(check, t, self._decision.source)
        self._report(check, latest.t)
        return True

    def _uncertainty(self, check: SelfCheck, t: np.ndarray, source: str) -> np.ndarray:
        """Return the expected error at ``t`` (K, n) of ``source``, kept until rescored."""
        key = (source, t.size, float(t[-1]))
        if self._sigma is None or self._sigma[:3] != key:
            self._sigma = key + (check.uncertainty(t, source),)
        return self._sigma[3]

    def _self_check(self, cfg, joints) -> SelfCheck:
        """Return the self-check for these settings (a new one if they changed), fed."""
        horizon = cfg['prediction.horizon']
        step = cfg['model_step']
        horizons = tuple(sorted({max(step, round(horizon * f / step) * step)
                                 for f in (0.25, 0.5, 1.0)}))
        n = len(joints)
        key = (tuple(joints), horizons, cfg['selfcheck.window'], cfg['selfcheck.margin'],
               max(MIN_GAP_S, cfg['gap_threshold']))
        if self._check is None or key != self._check_key:
            self._check = self._new_check(key)
            self._check_key = key
            self._replay.clear()
            self._decided_at = -math.inf
            self._models.restart_trial(self._fed)
        # taken in bulk: at 1 kHz, one call per sample cost the prediction thread more
        # than its rollouts
        feed = self._ingestion.feed
        states, commands = ([], []), ([], [])
        while True:
            try:
                kind, stamp, values = feed.popleft()
            except IndexError:
                break
            if values.size != n:
                continue
            if kind != 'state':
                commands[0].append(stamp)
                commands[1].append(values)
                continue
            if stamp < self._fed - CLOCK_JUMP_S:  # the clock went back: a new timeline
                self._check = self._new_check(key)
                self._decided_at = -math.inf
                self._replay.clear()
                self._models.restart_trial(stamp)
                for store in states + commands:
                    store.clear()
            self._fed = stamp
            states[0].append(stamp)
            states[1].append(values)
        if commands[0]:
            self._check.add_references(np.array(commands[0]), np.array(commands[1]))
        if states[0]:
            self._check.add_states(np.array(states[0]), np.array(states[1]))
        return self._check

    @staticmethod
    def _new_check(key) -> SelfCheck:
        joints, horizons, window, margin, max_gap = key
        return SelfCheck(len(joints), horizons, window=window, margin=margin, max_gap=max_gap,
                         rescore_every=RESCORE_EVERY_S, joint_names=joints)

    def _horizon(self, cfg, t0: float) -> Optional[Horizon]:
        """Return what a prediction from ``t0`` covers (None: nothing, see the module)."""
        step = cfg['model_step']
        k = max(1, int(round(cfg['prediction.horizon'] / step)))
        hold = cfg['prediction.beyond_plan'] == 'hold'
        plan = self._ingestion.reference()
        left = None if plan is None else plan.end - t0
        if not hold:
            if left is None or left < step - 1e-9:
                self._ingestion.drops.warn_throttled(
                    ('prediction', 'no_plan'),
                    '~/prediction: no plan on reference_trajectory reaches past the newest '
                    'state; with prediction.beyond_plan stop no prediction is published')
                self.inputs = 'no plan ahead (prediction.beyond_plan: stop)'
                return None
            k = min(k, int(math.floor(left / step + 1e-9)))
        t = np.arange(k + 1) * step
        beyond = None
        if plan is not None and t0 + plan.times[0] <= plan.end:
            reference = FromReference(plan, t0)
            what = 'reference'
            if left < t[-1] - 1e-9:
                beyond = max(0.0, left)
                what = "reference, its last point held past the plan's end"
        else:
            command = self._ingestion.latest_command
            if command is None:
                return Horizon(t, None, None, None, 0.0 if hold else None, 'no plan')
            reference, what, beyond = HeldCommand(command), 'held command', 0.0
        theta_d, theta_d_dot = reference.evaluate(t)
        return Horizon(t, theta_d, theta_d_dot, reference, beyond, what)

    def _rollout(self, slot: Optional[Slot], joints, x0, horizon: Horizon, t0: float,
                 check: SelfCheck, carry: bool = True) -> Optional[Tuple[np.ndarray, np.ndarray]]:
        """
        Return ``(θ, θ̇)`` (K, n) of a model's prediction, None if it has none.

        ``carry`` False: from a past state (a PID's integral is not carried to ``t0``).
        """
        if not predicts(slot) or horizon.theta_d is None:
            return None
        model, loop = slot
        if model is None:  # a closed loop alone (its kernel is compiled at start-up)
            if loop is None or loop.loop.n_joints != len(joints):
                return None
        elif model.joint_names != joints or not self._ready.is_set():
            return None
        n = len(joints)
        if loop is not None and loop.model is model:  # closed with a fitted servo law
            states = loop.loop.simulate(x0, horizon.t, horizon.theta_d, horizon.theta_d_dot,
                                        self._models.integral(loop, t0, check, carry))
        else:   # a searched model alone (case 1's and a rigid body's need their loop)
            # at most MAX_SUBSTEPS RKG steps per model_step, whatever step the model was made
            # with (model_step may have grown since): the rollout's memory stays bounded
            step = float(horizon.t[1] - horizon.t[0]) if horizon.t.size > 1 else model.dt
            substeps = min(MAX_SUBSTEPS, math.ceil(step * model.substeps / model.dt - 1e-9))
            states = model.simulate(x0, horizon.t, reference=horizon.reference,
                                    substeps=max(1, substeps))
        if not np.all(np.isfinite(states)):
            self._ingestion.drops.reject('~/prediction', 'prediction', 'prediction_non_finite',
                                         'the model diverged over the horizon; a baseline is '
                                         'published instead')
            return None
        theta, theta_dot = np.array(states[:, :n]), np.array(states[:, n:2 * n])
        theta[0], theta_dot[0] = x0[:n], x0[n:]
        return theta, theta_dot

    @staticmethod
    def _published(source: str, mine, horizon: Horizon, latest):
        """Return the published positions and velocities (K, n): the model's or a baseline's."""
        if source == 'model':
            return mine
        k = horizon.t.size
        if source == 'follow_reference':
            positions, velocities = np.array(horizon.theta_d), np.array(horizon.theta_d_dot)
        else:
            positions = np.tile(latest.theta, (k, 1))
            velocities = np.zeros_like(positions)
        positions[0], velocities[0] = latest.theta, latest.theta_dot
        return positions, velocities

    def _decide(self, check: SelfCheck, now: float, publishable):
        """Return the publish decision (taken again at most every DECIDE_EVERY_S)."""
        decision = self._decision
        if decision is None or _due(now, self._decided_at, DECIDE_EVERY_S):
            decision = check.decide(publishable)
            self._decided_at = now
            previous, self._decision = self._decision, decision
            if previous is None or previous.source != decision.source:
                level = 'warning' if decision.scored and decision.is_baseline else 'info'
                self._publish(LogLine(level, f'~/prediction publishes {decision.source}: '
                                             f'{decision.reason}'))
        return decision

    def _outside(self, check: SelfCheck, latest, horizon: Horizon, theta: np.ndarray, joints,
                 candidate: bool = False) -> bool:
        """
        Return whether a rollout left the band the plan and the recent errors allow.

        The model in use is then withdrawn (:meth:`SelfCheck.withdraw`, logged once per
        withdrawal), the candidate dropped: on their own rollout's evidence, before any
        score of it can come (:mod:`rkgnn_ros.core.band`).
        """
        excursion = check.excursion(horizon.t, theta, latest.theta, horizon.theta_d,
                                    ('candidate', 'model') if candidate else ('model',))
        if excursion is None:
            return False
        why = (f'its {excursion.offset:.2f} s-ahead prediction of {joints[excursion.joint]} '
               f'left the band the plan and the recent errors allow, '
               f'{excursion.outside:.3g} rad beyond the plan where the band is '
               f'{excursion.width:.3g} rad')
        if candidate:
            dropped = self._models.drop_candidate(check)
            self._publish(LogLine('info', f'{describe(dropped)} is not used: {why}'))
        elif check.withdraw(latest.t, why):
            self._publish(LogLine('warning', f'the model in use is withdrawn: {why}'))
        return True

    def _report(self, check: SelfCheck, now: float) -> None:
        """Hand the scores to the executor every REPORT_EVERY_S."""
        if self._decision is None or not _due(now, self._reported_at, REPORT_EVERY_S):
            return
        self._reported_at = now
        scores, joints, floor = self._decision.scores, check.joint_scores(), check.noise_floor()
        nan = np.full(check.n, math.nan)
        table = np.array([[h] + [scores.get(h, {}).get(name, math.nan)
                                 for name in SCORE_LABELS[1:]]
                          + list(np.column_stack([joints.get(h, {}).get(name, nan)
                                                  for name in JOINT_SCORE_COLUMNS[:-1]]
                                                 + [floor]).ravel())
                          for h in check.horizons])
        self.report = ScoreReport(self._decision.source, self._decision.reason, table,
                                  score_labels(check.joint_names))
        self._publish(self.report)

    # ------------------------------------------------------------------ the thread

    def _wake(self) -> None:
        """Wake the thread from its wait for a request (:meth:`stop`)."""
        self._wanted.set()

    def _run(self) -> None:
        """One prediction from the newest state per request, until stopped."""
        while not self._stop.is_set():
            if not self._wanted.wait(0.1):
                continue
            self._wanted.clear()
            if self._stop.is_set():
                break
            try:
                self.predict()
            except Exception:  # noqa: B902 - the thread must survive
                if self._stop.is_set():
                    break
                self._ingestion.drops.internal_error('prediction')

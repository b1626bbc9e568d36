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
The learned feed-forward: ``~/feedforward``, sent only while its model passes the gate.

:class:`FeedforwardSender` turns the newest ``reference_trajectory`` into the torque the
plan needs, τ_ff = M(θd)θ̈d + V + G + F (:func:`~rkgnn_ros.core.control.feedforward.
plan_feedforward`), and publishes it as a JointTrajectory: the reference's points (θd, θ̇d,
θ̈d) with ``effort`` filled, the form in which joint_trajectory_controller with an effort
interface takes a feed-forward; also on ``feedforward.forward_topic`` when set. The model
is :func:`~rkgnn_ros.core.control.model.feedforward_model` fitted to the buffer (its
training part; the newest ``validation_fraction`` is held out), every
:data:`REFIT_PERIOD_S`, and :class:`~rkgnn_ros.core.control.gate.FeedforwardGate` decides:

- ``feedforward.enabled``, a clip (``feedforward.max_effort``) and case 1 or 2; case 3
  says no and why (its torque scale is not identifiable);
- the held-out torque error at most ``feedforward.max_error``; the model finite and its
  rollout over the newest validation samples finite;
- joint data that arrived within ``stale_timeout`` (its arrival, not its stamp: a stream
  that keeps coming with a steady delay is not stale), checked every :data:`PERIOD_S`;
- every effort clipped per joint; a plan with a NaN is never sent and switches it off.

After each switch-on the efforts rise linearly from zero over :data:`RAMP_S` (bumpless
engagement): a torque step of several N m would jolt the arm, and the jolt itself, a kink
in θ̇ that no 100 Hz derivative follows, made the next verdict fail (held-out error 0.08-0.13
against 0.002-0.02 otherwise, in a run through the nodes) and the feed-forward toggle.
A ramp keeps the torque continuous at any length; while it rises the PD still carries the
missing part, so a short one costs less tracking: 0.5 s rather than 2 s took the 20 s after
the switch-on from 4.0-4.5 to 7.2-7.4 times less error than before (``bench/control_online.py``,
runs whose switch fell at the same point of the plan; 2.5-2.9 to 3.1 where it fell 1.3-1.9 s
later; no switch-off in any), and with the true model in an offline simulation it was the
better of the two at each of 6 switch-on times.
On every switch-off (at once, no ramp) it publishes an empty trajectory (which stops the
feed-forward of a joint_trajectory_controller or of ``sim_arm``), logs the reason and says
it at once in ``/diagnostics`` (a status of its own: name ``<node name>: feedforward``,
hardware id ``<node's full name>/feedforward``, beside the node's own status); it comes
back only after a new passing assessment. In case 2 the known PD law gives the applied
torque only while no feed-forward is added, so while it is on the model and its verdict
are kept (staleness and non-finite plans still switch it off) and it is refitted once it
is off.

The model is fitted and judged every :data:`REFIT_PERIOD_S` (a failing verdict switches
the feed-forward off at once; it comes back at the next passing one), in a thread of its
own: a fit takes 0.1-2 s, too long for the executor, and while it runs the node's other
threads get less of the interpreter, so after a fit longer than :data:`QUICK_FIT_S` the
data's freshness and the model are judged in the next pass; a quicker fit cannot have made
data that arrive within ``stale_timeout`` look stale and is judged at once. Until the
first verdict passes after ``feedforward.enabled`` is set the arm tracks with the PD's
error alone, at its largest 0.1-0.2 rad on the paper's arm; with a pass every 0.1 s and the
verdict a pass after the fit, sim_arm applied the first feed-forward 0.27-0.58 s after the
set (14 runs of ``bench/control_online.py``), with a pass every 0.05 s and a quick fit
judged at once 0.23-0.45 s (3 runs). The thread keeps the node's priority: a
thread that holds the interpreter lock and is not scheduled (a lowered priority on a loaded
machine) stalls every other thread of the node. Publishing and logging happen in the
executor thread, woken by a guard condition, like the rest of the node's outputs.
"""

from collections import deque
import math
import threading
import traceback
from typing import Callable, Optional

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
import numpy as np
from rkgnn_ros.core.control.feedforward import plan_feedforward
from rkgnn_ros.core.control.gate import FeedforwardGate, GateSettings
from rkgnn_ros.core.control.model import FEEDFORWARD_CASES, feedforward_model
from rkgnn_ros.core.fitting.validation import MIN_SEGMENT_SAMPLES, split_validation
from rkgnn_ros.wire.conversions import make_joint_trajectory
from trajectory_msgs.msg import JointTrajectory

__all__ = ['FeedforwardSender', 'PERIOD_S', 'REFIT_PERIOD_S']

PERIOD_S = 0.05        # the thread's pass: a switch-off (stale data) takes at most this long
REFIT_PERIOD_S = 5.0   # s between two fits of the feed-forward's model
ROLLOUT_S = 1.0        # s of the newest validation samples the model is rolled out over
RAMP_S = 0.5           # s over which the efforts rise from 0 after each switch-on
QUICK_FIT_S = 0.25     # a fit at most this long is judged in its own pass (see the module)
JOIN_TIMEOUT_S = 10.0


def rollout_error(model, validation, case: str) -> float:
    """Return the θ RMSE (rad) of ``model`` rolled out over the newest validation segment."""
    if not validation:
        return math.nan
    data = validation[-1]
    k = min(data.n_samples, max(2, int(round(ROLLOUT_S / data.dt)) + 1))
    with np.errstate(all='ignore'):
        if case == 'torque':
            states = model.simulate(data.state[0], data.t[:k], tau=data.tau[:k])
        else:
            states = model.simulate(data.state[0], data.t[:k], theta_d=data.theta_d[:k],
                                    theta_d_dot=data.theta_d_dot[:k])
        error = float(np.sqrt(np.mean(np.square(states[:, :data.n_joints] - data.theta[:k]))))
    return error if math.isfinite(error) else math.inf


class FeedforwardSender:
    """
    The identifier's feed-forward part: fit, gate, publish.

    Parameters
    ----------
    node : rclpy.node.Node
        The node (publishers, clock, logger, guard condition, timer).
    ingestion : Ingestion
        The joints, the newest state, buffer captures and the newest reference.
    config : callable
        Returns the current parameter snapshot (:class:`~.parameters.Config`).
    model : callable
        ``model(train, case, kp, kd)``: the feed-forward's model (default
        :func:`feedforward_model`; tests pass their own).
    publishers : dict, optional
        The node's publishers (:func:`~.publishing.create_publishers`): ``feedforward`` and
        ``feedforward_forward`` (when ``feedforward.forward_topic`` is set), ``diagnostics``.
        None: made here.

    """

    def __init__(self, node, ingestion, config: Callable, model: Callable = feedforward_model,
                 publishers: Optional[dict] = None):
        self._node = node
        self._ingestion = ingestion
        self._config = config
        self._fit = model
        if publishers is None:
            topic = config()['feedforward.forward_topic']
            publishers = {'feedforward': node.create_publisher(JointTrajectory,
                                                               '~/feedforward', 10),
                          'diagnostics': node.create_publisher(DiagnosticArray,
                                                               '/diagnostics', 10)}
            if topic:
                publishers['feedforward_forward'] = node.create_publisher(JointTrajectory,
                                                                          topic, 10)
        self._publishers = [publishers[key] for key in ('feedforward', 'feedforward_forward')
                            if key in publishers]
        self._diagnostics = publishers['diagnostics']
        self._items: deque = deque(maxlen=100)
        self._wake = node.create_guard_condition(lambda: self.drain(False)).trigger
        node.create_timer(1.0, self.drain)  # 1 Hz diagnostics, and whatever is queued
        self._gate: Optional[FeedforwardGate] = None
        self._gate_key = None
        self._model = None
        self._candidate = None  # (model, validation, rollout error): fitted, not yet judged
        self._fitted_at = -math.inf
        self._sent = (None, None)  # (reference, model) of the last message
        self._on = False
        self._on_since = math.inf  # node-clock time the feed-forward last switched on
        self._reason = 'not started'
        self._logged = ''
        self.published = 0
        self.clipped = 0
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None

    def forward_to(self, publisher) -> None:
        """Also publish on ``publisher`` (``feedforward.forward_topic``); before :meth:`start`."""
        self._publishers.append(publisher)

    def _now(self) -> float:
        return self._node.get_clock().now().nanoseconds * 1e-9

    # ----- the thread
    def start(self) -> None:
        """Start the feed-forward thread."""
        self._thread = threading.Thread(target=self._run, name='rkgnn_feedforward', daemon=True)
        self._thread.start()

    def stop(self) -> bool:
        """Stop and join the thread; return False if it did not stop in time."""
        self._stop.set()
        if self._thread is not None and self._thread.is_alive():
            self._thread.join(JOIN_TIMEOUT_S)
            return not self._thread.is_alive()
        return True

    def _run(self) -> None:
        while not self._stop.wait(PERIOD_S):
            try:
                self.step()
            except Exception:  # noqa: B902 - the thread must survive; the gate stays shut
                if self._gate is not None:
                    self._gate.switch_off('internal error (see the log)')
                self._put(('log', 'error', f'feed-forward: unexpected error\n'
                                           f'{traceback.format_exc()}'))
                self._transition(False, 'internal error (see the log)')

    # ----- one pass
    def step(self) -> None:
        """Check, refit when due, send the plan's feed-forward when on (one pass)."""
        cfg = self._config()
        gate, problem = self._gate_for(cfg)
        self._note_data(gate)
        if problem is not None:
            if gate is not None:
                gate.switch_off(problem)
            self._model, self._fitted_at = None, -math.inf  # fit as soon as it is solved
            self._transition(False, problem)
            return
        self._judge(gate)  # a model fitted in the previous pass
        now = self._now()
        frozen = self._on and cfg.case == 'pd_gains'
        if not frozen and now - self._fitted_at >= REFIT_PERIOD_S:
            self._fitted_at = now
            self._refit(cfg, gate)
            if self._now() - now > QUICK_FIT_S:
                return  # the status next pass, once the ingest thread has caught up
            self._note_data(gate)
            self._judge(gate)
        on, reason = gate.status()
        if on and not self._on:
            self._on_since = self._now()
        if on:
            self._send(gate)
            on, reason = gate.status()  # a non-finite plan switches it off
        self._transition(on, reason)

    def _judge(self, gate) -> None:
        """Assess the fitted candidate, if any: it becomes the model when it passes."""
        if self._candidate is not None:
            model, validation, rollout = self._candidate
            self._candidate = None
            self._model = model if gate.assess(model, validation, rollout_nrmse=rollout).passed \
                else None

    def _gate_for(self, cfg):
        """Return (gate, None) for the current settings, or (gate or None, why it is off)."""
        joints = self._ingestion.joints
        clip = cfg['feedforward.max_effort']
        if not cfg['feedforward.enabled']:
            return self._gate, 'feedforward.enabled is false'
        if cfg.case == 'auto':
            return self._gate, 'case auto: not decided yet (no joint_states so far)'
        if cfg.case not in FEEDFORWARD_CASES:
            return self._gate, ("case 'unknown': the torque scale is not identifiable (M, V, "
                                'G, F and the controller scale together), so no torque can '
                                'be sent; use case torque or pd_gains')
        if not clip:
            return self._gate, 'feedforward.max_effort is not set'
        if joints is None:
            return self._gate, 'joints not known yet'
        if len(clip) not in (1, len(joints)):
            return self._gate, (f'feedforward.max_effort has {len(clip)} values for '
                                f'{len(joints)} joints')
        key = (len(joints), cfg['feedforward.max_error'], clip, cfg['stale_timeout'])
        if key != self._gate_key:
            self._gate = FeedforwardGate(GateSettings.for_joints(
                len(joints), cfg['feedforward.max_error'], np.broadcast_to(clip, len(joints)),
                cfg['stale_timeout']), self._now)
            self._gate_key, self._model, self._fitted_at = key, None, -math.inf
        return self._gate, None

    def _note_data(self, gate) -> None:
        """Tell the gate when joint data last arrived, on the node's clock."""
        received = self._ingestion.view()[3].get('state')  # the ingestion clock's time
        if gate is not None and received is not None:
            gate.data_received(self._now() - (self._ingestion.seconds() - received))

    def _refit(self, cfg, gate) -> None:
        capture = self._ingestion.capture()
        if capture is None:
            gate.switch_off('no joint data yet')
            return
        segments = capture.segments(MIN_SEGMENT_SAMPLES, cfg.case == 'pd_gains')
        train, validation, _ = split_validation(segments, cfg['validation_fraction'],
                                                MIN_SEGMENT_SAMPLES)
        if not train:
            gate.switch_off('not enough buffered data to fit the model')
            self._model = None
            return
        try:
            model = self._fit(train, cfg.case, cfg['kp'] or None, cfg['kd'] or None)
            rollout = rollout_error(model, validation, cfg.case)
        except (ValueError, ArithmeticError, MemoryError, np.linalg.LinAlgError) as exc:
            gate.switch_off(f'the model could not be fitted: {exc}')
            self._model = None
            return
        # after a long fit judged in the next pass: the ingest thread, slowed down by the fit,
        # catches up in between, so the gate sees how fresh the data is, not how long the
        # fit took
        self._candidate = (model, validation, rollout)

    def _send(self, gate) -> None:
        reference, model = self._ingestion.reference(), self._model
        if reference is None or model is None or self._sent == (reference, model):
            return
        self._sent = (reference, model)
        if reference.times.size < 2:
            return
        with np.errstate(all='ignore'):
            plan = plan_feedforward(model, reference.times, reference.positions,
                                    reference.velocities)
        times = reference.t0 + plan.t
        ramp = np.clip((times - self._on_since) / RAMP_S, 0.0, 1.0)[:, None]
        release = gate.release(times, ramp * plan.effort)
        if release.effort is None:
            return
        msg = make_joint_trajectory(reference.t0, self._ingestion.joints, plan.t,
                                    plan.theta_d, plan.theta_d_dot)
        for point, acc, effort in zip(msg.points, plan.theta_d_ddot, release.effort):
            point.accelerations = acc.tolist()
            point.effort = effort.tolist()
        self.clipped += release.clipped
        self._put(('publish', msg))

    def _transition(self, on: bool, reason: str) -> None:
        was_on, self._on, self._reason = self._on, on, reason
        if on and not was_on:
            verdict = self._gate.assessment.reason if self._gate.assessment else ''
            self._put(('log', 'info', f'feed-forward on: {verdict}'))
        elif was_on and not on:
            stop = JointTrajectory(joint_names=list(self._ingestion.joints or ()))
            stop.header.stamp = self._node.get_clock().now().to_msg()
            self._sent = (None, None)
            self._put(('publish', stop))
            self._put(('log', 'warning', f'feed-forward off: {reason}'))
            self._put(('diagnostics',))
        elif not on and ' '.join(reason.split()[:2]) != self._logged:
            self._put(('log', 'info', f'feed-forward off: {reason}'))
        if not on:  # a new kind of reason is logged once (figures change at every fit)
            self._logged = ' '.join(reason.split()[:2])

    # ----- the executor side
    def _put(self, item) -> None:
        self._items.append(item)
        try:
            self._wake()
        except Exception:  # noqa: B902 - shutting down: nothing drains any more
            pass

    def drain(self, diagnostics: bool = True) -> None:
        """Publish and log what the thread queued (the guard condition's callback)."""
        if diagnostics:
            self._items.append(('diagnostics',))
        while self._items:
            item = self._items.popleft()
            try:
                if item[0] == 'publish':
                    for publisher in self._publishers:
                        publisher.publish(item[1])
                    self.published += bool(item[1].points)
                elif item[0] == 'diagnostics':
                    self._diagnostics.publish(self.diagnostics())
                elif item[1] == 'info':
                    self._node.get_logger().info(item[2])
                elif item[1] == 'warning':
                    self._node.get_logger().warning(item[2])
                else:
                    self._node.get_logger().error(item[2])
            except Exception:  # noqa: B902 - a callback must never raise
                self._ingestion.drops.internal_error('feedforward')

    def diagnostics(self) -> DiagnosticArray:
        """Return the feed-forward's status: on or off and why, its model's verdict."""
        cfg = self._config()
        assessment = self._gate.assessment if self._gate is not None else None
        error = assessment.error if assessment is not None else None
        pairs = [('state', 'on' if self._on else 'off'), ('reason', self._reason),
                 ('model', 'LinearDynamics, tied planar trigonometric basis'),
                 ('heldout_torque_error', '' if error is None else
                  ','.join(f'{e:.4g}' for e in error)),
                 ('validation_samples', assessment.samples if assessment else 0),
                 ('max_error', cfg['feedforward.max_error']),
                 ('max_effort', ','.join(f'{v:g}' for v in cfg['feedforward.max_effort'])),
                 ('messages_published', self.published), ('efforts_clipped', self.clipped)]
        level = DiagnosticStatus.OK if self._on or not cfg['feedforward.enabled'] else \
            DiagnosticStatus.WARN
        node = self._node
        status = DiagnosticStatus(
            level=level, name=f'{node.get_name()}: feedforward',
            message='on' if self._on else f'off: {self._reason}',
            hardware_id=f'{node.get_fully_qualified_name()}/feedforward',
            values=[KeyValue(key=k, value=str(v)) for k, v in pairs])
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = node.get_clock().now().to_msg()
        return msg

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
Publishing: everything the identifier tells the world, from the executor thread only.

The worker, ingest and prediction threads never touch a publisher, a parameter or the
logger: they put what they have to say into the :class:`Outbox` (a bounded queue whose
``put`` triggers a guard condition), and :meth:`Publishing.drain`, the guard condition's
callback, handles it in the executor thread: a prediction goes to ``~/prediction``, its
uncertainty to ``~/prediction_uncertainty`` and its state ``prediction.lookahead`` ahead
to ``~/predicted_state``; the self-check's scores to ``~/prediction_scores``; a new model
to ``~/model`` (its YAML was made in the worker), to the ``identified.*`` output
parameters and to the predictor; generation statistics to ``~/evolution``; log lines to
the node's logger. :meth:`Publishing.publish_diagnostics` (a 1 Hz timer) gathers
``/diagnostics`` from the parts' read-only views. :func:`create_publishers` makes the
publishers, so the node and its tests agree on them.
"""

from collections import deque
import math
from typing import Callable, NamedTuple, Optional

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import InertiaStamped
import numpy as np
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rkgnn_ros.core.fitting.online import GenerationStats, LogLine, LoopUpdate, ModelUpdate, Status
from rkgnn_ros.core.fitting.online_records import DynamicsChange, PayloadEstimate
from rkgnn_ros.core.model.model import RKGNNModel
from rkgnn_ros.identification.prediction import (JOINT_SCORE_COLUMNS, Prediction, SCORE_LABELS,
                                                 ScoreReport)
from rkgnn_ros.wire.conversions import make_float64_multiarray
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, String
from trajectory_msgs.msg import JointTrajectory

__all__ = ['EVOLUTION_LABELS', 'SCORE_LABELS', 'ModelMessage', 'Outbox', 'Publishing',
           'create_forward_publisher', 'create_publishers']

#: Field names of ``~/evolution`` (the layout label of its one dimension).
EVOLUTION_LABELS = GenerationStats._fields

OUTBOX_LIMIT = 10000  # items kept when nothing drains the outbox (no executor spins)


def create_publishers(node, events, forward_topic: str = '') -> dict:
    """
    Create the identifier's publishers on ``node`` (``events``: their event callbacks).

    ``~/model`` is reliable, transient local, depth 1 (a late subscriber gets the last
    model at once); the others are volatile, depth 10. ``feedforward`` is ``~/feedforward``
    (:mod:`~rkgnn_ros.identification.feedforward`), ``feedforward_forward`` the same on
    ``forward_topic`` when it is not empty (:func:`create_forward_publisher`; the node makes
    that one itself, after its subscriptions).
    """
    model_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                           reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.TRANSIENT_LOCAL)
    topics = {'model': (String, '~/model', model_qos),
              'prediction': (JointTrajectory, '~/prediction', 10),
              'prediction_uncertainty': (JointTrajectory, '~/prediction_uncertainty', 10),
              'predicted_state': (JointState, '~/predicted_state', 10),
              'prediction_scores': (Float64MultiArray, '~/prediction_scores', 10),
              'evolution': (Float64MultiArray, '~/evolution', 10),
              'diagnostics': (DiagnosticArray, '/diagnostics', 10),
              'feedforward': (JointTrajectory, '~/feedforward', 10),
              'change': (DiagnosticStatus, '~/change', model_qos),
              'payload': (InertiaStamped, '~/payload', model_qos)}
    publishers = {key: node.create_publisher(kind, topic, qos, event_callbacks=events)
                  for key, (kind, topic, qos) in topics.items()}
    if forward_topic:
        publishers['feedforward_forward'] = create_forward_publisher(node, forward_topic,
                                                                     events)
    return publishers


def _type_name(msg_type) -> str:
    """Return 'package/msg/Name' of a message class."""
    return f"{msg_type.__module__.split('.')[0]}/msg/{msg_type.__name__}"


def create_forward_publisher(node, topic: str, events=None):
    """
    Return the JointTrajectory publisher on ``feedforward.forward_topic``.

    Create it after the node's other publishers and subscriptions: a topic the node uses
    with another type (``/diagnostics``, ``joint_states``, ``/rosout``, ...) cannot carry
    JointTrajectory in the same process (rmw refuses it with an exception), and raises
    :class:`~.parameters.ConfigurationError` naming the parameter, the topic and its type,
    so the node refuses to start with that one line.
    """
    from rclpy.exceptions import InvalidTopicNameException
    from rkgnn_ros.identification.parameters import ConfigurationError
    try:
        name = node.resolve_topic_name(topic)
    except (InvalidTopicNameException, RuntimeError, ValueError) as exc:
        raise ConfigurationError(f'feedforward.forward_topic {topic!r} is not a topic name: '
                                 f'{exc}') from None
    used = {'/rosout': 'rcl_interfaces/msg/Log'}
    for entity in list(node.publishers) + list(node.subscriptions):
        used.setdefault(entity.topic_name, _type_name(entity.msg_type))
    other = used.get(name)
    if other is not None and other != _type_name(JointTrajectory):
        raise ConfigurationError(
            f'feedforward.forward_topic {topic!r} is {name}, which this node uses as '
            f'{other}: it cannot carry trajectory_msgs/msg/JointTrajectory; choose another '
            'topic')
    try:
        return node.create_publisher(JointTrajectory, topic, 10, event_callbacks=events)
    except Exception as exc:  # noqa: B902 - rclpy's RCLError: say which and why, no traceback
        raise ConfigurationError(f'feedforward.forward_topic {topic!r}: cannot publish '
                                 f"JointTrajectory there: {' '.join(str(exc).split())}") \
            from None


class ModelMessage(NamedTuple):
    """A model to publish, with its YAML (made in the worker thread)."""

    update: ModelUpdate
    text: str


class Outbox:
    """
    What the threads hand to the executor: a bounded queue that wakes the executor.

    ``connect`` gives it the function that wakes the executor (a guard condition's
    ``trigger``); ``put`` and ``log`` may be called from any thread.
    """

    def __init__(self, limit: int = OUTBOX_LIMIT):
        self._items: deque = deque(maxlen=limit)
        self._wake: Callable[[], None] = lambda: None

    def connect(self, wake: Callable[[], None]) -> None:
        """Call ``wake`` after every ``put`` (and now, if anything is queued already)."""
        self._wake = wake
        if self._items:
            wake()

    def put(self, item) -> None:
        """Queue ``item`` for the executor thread."""
        self._items.append(item)
        try:
            self._wake()
        except Exception:  # noqa: B902 - shutting down: nothing drains any more
            pass

    def log(self, level: str, text: str) -> None:
        """Queue a log line ('info', 'warning' or 'error')."""
        self.put(LogLine(level, text))

    def take(self) -> list:
        """Return and remove everything queued, oldest first."""
        items = []
        while True:
            try:
                items.append(self._items.popleft())
            except IndexError:
                return items


class Publishing:
    """
    The identifier's outputs, handled in the executor thread.

    Parameters
    ----------
    node : rclpy.node.Node
        The node (logger, clock, names).
    outbox : Outbox
        What the other threads queued.
    publishers : dict
        Those of :func:`create_publishers` (the trajectories take CDR bytes).
    parameters : IdentifierParameters
        Where the ``identified.*`` outputs are set.
    predictor : Predictor
        Gets every published model.
    ingestion : Ingestion
        Joints, buffered samples and drop counts for the diagnostics.
    status : callable
        Returns the search's current :class:`Status`.

    """

    def __init__(self, node, outbox: Outbox, publishers: dict, parameters, predictor,
                 ingestion, status: Callable[[], Status], description=None):
        self._node = node
        self._description = description   # its status joins /diagnostics
        self.last_change: Optional[DynamicsChange] = None
        self.last_payload: Optional[PayloadEstimate] = None
        self._outbox = outbox
        self._publishers = publishers
        self._parameters = parameters
        self._predictor = predictor
        self._ingestion = ingestion
        self._status = status
        self._model: Optional[RKGNNModel] = None

    @property
    def model(self) -> Optional[RKGNNModel]:
        """Return the last model published, None before the first."""
        return self._model

    def drain(self) -> None:
        """Handle everything queued (the guard condition's callback); never raises."""
        for item in self._outbox.take():
            try:
                self._handle(item)
            except Exception:  # noqa: B902 - a callback must never raise
                self._ingestion.drops.internal_error('publishing')

    def publish_prediction(self, item: Prediction) -> None:
        """
        Publish a prediction, its uncertainty and the state ahead; record its latency.

        Called from the prediction thread itself (rclpy publishers are thread-safe): handed
        to the executor instead, a prediction waited for the executor's next wake-up.
        """
        self._publishers['prediction'].publish(item.data)
        self._predictor.published(item)
        if item.uncertainty is not None:
            self._publishers['prediction_uncertainty'].publish(item.uncertainty)
        if item.state is not None and 'predicted_state' in self._publishers:
            self._publishers['predicted_state'].publish(item.state)

    def _handle(self, item) -> None:
        if isinstance(item, Prediction):
            self.publish_prediction(item)
        elif isinstance(item, ScoreReport):
            self._publishers['prediction_scores'].publish(
                make_float64_multiarray(item.table, item.labels))
        elif isinstance(item, LogLine):
            self.log(item.level, item.text)
        elif isinstance(item, GenerationStats):
            self._publishers['evolution'].publish(
                make_float64_multiarray(list(item), EVOLUTION_LABELS))
        elif isinstance(item, ModelMessage):
            self.publish_model(item.update, item.text)
        elif isinstance(item, LoopUpdate):
            self._predictor.update_loop(item.model, item.loop)
        elif isinstance(item, (DynamicsChange, PayloadEstimate)):
            self._publish_change(item)

    def _publish_change(self, item) -> None:
        """Publish a change on ``~/change`` or a payload on ``~/payload`` (and keep it)."""
        if isinstance(item, DynamicsChange):
            self.last_change = item
            self._predictor.dynamics_changed(item.time)
            values = [('time', f'{item.time:.6f}'), ('joints', ','.join(item.joints))]
            values += [(f'statistic.{i}', f'{v:.4g}') for i, v in enumerate(item.statistic)]
            self._publishers['change'].publish(DiagnosticStatus(
                level=DiagnosticStatus.WARN, name=f'{self._node.get_name()}: dynamics change',
                message=f'the dynamics changed at {item.time:.3f} s on {list(item.joints)}',
                hardware_id=self._node.get_fully_qualified_name(),
                values=[KeyValue(key=k, value=v) for k, v in values]))
            return
        self.last_payload = item
        msg = InertiaStamped()
        sec, nanosec = divmod(int(round(item.time * 1e9)), 1_000_000_000)
        msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
        msg.header.frame_id = item.frame
        msg.inertia.m = float(item.mass)
        msg.inertia.com.x, msg.inertia.com.y, msg.inertia.com.z = map(float, item.com)
        (msg.inertia.ixx, msg.inertia.iyy, msg.inertia.izz, msg.inertia.ixy,
         msg.inertia.ixz, msg.inertia.iyz) = map(float, item.inertia)
        self._publishers['payload'].publish(msg)

    def publish_model(self, update: ModelUpdate, text: Optional[str] = None) -> None:
        """Publish a model on ``~/model``, predict with it, set the ``identified.*`` outputs."""
        model = update.model
        # kept before publishing: a SIGINT that lands between the publish call and the next
        # statement must not lose a model that subscribers have already received (the one
        # saved at shutdown is the one they saw last)
        self._model = model
        self._publishers['model'].publish(String(data=text or model.to_yaml()))
        self._predictor.set_model(model, update.loop)
        refused = self._parameters.set_outputs(
            self._node, update.generation, update.cost, update.validation_nrmse, update.kp,
            update.kd)
        for name, reason in refused.items():
            self.log('warning', f'cannot update {name}: {reason}')

    def log(self, level: str, text: str) -> None:
        """Log with the node's logger (one call site per severity, as rclpy requires)."""
        logger = self._node.get_logger()
        if level == 'info':
            logger.info(text)
        elif level == 'warning':
            logger.warning(text)
        else:
            logger.error(text)

    def publish_diagnostics(self) -> None:
        """Publish the node's status on ``/diagnostics`` (the 1 Hz timer); never raises."""
        try:
            self._publishers['diagnostics'].publish(self._diagnostics())
        except Exception:  # noqa: B902 - a callback must never raise
            self._ingestion.drops.internal_error('diagnostics')

    def _diagnostics(self) -> DiagnosticArray:
        status = self._status()
        ingestion = self._ingestion
        latencies = self._predictor.latencies()
        state = status.state
        level = {'error': DiagnosticStatus.ERROR,
                 'stale': DiagnosticStatus.WARN}.get(state, DiagnosticStatus.OK)
        pairs = [
            ('state', state), ('detail', status.detail),
            ('generation', status.generation), ('best_cost', status.best_cost),
            ('validation_nrmse', status.validation_nrmse),
            ('generations_per_s', f'{status.generations_per_s:.2f}'),
            ('samples_buffered', ingestion.samples_buffered()),
            ('population_size', status.population_size),
            ('excitation.condition_number', f'{status.condition_number:.4g}'),
            ('excitation.memory_samples', status.memory_samples),
            ('case', self._parameters.config.case),
            ('joints', ','.join(ingestion.joints or ())),
            ('prediction_inputs', self._predictor.inputs),
        ]
        pairs += list(ingestion.sources.describe().items())
        if self._description is not None:
            pairs.append(('robot_description', self._description.status))
        if self.last_change is not None:
            pairs += [('change.time', f'{self.last_change.time:.6f}'),
                      ('change.joints', ','.join(self.last_change.joints))]
        if self.last_payload is not None:
            pairs += [('payload.mass_kg', f'{self.last_payload.mass:.4g}'),
                      ('payload.com_m', ' '.join(f'{v:.4g}' for v in self.last_payload.com))]
        pairs += _selfcheck_pairs(self._predictor.report)
        pairs += [
            ('prediction_latency_p50_ms', _percentile_text(latencies, 50)),
            ('prediction_latency_p99_ms', _percentile_text(latencies, 99)),
        ]
        pairs += [(f'drops.{reason}', count)
                  for reason, count in ingestion.drops.counts().items()]
        node = self._node
        diag = DiagnosticStatus(level=level, name=node.get_name(),
                                message=f'{state}: {status.detail}',
                                hardware_id=node.get_fully_qualified_name(),
                                values=[KeyValue(key=k, value=str(v)) for k, v in pairs])
        msg = DiagnosticArray(status=[diag])
        msg.header.stamp = node.get_clock().now().to_msg()
        return msg


def _selfcheck_pairs(report: Optional[ScoreReport]) -> list:
    """Return the self-check's diagnostics entries (what is published, why, the scores)."""
    if report is None:
        return [('prediction_source', 'none yet')]
    pairs = [('prediction_source', report.source), ('prediction_source_reason', report.reason)]
    worst = None  # (ratio, text) of the joint where the model is furthest behind
    for row in report.table:
        fields = dict(zip(report.labels, row))
        text = ', '.join(f'{name} {fields[name]:.2%}' for name in SCORE_LABELS[1:5]
                         if np.isfinite(fields[name]))
        count = int(fields['count']) if np.isfinite(fields['count']) else 0
        horizon = f"{fields['horizon_s']:g}s"
        pairs.append((f'selfcheck.{horizon}',
                      f'{text} (model: {count} scored)' if text else 'not scored yet'))
        for joint in report.labels[len(SCORE_LABELS)::len(JOINT_SCORE_COLUMNS)]:
            joint = joint.split(':', 1)[1]
            of = {name: fields[f'{name}:{joint}'] for name in JOINT_SCORE_COLUMNS}
            shown = [f"{name.replace('_', ' ')} {value:.2%}" for name, value in of.items()
                     if np.isfinite(value)]
            pairs.append((f'selfcheck.{horizon}.{joint}',
                          ', '.join(shown) if len(shown) > 1 else 'not scored yet'))
            better = min((of[b] for b in ('follow_reference', 'hold_last')
                          if np.isfinite(of[b])), default=math.nan)
            ratio = of['model'] / max(better, 1e-300)
            if np.isfinite(ratio) and (worst is None or ratio > worst[0]):
                worst = (ratio, f'{joint} at {horizon}: {ratio:.2f} x the better baseline')
    if worst is not None:
        pairs.append(('selfcheck.worst_joint', worst[1]))
    return pairs


def _percentile_text(values: np.ndarray, q: float) -> str:
    return f'{np.percentile(values, q):.2f}' if values.size else 'nan'

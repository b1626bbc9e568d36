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
The ``identifier`` node: evolve an RKGNN model of the arm online while it moves.

This module declares the interface and wires the parts (:mod:`rkgnn_ros.identification`);
each part's module says what it does and why, :mod:`rkgnn_ros.core.fitting.online` the
search's rules.

Interface
---------
Subscribed (:mod:`~rkgnn_ros.identification.subscriptions`: QoS, who reads each)
    ``joint_states`` (sensor_msgs/JointState): θ, and θ̇ and τ (effort) where the driver has
    them (``case: auto`` takes case 1 with effort, θ̇ is estimated from θ without velocity).
    ``joint_commands`` (sensor_msgs/JointState, optional): θd (position), θ̇d (velocity).
    ``reference_trajectory`` (trajectory_msgs/JointTrajectory): the plan; it stands in for
    ``joint_commands`` where that topic is silent, and predictions end where it ends.
    ``controller_state`` parameter's topic (control_msgs, optional): θd, θ̇d of a
    joint_trajectory_controller (:mod:`~rkgnn_ros.identification.ros2_control`).
    Size budgets (:mod:`rkgnn_ros.wire.conversions`): a JointState of at most 64 KiB, a
    JointTrajectory of at most 8 MiB and 10,000 points, at most 256 joint names of at most
    256 bytes each; a message over any is dropped, counted as ``over_budget``. A stamp far
    from its stream (more than 1 s) is dropped as ``stamp_outlier`` unless three in a row
    show that the stream itself moved (a clock jump, :mod:`rkgnn_ros.streams.buffer`); the
    node clock jumping back by more than 1 s (``/clock`` under ``use_sim_time``) clears the
    buffer too.
Published
    ``~/model`` (std_msgs/String, reliable, transient local, depth 1): the model YAML when
    the best improves, at most every ``model_publish_period`` s; at start when
    ``model_file`` held a usable model.
    ``~/prediction`` (trajectory_msgs/JointTrajectory): from the newest accepted
    joint_states sample (header stamp copied, ``points[0]`` that state exactly) over
    ``prediction.horizon`` s at ``model_step``, ending where the plan ends unless
    ``prediction.beyond_plan`` says otherwise; at ``prediction.rate`` Hz and with
    ``prediction.on_state`` on each accepted state (at most once per ``model_step``).
    ``header.frame_id`` says what it is: ``model``, ``baseline:follow_reference`` or
    ``baseline:hold_last`` (the self-check publishes a baseline while the model has not
    earned trust or did worse lately), with ``;beyond_plan_from=<s>`` when points lie past
    the plan's end. Never non-finite (counted ``prediction_non_finite``).
    ``~/prediction_uncertainty`` (trajectory_msgs/JointTrajectory): the same stamp, joints
    and times, positions = the expected θ error (rad, the published predictor's recent
    RMSE per horizon), ``frame_id`` ``rmse:<source>``.
    ``~/predicted_state`` (sensor_msgs/JointState): with each prediction, its state
    ``prediction.lookahead`` s ahead, stamped at that time (plot it against joint_states).
    ``~/prediction_scores`` (std_msgs/Float64MultiArray, 1 Hz): a row per scored horizon,
    columns :data:`SCORE_LABELS` (windowed RMSE / θ range, averaged over the joints), then
    per joint ``model:<joint>``, ``follow_reference:<joint>``, ``hold_last:<joint>``,
    ``published:<joint>`` and ``noise_floor:<joint>`` (:func:`score_labels`; layout
    ``rows``, then the labels).
    ``~/evolution`` (std_msgs/Float64MultiArray, labels :data:`EVOLUTION_LABELS`): per
    generation, at most 20 Hz.
    ``/diagnostics`` (diagnostic_msgs/DiagnosticArray, 1 Hz): the state, the search's
    figures, the case in effect, where θ̇ and the commands come from, what is published
    and why, the scores, the prediction latency, a ``drops.<reason>`` per reason.
    ``~/feedforward`` (trajectory_msgs/JointTrajectory): the plan's torque from the gated
    model (:mod:`~rkgnn_ros.identification.feedforward`), also on ``feedforward.forward_topic``.
Services
    ``~/reset`` (std_srvs/Trigger): clear the buffer and restart the search.
    ``~/save_model`` (std_srvs/Trigger): write the published model to ``model_file``.
    ``~/save_urdf`` (std_srvs/Trigger): with a robot description, write the identified URDF
    (its inertials and friction replaced) to ``identified_urdf_file``.
    ``~/pause`` (std_srvs/SetBool): True pauses the search, False resumes it.
Node parameters
    :data:`~rkgnn_ros.identification.parameters.PARAMETERS` (``ros2 param describe``
    shows each and what a change does); defaults in ``config/identifier.yaml``.
    ``identified.*`` are outputs, refused from outside. An invalid value at start (or of
    another type) makes the node refuse to start (exit code 1), naming the parameter.
    Every time rule runs on the node's clock (``use_sim_time``: identification/clock.py).

Threads
-------
The executor thread runs the callbacks, publishes and sets parameters, and nothing else
does. The ingest, worker, prediction and feed-forward threads (the parts of those names in
:mod:`rkgnn_ros.identification`) hand what is to be published or logged to the executor
(outboxes and guard conditions). Objects alive at start are frozen out of the cyclic
garbage collector and no QoS-event handlers are created: the executor stays cheap.
"""

from functools import partial
import gc
import sys

import rclpy
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rkgnn_ros.core.control.model import feedforward_model
from rkgnn_ros.core.fitting.identify import precompile
from rkgnn_ros.core.fitting.online import model_update, OnlineIdentification
from rkgnn_ros.identification.clock import NodeSeconds, watch_clock_jumps
from rkgnn_ros.identification.description import description_text, RobotDescription
from rkgnn_ros.identification.feedforward import FeedforwardSender
from rkgnn_ros.identification.ingest import Ingestion
from rkgnn_ros.identification.model_file import (load_at_start, save_identified_urdf,
                                                 save_model_file)
from rkgnn_ros.identification.parameters import ConfigurationError, IdentifierParameters
from rkgnn_ros.identification.prediction import Prediction, Predictor, score_labels
from rkgnn_ros.identification.publishing import (create_forward_publisher, create_publishers,
                                                 EVOLUTION_LABELS, Outbox, Publishing,
                                                 SCORE_LABELS)
from rkgnn_ros.identification.subscriptions import (quiet_events, subscribe_description,
                                                    subscribe_streams)
from rkgnn_ros.identification.worker import SearchWorker
from rkgnn_ros.node.parameters import Change
from rkgnn_ros.node.stacks import start_up, tear_down
from std_srvs.srv import SetBool, Trigger

__all__ = ['EVOLUTION_LABELS', 'SCORE_LABELS', 'ConfigurationError', 'IdentifierNode', 'main',
           'score_labels']


class IdentifierNode(Node):
    """
    Online RKGNN identification: buffers joint streams, evolves a model, publishes it.

    Parameters
    ----------
    node_name : str
        Node name (default ``identifier``).
    **kwargs
        Passed to :class:`rclpy.node.Node` (``context``, ``parameter_overrides``, ...).

    Raises
    ------
    ConfigurationError, rclpy.exceptions.ParameterException
        An invalid parameter given at start (the message names it).

    """

    def __init__(self, node_name: str = 'identifier', **kwargs):
        super().__init__(node_name, **kwargs)
        self._params = IdentifierParameters(self)  # an invalid one refuses at once
        # compile every kernel now (numba holds the GIL while compiling): never in the worker
        seconds = precompile()
        self.get_logger().info(f'compiled kernels ready in {seconds:.1f} s'
                               + (' (first run: compiled and cached)' if seconds > 5 else ''))
        self.add_on_set_parameters_callback(self._params.validate)
        self.add_post_set_parameters_callback(self._after_set_parameters)
        config = self._params.config

        publishers = create_publishers(self, quiet_events()[0])

        self._outbox = Outbox()
        # every time rule on the node's clock (use_sim_time), never running backwards
        clock = NodeSeconds(lambda: self.get_clock().now().nanoseconds)
        self._ingestion = Ingestion(config, self._outbox.log, alive=self.context.ok,
                                    on_state=lambda: self._predictor.request(), clock=clock)
        self._predictor = Predictor(self._ingestion, self._from_predictor,
                                    lambda: self._params.config)
        model = load_at_start(config, self._ingestion, self._outbox.log)
        self._description = RobotDescription(self._outbox.log)
        self._configure_description()
        self._worker = SearchWorker(self._ingestion, self._predictor, self._outbox,
                                    alive=self.context.ok, published=model,
                                    policy=partial(OnlineIdentification, clock=clock),
                                    description=self._description)
        self._publishing = Publishing(self, self._outbox, publishers, self._params,
                                      self._predictor, self._ingestion,
                                      lambda: self._worker.status, self._description)
        self._outbox.connect(self.create_guard_condition(self._publishing.drain).trigger)
        # the case in effect (``case: auto`` follows the streams) decides the feed-forward
        self._feedforward = FeedforwardSender(self, self._ingestion,
                                              lambda: self._ingestion.view()[0],
                                              model=self._feedforward_model,
                                              publishers=publishers)
        if model is not None:
            self._publishing.publish_model(model_update(model))

        # the two 1 kHz-capable streams are taken by the ingest thread, the plan here
        state_sub, command_sub = subscribe_streams(self, self._ingestion, self._on_reference,
                                                   config['controller_state'])
        subscribe_description(self, self._on_description)
        self.create_service(Trigger, '~/reset', self._on_reset)
        self.create_service(Trigger, '~/save_model', self._on_save_model)
        self.create_service(Trigger, '~/save_urdf', self._on_save_urdf)
        self.create_service(SetBool, '~/pause', self._on_pause)
        self._prediction_timer = None
        self._make_prediction_timer()
        self.create_timer(1.0, self._publishing.publish_diagnostics)
        if config['feedforward.forward_topic']:  # last: checked against every topic above
            self._feedforward.forward_to(create_forward_publisher(
                self, config['feedforward.forward_topic'], quiet_events()[0]))
        # /clock reset under use_sim_time: the buffered data belong to the old timeline
        self._clock_jumps = watch_clock_jumps(self, self._ingestion)

        self._worker.start()
        self._predictor.start()
        self._feedforward.start()
        self._ingestion.start(state_sub, command_sub)
        # everything built so far (modules, compiled kernels, rclpy) lives as long as the
        # node: keep it out of the cyclic garbage collector, whose full passes over it held
        # the GIL for tens of milliseconds and stalled the 1 kHz streams
        gc.collect()
        gc.freeze()

    def _from_predictor(self, item) -> None:
        """Publish a prediction at once, in the prediction thread; queue anything else."""
        if not isinstance(item, Prediction):
            self._outbox.put(item)
        elif self.context.ok():
            try:
                self._publishing.publish_prediction(item)
            except Exception:  # noqa: B902 - shutting down: the context went meanwhile
                if self.context.ok():
                    raise

    def _after_set_parameters(self, params) -> None:
        """Hand accepted parameters to the parts that depend on them."""
        try:
            changed, effects = self._params.apply(params)
            if not changed:
                return
            self._ingestion.reconfigure(self._params.config,
                                        rebuild=bool(effects & Change.BUFFER),
                                        joints_changed='joints' in changed)
            notes = []
            if effects & Change.RESTART:
                notes.append('structural: the search restarts before the next generation')
            if effects & Change.ES:
                notes.append('applied between generations')
            self.get_logger().info(f'parameters changed: {", ".join(changed)}'
                                   + (f' ({"; ".join(notes)})' if notes else ''))
            if 'prediction.rate' in changed:
                self._make_prediction_timer()
            self._configure_description()
        except Exception:  # noqa: B902 - a callback must never raise
            self._ingestion.drops.internal_error('parameters')

    def _feedforward_model(self, train, case, kp, kd):
        """Return the feed-forward's model: the description's rigid body where there is one."""
        structure = self._description.structure(self._ingestion.joints)
        return feedforward_model(train, case, kp, kd, structure)

    def _configure_description(self) -> None:
        config = self._params.config
        self._description.configure(config['robot_description'], config['urdf.locked_joints'],
                                    config['urdf.locked_positions'], config['gravity'])

    def _on_description(self, raw: bytes) -> None:
        try:
            self._description.take_message(description_text(raw))
        except ValueError as problem:
            self._ingestion.drops.reject('robot_description', 'robot_description', 'over_budget'
                                         if 'bytes' in str(problem) else 'malformed', str(problem))
        except Exception:  # noqa: B902 - a callback must never raise
            self._ingestion.drops.internal_error('robot_description')

    def _make_prediction_timer(self) -> None:
        if self._prediction_timer is not None:
            self.destroy_timer(self._prediction_timer)
            self._prediction_timer = None
        rate = self._params.config['prediction.rate']
        if rate > 0.0:
            self._prediction_timer = self.create_timer(1.0 / rate, self._predictor.request)

    def _on_reference(self, raw: bytes) -> None:
        self._ingestion.handle_reference(raw, self.get_clock().now().nanoseconds * 1e-9)

    def _on_reset(self, request, response):
        self._ingestion.clear()  # first: whatever the worker takes from now on is new
        self._worker.request_reset()
        response.success = True
        response.message = ('buffer cleared; the search restarts when '
                            f"{self._params.config['min_window']} s of data are buffered")
        self.get_logger().info(f'~/reset: {response.message}')
        return response

    def _on_save_model(self, request, response):
        response.success, response.message = save_model_file(
            self._params.config['model_file'], self._publishing.model)
        return response

    def _on_save_urdf(self, request, response):
        response.success, response.message = save_identified_urdf(
            self._params.config['identified_urdf_file'], self._publishing.model)
        return response

    def _on_pause(self, request, response):
        generation = self._worker.pause(request.data)
        response.success = True
        response.message = (f'paused after generation {generation}' if request.data
                            else f'resumed at generation {generation}')
        self.get_logger().info(f'~/pause: {response.message}')
        return response

    def stop(self) -> None:
        """Stop and join the threads, then save the model to ``model_file`` (if set)."""
        # after SIGINT the context is shut down and /rosout cannot be published to: log
        # through a logger that rosout does not know (console only)
        logger = self.get_logger() if self.context.ok() else rclpy.logging.get_logger(
            f'{self.get_name()}.shutdown')
        for part, what in ((self._worker, 'identification worker'),
                           (self._predictor, 'prediction thread'),
                           (self._feedforward, 'feed-forward thread'),
                           (self._ingestion, 'ingest thread')):
            if not part.stop():
                logger.warning(f'the {what} did not stop in time')
        self._publishing.drain()  # publish and log what the threads left
        path = self._params.config['model_file']
        if not path:
            return
        if self._publishing.model is None:
            logger.info(f'at shutdown: no model identified yet, nothing saved to {path}')
            return
        ok, message = save_model_file(path, self._publishing.model)
        (logger.info if ok else logger.error)(f'at shutdown: {message}')


def main(args=None):
    """Run the identifier node until SIGINT or shutdown; return the exit code."""
    interrupt = start_up(args)
    node, code = None, 0
    try:
        node = IdentifierNode()
        interrupt.arm()                     # a SIGINT now ends the spin, raises nothing
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RuntimeError as exc:
        # SIGINT landing inside rclpy's message conversion surfaces as a pybind11
        # RuntimeError ("Unable to convert call argument"), sometimes before rclpy has shut
        # the context down: that is the requested shutdown, not a failure.
        if rclpy.ok() and 'Unable to convert call argument' not in str(exc):
            raise
    except (ConfigurationError, ParameterException) as exc:
        rclpy.logging.get_logger('identifier').fatal(f'refusing to start: {exc}')
        code = 1
    finally:
        if node is not None:
            node.stop()                     # the worker joined, the model file written
        tear_down(node)
    return code


if __name__ == '__main__':
    sys.exit(main())

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
The 27 faults of ``shared/guide/reliability.md``: one named test each.

Each test feeds its exact fault to a running identifier node (in-process, private Context,
its own namespace on this run's ROS_DOMAIN_ID) through the callbacks rclpy calls, the
``set_parameters`` path the ``~/set_parameters`` service calls, or the installed module as
a process, and asserts the documented outcome: the node keeps running, the reason is
counted (``drop_counts()`` is what ``/diagnostics`` shows as ``drops.<reason>``) and
logged (once per second per topic and reason, naming both), buffered data and the model
are intact, and what is published stays finite.
"""

import math
import os
import random
import signal
import subprocess
import sys
import threading
import time

from hypothesis import given, HealthCheck, settings, strategies as st
import numpy as np
import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message, serialize_message
from rkgnn_ros.conversions import make_joint_state
from rkgnn_ros.core.fitting.fitness import FitnessProblem
from rkgnn_ros.core.fitting.identify import Evolution, RKGNNModel
from rkgnn_ros.core.fitting.optimizers import make_optimizer
from rkgnn_ros.core.model.network import NetworkSpec
from rkgnn_ros.core.sim.plant import PDController, PlanarArm
from rkgnn_ros.core.sim.simulate import simulate
from rkgnn_ros.core.sim.trajectories import paper_reference
from rkgnn_ros.identifier import IdentifierNode
from ros_helpers import retire_node
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from std_srvs.srv import SetBool, Trigger
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

pytestmark = pytest.mark.ros

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DOMAIN_ID = int(os.environ.get('ROS_DOMAIN_ID', random.randint(150, 230)))
JOINTS = ('j1', 'j2', 'j3')
T0 = 1000.0  # stamp of the first sample (s)
BASE = {'joints': list(JOINTS), 'window': 4.0, 'min_window': 1.0, 'stale_timeout': 0.5,
        'validation_fraction': 0.25, 'model_publish_period': 0.2, 'prediction.rate': 0.0,
        'prediction.horizon': 0.5, 'es.population_size': 8, 'es.seed': 3}


@pytest.fixture(scope='module')
def data():
    """6 s at 100 Hz of the paper's arm under its PD (every stream the node uses)."""
    return simulate(PlanarArm.paper(), PDController.paper(), paper_reference(3), 6.0,
                    rate=100.0, joint_names=JOINTS)


@pytest.fixture(scope='module')
def model_path(data, tmp_path_factory):
    """Save a case-1 model of the arm (start genome, not fitted) where nodes can load it."""
    spec = NetworkSpec.recommended(3, 'torque')
    model = Evolution(spec, [data], seed=0).best_model(JOINTS)
    path = tmp_path_factory.mktemp('model') / 'model.yaml'
    model.save(path)
    return path


class Harness:
    """One identifier node, its log lines, and what it publishes as predictions."""

    def __init__(self, overrides, spin=False):
        self.context = Context()
        rclpy.init(context=self.context, domain_id=DOMAIN_ID)
        self.ns = f'/rel{os.getpid()}_{random.randint(0, 10 ** 6)}'
        self.node = IdentifierNode(context=self.context, namespace=self.ns,
                                   parameter_overrides=[Parameter(k, value=v)
                                                        for k, v in overrides.items()])
        self.logs = []
        logger = self.node.get_logger()
        for level in ('info', 'warning', 'error'):
            self._record(logger, level)
        self.predictions = []
        self.node._prediction_pub.publish = self.predictions.append
        self.executor = None
        if spin:
            self.executor = SingleThreadedExecutor(context=self.context)
            self.executor.add_node(self.node)
            self.spinner = threading.Thread(target=self.executor.spin, daemon=True)
            self.spinner.start()

    def _record(self, logger, level):
        # recorded instead of printed (rclpy refuses one call site at several severities)
        def log(message, **kwargs):
            self.logs.append((level, str(message)))
            return True
        setattr(logger, level, log)

    def close(self):
        self.node.stop()
        if self.executor is not None:
            self.executor.shutdown(timeout_sec=2.0)
            self.spinner.join(5.0)
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)

    # feeding, exactly as rclpy calls the subscription callbacks (the two streams are
    # raw subscriptions: the callbacks get the CDR bytes)
    def state(self, msg):
        self.node._on_state(serialize_message(msg), None)

    def command(self, msg):
        self.node._on_command(serialize_message(msg))

    def feed(self, data, k0, k1, t0=T0, names=JOINTS, commands=True):
        for k in range(k0, k1):
            stamp = t0 + data.t[k]
            self.state(make_joint_state(stamp, names, data.theta[k], data.theta_dot[k],
                                        data.tau[k]))
            if commands:
                self.command(make_joint_state(stamp, names, data.theta_d[k],
                                              data.theta_d_dot[k]))

    def feed_live(self, data, k0):
        """
        Feed states and commands at 100 Hz from sample ``k0`` on, in a thread.

        The data wraps around, so the streams stay fresh; return the function that stops it.
        """
        stop = threading.Event()

        def run():
            k = k0
            while not stop.is_set():
                i = k % data.t.size
                stamp = T0 + 0.01 * k
                self.state(make_joint_state(stamp, JOINTS, data.theta[i], data.theta_dot[i],
                                            data.tau[i]))
                self.command(make_joint_state(stamp, JOINTS, data.theta_d[i],
                                              data.theta_d_dot[i]))
                k += 1
                time.sleep(0.01)
        thread = threading.Thread(target=run, daemon=True)
        thread.start()

        def halt():
            stop.set()
            thread.join(5.0)
        return halt

    def pause(self, on=True):
        response = self.node._on_pause(SetBool.Request(data=on), SetBool.Response())
        assert response.success, response.message

    def drops(self):
        return dict(self.node.drop_counts())

    def buffered(self):
        return self.node._buffer.stats()['state_samples']

    def warnings_about(self, *words):
        return [m for level, m in self.logs if level in ('warning', 'error')
                and all(w in m for w in words)]

    def predict_finite(self):
        """Publish one prediction now; return its positions and velocities (all finite)."""
        before = len(self.predictions)
        self.node._predict()
        assert len(self.predictions) == before + 1, 'no prediction published'
        msg = deserialize_message(self.predictions[-1], JointTrajectory)
        values = np.array([list(p.positions) + list(p.velocities) for p in msg.points])
        assert values.size and np.isfinite(values).all()
        return msg


@pytest.fixture(scope='module')
def harness(data, model_path):
    """Run a case-1 node with a loaded model, paused, fed 2 s of good data."""
    h = Harness(dict(BASE, model_file=str(model_path)))
    try:
        assert h.node.model is not None, 'the model file was not loaded'
        h.pause(True)
        h.feed(data, 0, 200)
        assert h.buffered() == 200
        yield h
    finally:
        h.close()


def _intact(h, model, buffered):
    """Assert the node alive, its buffer and model unchanged, its prediction finite."""
    assert h.node._worker.is_alive() and h.node._predictor.is_alive()
    assert h.buffered() == buffered
    assert h.node.model is model
    h.predict_finite()


def _fault(h, reason, send, topic='joint_states'):
    """Send a fault; assert it is counted once, logged naming topic and reason, harmless."""
    model, buffered, drops = h.node.model, h.buffered(), h.drops()
    h.node._log_times.clear()
    send()
    after = h.drops()
    assert after[reason] == drops.get(reason, 0) + 1, (reason, after)
    logged = h.warnings_about(topic, reason)
    assert logged, f'no log line names {topic} and {reason}'
    _intact(h, model, buffered)
    return logged[-1]


def _js(names, position, velocity=(), effort=(), stamp=T0 + 50.0):
    msg = JointState(name=list(names), position=[float(v) for v in position],
                     velocity=[float(v) for v in velocity], effort=[float(v) for v in effort])
    msg.header.stamp.sec, frac = int(stamp), stamp - int(stamp)
    msg.header.stamp.nanosec = int(round(frac * 1e9))
    return msg


# ----------------------------------------------------------------------------- streams

def test_item_01_position_length_differs_from_names(harness):
    text = _fault(harness, 'size_mismatch',
                  lambda: harness.state(_js(JOINTS, [0.1, 0.2], [0, 0, 0], [0, 0, 0])))
    assert '3' in text and '2' in text  # both sizes named


@pytest.mark.parametrize('field', ['name', 'position'])
def test_item_02_empty_name_or_position(harness, field):
    msg = _js(JOINTS, [0.1, 0.2, 0.3], [0, 0, 0], [0, 0, 0])
    setattr(msg, field, [])
    _fault(harness, 'empty', lambda: harness.state(msg))


@pytest.mark.parametrize('velocity, effort, reason', [
    ([], [1, 1, 1], 'missing_velocity'), ([0, math.nan, 0], [1, 1, 1], 'missing_velocity'),
    ([0, 0, 0], [], 'missing_effort'), ([0, 0, 0], [1, math.nan, 1], 'missing_effort')])
def test_item_03_missing_velocity_or_effort_is_not_data(harness, velocity, effort, reason):
    # documented decision: velocities are never estimated; such a sample is dropped
    _fault(harness, reason, lambda: harness.state(_js(JOINTS, [0.1, 0.2, 0.3], velocity,
                                                      effort)))


@pytest.mark.parametrize('field', ['position', 'velocity', 'effort'])
@pytest.mark.parametrize('bad', [math.nan, math.inf, -math.inf])
def test_item_04_non_finite_values_are_rejected(harness, field, bad):
    values = {'position': [0.1, 0.2, 0.3], 'velocity': [0.0, 0.0, 0.0],
              'effort': [1.0, 1.0, 1.0]}
    values[field][1] = bad
    reason = 'non_finite'
    if math.isnan(bad) and field != 'position':  # NaN velocity/effort means "not filled"
        reason = 'missing_velocity' if field == 'velocity' else 'missing_effort'
    _fault(harness, reason, lambda: harness.state(_js(JOINTS, **values)))


def test_latency_counts_the_first_prediction_from_each_state(data, model_path):
    # a timer predicting again from the same state (the stream stopped) is not a latency
    h = _fresh(data, model_path)
    try:
        h.pause(True)
        h.feed(data, 0, 200)
        before = len(h.node._latencies)
        h.predict_finite()
        h.predict_finite()  # published again, not counted again
        assert len(h.node._latencies) == before + 1
        h.feed(data, 200, 201)
        h.predict_finite()
        assert len(h.node._latencies) == before + 2
    finally:
        h.close()


def test_item_05_extra_joints_ignored_missing_joint_dropped(harness, data):
    h = harness
    k = 300
    names = ['gripper', 'j3', 'j1', 'j2']
    order = [2, 0, 1]
    before = h.buffered()
    h.state(_js(names, [9.9] + list(data.theta[k][order]), [0.0] + list(data.theta_dot[k][order]),
                [5.0] + list(data.tau[k][order]), stamp=T0 + data.t[k]))
    assert h.buffered() == before + 1  # the gripper is ignored, the sample kept
    text = _fault(h, 'missing_joint',
                  lambda: h.state(_js(['j1', 'j3'], [0.1, 0.2], [0, 0], [1, 1],
                                      stamp=T0 + 60.0)))
    assert "missing joint 'j2'" in text or 'j2' in text


def test_item_06_joint_order_is_mapped_by_name(harness, data):
    h = harness
    k = 301
    perm = [2, 0, 1]
    names = [JOINTS[i] for i in perm]
    h.state(_js(names, data.theta[k][perm], data.theta_dot[k][perm], data.tau[k][perm],
                stamp=T0 + data.t[k]))
    t, theta, theta_dot = h.node._buffer.latest_state()
    assert t == pytest.approx(T0 + data.t[k])
    np.testing.assert_array_equal(theta, data.theta[k])  # per joint, in model order
    np.testing.assert_array_equal(theta_dot, data.theta_dot[k])


def test_item_07_duplicate_joint_name_is_rejected(harness):
    _fault(harness, 'duplicate_name',
           lambda: harness.state(_js(['j1', 'j2', 'j2'], [0.1, 0.2, 0.3], [0, 0, 0],
                                     [1, 1, 1])))


def _trajectory(times, positions, names=JOINTS):
    msg = JointTrajectory(joint_names=list(names))
    msg.header.stamp.sec = int(T0 + 10)
    for t, pos in zip(times, positions):
        point = JointTrajectoryPoint(positions=[float(v) for v in pos])
        point.time_from_start.sec = int(t)
        point.time_from_start.nanosec = int(round((t - int(t)) * 1e9))
        msg.points.append(point)
    return msg


@pytest.mark.parametrize('case', ['no_points', 'non_increasing', 'point_size'])
def test_item_08_bad_trajectory_is_rejected_saying_which(harness, case):
    if case == 'no_points':
        msg, reason, word = _trajectory([], []), 'empty', 'point'
    elif case == 'non_increasing':
        msg = _trajectory([0.0, 0.5, 0.5], [[0, 0, 0]] * 3)
        reason, word = 'non_increasing_time', 'time_from_start'
    else:
        msg = _trajectory([0.0, 0.5], [[0, 0, 0], [0, 0]])
        reason, word = 'size_mismatch', '1'  # names the point index
    text = _fault(harness, reason, lambda: harness.node._on_reference(msg),
                  topic='reference_trajectory')
    assert word in text


def test_item_09_out_of_order_stamps_never_give_a_bad_dt(harness, data):
    h = harness
    newest = h.node._buffer.latest_state()[0]
    late = newest - 0.5  # later than the reorder tolerance, earlier than a clock jump
    k = 0
    _fault(h, 'out_of_order', lambda: h.state(make_joint_state(
        late, JOINTS, data.theta[k], data.theta_dot[k], data.tau[k])))
    for seg in h.node._buffer.snapshot():
        assert np.all(np.diff(seg.t) > 0)


def test_item_10_duplicate_stamps_keep_the_first(harness, data):
    h = harness
    t, theta, _ = h.node._buffer.latest_state()
    _fault(h, 'duplicate_stamp', lambda: h.state(make_joint_state(
        t, JOINTS, theta + 1.0, data.theta_dot[0], data.tau[0])))
    np.testing.assert_array_equal(h.node._buffer.latest_state()[1], theta)


def test_item_11_zero_stamp_before_the_clock_is_rejected(harness):
    msg = _js(JOINTS, [0.1, 0.2, 0.3], [0, 0, 0], [1, 1, 1])
    msg.header.stamp.sec = msg.header.stamp.nanosec = 0
    _fault(harness, 'zero_stamp', lambda: harness.state(msg))


def _fresh(data, model_path=None, **overrides):
    values = dict(BASE, **overrides)
    if model_path is not None:
        values['model_file'] = str(model_path)
    return Harness(values)


def test_item_12_a_gap_splits_the_data_into_segments(data):
    h = _fresh(data)
    try:
        h.pause(True)
        h.feed(data, 0, 150)
        h.feed(data, 150, 300, t0=T0 + 0.5)  # 0.5 s gap > gap_threshold 0.1 s
        segments = list(h.node._buffer.snapshot())
        assert len(segments) == 2
        assert segments[0].t[-1] < segments[1].t[0] - 0.4  # no segment crosses the gap
        assert all(np.allclose(np.diff(s.t), 0.01) for s in segments)
    finally:
        h.close()


def test_item_13_clock_jump_back_clears_and_identification_continues(data):
    h = _fresh(data)
    try:
        h.feed(data, 0, 200)
        assert h.buffered() == 200
        h.node._log_times.clear()
        h.feed(data, 0, 200, t0=T0 - 100.0)  # a simulator restarted 100 s earlier
        assert h.drops()['clock_jump'] >= 1
        assert h.buffered() == 200  # only the new timeline is kept
        assert [m for _, m in h.logs if 'clock jumped' in m]
        h.feed(data, 200, 400, t0=T0 - 100.0)
        assert wait_for(lambda: h.node.generation > 0, 30.0), 'no generation after the jump'
    finally:
        h.close()


def wait_for(predicate, timeout, interval=0.02):
    """Poll ``predicate`` until truthy or ``timeout`` s pass; return its last value."""
    end = time.monotonic() + timeout
    while True:
        value = predicate()
        if value or time.monotonic() > end:
            return value
        time.sleep(interval)


def test_item_14_missing_or_stale_commands_pause_then_resume(data):
    h = _fresh(data, case='pd_gains', kp=[32.84, 42.05, 42.31], kd=[42.44, 0.19, 4.86])
    try:
        status = h.node._status
        h.feed(data, 0, 150, commands=False)
        assert wait_for(lambda: status['state'] == 'waiting for data'
                        and 'joint_commands' in status['detail'], 15.0), status
        # commands arrive: the search starts by itself
        stop = threading.Event()

        def stream(k0):
            k = k0
            while not stop.is_set() and k < data.n_samples:
                h.feed(data, k, k + 1)
                k += 1
                time.sleep(0.01)
        thread = threading.Thread(target=stream, args=(150,), daemon=True)
        thread.start()
        assert wait_for(lambda: h.node.generation > 0, 30.0), status
        stop.set()
        thread.join()
        # the stream stops: stale (noticed between generations), one warning, no generation
        assert wait_for(lambda: status['state'] == 'stale', 20.0), status
        generation = h.node.generation
        time.sleep(0.5)
        assert h.node.generation == generation
        assert len(h.warnings_about('no data')) == 1
        # data returns: the search resumes by itself
        h.feed(data, 0, 300, t0=T0 + data.t[-1] + 0.5)  # after a gap, on the same clock
        assert wait_for(lambda: h.node.generation > generation, 30.0), status
    finally:
        h.close()


def test_streamed_states_are_taken_without_the_executor(data):
    # the ingest thread takes the streams: no executor spins this node, and a burst of
    # states still reaches the buffer (waking the executor per message was the 1 kHz
    # bottleneck), and the executor would not take them either
    h = Harness(dict(BASE))
    pub_node = rclpy.create_node('queue_publisher', context=h.context, namespace=h.ns)
    executor = SingleThreadedExecutor(context=h.context)
    try:
        executor.add_node(h.node)
        assert not executor.can_execute(h.node._state_sub)
        pub = pub_node.create_publisher(JointState, 'joint_states', 100)
        assert wait_for(lambda: pub.get_subscription_count() >= 1, 10.0), 'no discovery'
        count = 60
        for k in range(count):
            pub.publish(make_joint_state(T0 + data.t[k], JOINTS, data.theta[k],
                                         data.theta_dot[k], data.tau[k]))
        # best effort on loopback may lose a few of the burst
        assert wait_for(lambda: h.buffered() >= count // 2, 5.0), h.buffered()
        assert h.drops()['internal_error'] == 0
    finally:
        executor.shutdown(timeout_sec=2.0)
        pub_node.destroy_node()
        h.close()


def test_item_15_a_10khz_burst_stays_bounded_and_services_answer(data):
    h = Harness(dict(BASE), spin=True)
    client_node = rclpy.create_node('burst_client', context=h.context, namespace=h.ns)
    h.executor.add_node(client_node)
    try:
        client = client_node.create_client(Trigger, 'identifier/save_model')
        assert client.wait_for_service(timeout_sec=5.0)
        cap = h.node._buffer.max_samples
        stop = threading.Event()
        sent = [0]

        def burst():  # 3 s of states at 10 kHz stamps (1e-4 s apart), as fast as possible
            k = 0
            while not stop.is_set() and k < 30000:
                i = k % data.n_samples
                h.state(make_joint_state(T0 + 1e-4 * k, JOINTS, data.theta[i],
                                         data.theta_dot[i], data.tau[i]))
                k += 1
            sent[0] = k
        thread = threading.Thread(target=burst, daemon=True)
        thread.start()
        answered = []
        for _ in range(3):
            time.sleep(0.3)
            start = time.monotonic()
            future = client.call_async(Trigger.Request())
            assert wait_for(future.done, 1.0), 'service did not answer within 1 s'
            answered.append(time.monotonic() - start)
        results = h.node.set_parameters([Parameter('es.sigma', value=0.3)])
        assert results[0].successful
        stop.set()
        thread.join(30.0)
        assert h.buffered() <= cap  # memory bounded by max_rate_hz * window
        drops = h.drops()
        assert drops['rate_limited'] > 0  # decimated to max_rate_hz, and counted
        assert h.buffered() + drops['rate_limited'] + drops['overflow'] <= sent[0]
        assert max(answered) < 1.0
    finally:
        retire_node(h.executor, client_node)
        h.close()


# ----------------------------------------------------------------------------- parameters

def _set(h, name, value):
    return h.node.set_parameters([Parameter(name, value=value)])[0]


@pytest.mark.parametrize('name, bad, good, bound', [
    ('es.population_size', -1, 4, '0'),
    ('es.sigma', 0.0, 1e-9, '0'),
    ('es.crossover_rate', 1.5, 1.0, '1'),
    ('es.crossover_rate', -0.1, 0.0, '0'),
    ('es.sigma', math.nan, 0.5, 'sigma'),
    ('stale_timeout', 0.04, 0.05, '0.05'),  # (window would rebuild the buffer)
    ('validation_fraction', 0.51, 0.5, '0.5'),
])
def test_item_16_out_of_range_is_rejected_naming_the_bound(harness, name, bad, good, bound):
    h = harness
    stored = h.node.get_parameter(name).value
    generation = h.node.generation
    result = _set(h, name, bad)
    assert not result.successful
    assert name in result.reason or name.split('.')[-1] in result.reason
    assert bound in result.reason
    assert h.node.get_parameter(name).value == stored
    assert h.node.generation == generation  # paused: the running search is untouched
    assert _set(h, name, good).successful  # the boundary itself is accepted
    assert _set(h, name, stored).successful


def test_item_17_wrong_type_has_one_documented_behaviour(harness):
    h = harness
    stored = h.node.get_parameter('es.sigma').value
    result = _set(h, 'es.sigma', 1)  # an integer for a double: rejected by type
    assert not result.successful and 'type' in result.reason.lower()
    result = _set(h, 'es.population_size', 4.0)
    assert not result.successful and 'type' in result.reason.lower()
    assert h.node.get_parameter('es.sigma').value == stored


def test_item_18_read_only_parameter_is_rejected_by_rclpy(harness):
    h = harness
    result = _set(h, 'max_rate_hz', 500.0)
    assert not result.successful
    assert 'read-only' in result.reason.lower() or 'read only' in result.reason.lower()
    assert h.node.get_parameter('max_rate_hz').value == 2000.0
    result = _set(h, 'identified.cost', 1.0)  # outputs are not settable either
    assert not result.successful and 'identified.cost' in result.reason


def test_item_19_cross_parameter_rule_is_rejected(harness):
    h = harness
    assert _set(h, 'es.algorithm', 'paper').successful
    try:
        assert _set(h, 'es.population_size', 10).successful
        result = _set(h, 'es.tournament_size', 11)
        assert not result.successful and 'tournament_size' in result.reason
        result = _set(h, 'min_window', 4.5)  # > window 4.0
        assert not result.successful and 'min_window' in result.reason
    finally:
        assert _set(h, 'es.algorithm', 'cmaes').successful
        assert _set(h, 'es.population_size', 8).successful


def test_item_20_parameter_burst_applies_between_generations(data):
    h = _fresh(data)
    try:
        stop = threading.Event()

        def stream():
            k = 0
            while not stop.is_set():
                h.feed(data, k % data.n_samples, k % data.n_samples + 1,
                       t0=T0 + (k // data.n_samples) * (data.t[-1] + 0.01))
                k += 1
                time.sleep(0.005)
        thread = threading.Thread(target=stream, daemon=True)
        thread.start()
        try:
            assert wait_for(lambda: h.node.generation > 1, 40.0)
            rng = random.Random(5)
            for _ in range(30):
                size = rng.randint(6, 16)
                results = h.node.set_parameters([
                    Parameter('es.population_size', value=size),
                    Parameter('es.sigma', value=rng.uniform(0.1, 1.0))])
                assert all(r.successful for r in results)
                time.sleep(0.02)
            generation = h.node.generation
            assert wait_for(lambda: h.node.generation > generation + 1, 20.0)
            assert h.node._status['population_size'] == size  # the last set, one snapshot
            assert [m for _, m in h.logs if 'generation' in m and 'setting' in m.lower()]
        finally:
            stop.set()
            thread.join()
    finally:
        h.close()


def _bad_params_file(tmp_path, line):
    with open(os.path.join(ROOT, 'config', 'identifier.yaml')) as f:
        text = f.read()
    key = line.split(':')[0]
    lines = [f'    {line}' if row.strip().startswith(f'{key}:') else row
             for row in text.splitlines()]
    path = tmp_path / 'bad.yaml'
    path.write_text('\n'.join(lines) + '\n')
    return path


def _run_module(args, **kw):
    env = dict(os.environ, ROS_DOMAIN_ID=str(DOMAIN_ID),
               PYTHONPATH=os.pathsep.join(filter(None, [ROOT, os.environ.get('PYTHONPATH')])))
    return subprocess.Popen([sys.executable, '-m', 'rkgnn_ros.identifier', '--ros-args']
                            + args, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, **kw)


def test_item_21_out_of_range_yaml_refuses_to_start(tmp_path):
    path = _bad_params_file(tmp_path, 'validation_fraction: 0.9')
    proc = _run_module(['--params-file', str(path)])
    _, err = proc.communicate(timeout=120)
    assert proc.returncode != 0
    assert 'validation_fraction' in err and 'refusing to start' in err


@settings(max_examples=500, deadline=None, suppress_health_check=list(HealthCheck))
@given(st.lists(st.tuples(
    st.sampled_from(['es.sigma', 'es.population_size', 'window', 'case', 'joints', 'kp',
                     'es.algorithm', 'identified.cost', 'max_rate_hz', 'nonexistent', '']),
    st.one_of(st.none(), st.booleans(), st.integers(-2 ** 70, 2 ** 70),
              st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=8),
              st.lists(st.floats(allow_nan=True), max_size=4),
              st.lists(st.text(max_size=4), max_size=4))), max_size=4))
def test_item_22_on_set_callback_never_raises(harness, params):
    built = []
    for name, value in params:
        try:
            built.append(Parameter(name, value=value))
        except Exception:  # noqa: B902 - rclpy itself refuses some values: not our callback
            built.append(Parameter(name, Parameter.Type.NOT_SET))
    result = harness.node._on_set_parameters(built)
    assert isinstance(result.successful, bool)
    assert result.successful or result.reason


# ------------------------------------------------------------------ threads, shutdown, files

def test_item_23_worker_exception_is_logged_counted_and_survived(data, monkeypatch):
    h = _fresh(data)
    try:
        h.feed(data, 0, 300)
        assert wait_for(lambda: h.node._evo is not None and h.node.generation > 0, 30.0)
        original = Evolution.step
        failed = []

        def failing_step(self):  # the next generation of whichever search runs fails
            if not failed:
                failed.append(True)
                raise np.linalg.LinAlgError('injected: singular matrix')
            return original(self)
        monkeypatch.setattr(Evolution, 'step', failing_step)
        halt = h.feed_live(data, 300)  # fresh streams: a stale stream would pause the search
        try:
            assert wait_for(lambda: h.drops()['worker_error'] == 1, 20.0)  # after a warm start
            assert [m for level, m in h.logs if level == 'error' and 'Traceback' in m
                    and 'singular matrix' in m]
            generation = h.node.generation
            assert wait_for(lambda: h.node.generation > generation, 20.0)
            assert h.node._worker.is_alive()
        finally:
            halt()
    finally:
        h.close()


def test_item_24_sigint_mid_generation_exits_cleanly(data, tmp_path):
    path = tmp_path / 'saved.yaml'
    proc = _run_module(['-p', 'min_window:=0.5', '-p', f'model_file:={path}'])
    node = None
    try:
        # feed it over the middleware so it evolves, then interrupt
        context = Context()
        rclpy.init(context=context, domain_id=DOMAIN_ID)
        node = rclpy.create_node('sigint_feeder', context=context)
        pub_s = node.create_publisher(JointState, 'joint_states', 100)
        pub_c = node.create_publisher(JointState, 'joint_commands', 100)
        models = []
        node.create_subscription(String, 'identifier/model', models.append, QoSProfile(
            depth=1, reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL))
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        t_base = time.time()
        end = time.monotonic() + 90.0
        k = 0
        while time.monotonic() < end and not path.exists():
            i = k % data.n_samples
            stamp = t_base + 0.01 * k
            pub_s.publish(make_joint_state(stamp, JOINTS, data.theta[i], data.theta_dot[i],
                                           data.tau[i]))
            pub_c.publish(make_joint_state(stamp, JOINTS, data.theta_d[i], data.theta_d_dot[i]))
            k += 1
            executor.spin_once(timeout_sec=0.01)
            if models and k >= 200:  # it has a model and is evolving: interrupt it
                proc.send_signal(signal.SIGINT)
                break
        out, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
        if node is not None:
            node.destroy_node()
            rclpy.try_shutdown(context=context)
    assert proc.returncode == 0, err[-2000:]
    assert 'Traceback' not in err
    assert RKGNNModel.load(path).joint_names == JOINTS  # saved at shutdown, loadable


KILL_SAVER = """
import sys, numpy as np
from rkgnn_ros.core.fitting.identify import RKGNNModel
model = RKGNNModel.load(sys.argv[1])
k = 0
while True:
    model.genome[0] = k  # each save differs
    model.save(sys.argv[1])
    k += 1
    if k == 1:
        print('saving', flush=True)
"""


def test_item_25_a_kill_during_saves_leaves_a_loadable_model(model_path, tmp_path):
    path = tmp_path / 'model.yaml'
    path.write_bytes(model_path.read_bytes())
    rng = random.Random(11)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        filter(None, [ROOT, os.environ.get('PYTHONPATH')])))
    for _ in range(10):
        proc = subprocess.Popen([sys.executable, '-c', KILL_SAVER, str(path)], env=env,
                                stdout=subprocess.PIPE, text=True)
        assert proc.stdout.readline().strip() == 'saving'
        time.sleep(rng.uniform(0.0, 0.2))
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
        model = RKGNNModel.load(path)  # the old or the new model, never a torn file
        assert float(model.genome[0]).is_integer()


def test_item_26_saved_model_is_published_first_and_bad_files_refused(data, model_path,
                                                                      tmp_path):
    h = _fresh(data, model_path)
    try:
        assert h.node.model is not None and h.node.generation == 0
        assert h.node.model.joint_names == JOINTS
    finally:
        h.close()
    bad = tmp_path / 'bad.yaml'
    text = model_path.read_text()
    for broken in (text.replace('genome:', 'genome: [.nan]\n  old_genome:', 1),
                   text.replace('- j2\n', '', 1), 'not: a model',
                   text[:len(text) // 2]):
        bad.write_text(broken)
        h = _fresh(data, bad)
        try:
            assert h.node.model is None  # refused: starts fresh
            h.node._load_model_file()  # again, now that its log lines are recorded
            assert h.node.model is None
            assert [m for level, m in h.logs if level == 'error'
                    and 'cannot use model_file' in m and str(bad) in m]
        finally:
            h.close()


def test_item_27_divergence_costs_inf_and_is_never_published(harness, data):
    h = harness
    # the paper's structure (learned V, penalty on M) diverges for random genomes
    spec = NetworkSpec.paper(3, 'torque')
    problem = FitnessProblem(spec, [data])
    rng = np.random.default_rng(0)
    pool = spec.initial_genome() + 10.0 * rng.standard_normal((60, spec.genome_size))
    pool_costs = problem.cost(pool)
    finite = np.flatnonzero(np.isfinite(pool_costs))
    assert finite.size and np.isinf(pool_costs).sum() > 20  # overflow gives +inf, no NaN
    assert not np.isnan(pool_costs).any()
    for name in ('paper', 'cmaes'):
        optimizer = make_optimizer(name, spec.genome_size, x0=spec.initial_genome(), rng=rng,
                                   population_size=20)
        X = optimizer.ask()
        X[:] = pool[np.isinf(pool_costs)][:20]
        X[7] = pool[finite[0]]  # the one candidate that does not diverge
        costs = problem.cost(X)
        assert np.isinf(costs).sum() == 19 and math.isfinite(costs[7])
        optimizer.tell(X, costs)
        assert optimizer.best_cost == np.min(costs[np.isfinite(costs)])
        assert math.isfinite(problem.cost(optimizer.best_x[None])[0])  # never selected
    # a published model that diverges from the newest state: no prediction is published
    model = h.node.model
    bad = RKGNNModel(spec, model.scales, spec.initial_genome() + 10.0 * rng.standard_normal(
        spec.genome_size), joint_names=JOINTS, dt=model.dt, substeps=1)
    with h.node._lock:
        h.node._model = bad
    try:
        before, published = h.drops()['prediction_non_finite'], len(h.predictions)
        h.node._predict()
        assert len(h.predictions) == published
        assert h.drops()['prediction_non_finite'] == before + 1
    finally:
        with h.node._lock:
            h.node._model = model
    h.predict_finite()


# ------------------------------------------------ property-based: the whole input path

_FLOATS = st.floats(allow_nan=True, allow_infinity=True, width=64)
_NAMES = st.lists(st.sampled_from(['j1', 'j2', 'j3', 'gripper', '', 'j1 ']), max_size=5)
_VALUES = st.lists(st.one_of(_FLOATS, st.sampled_from([1e300, -1e300, 0.0])), max_size=5)
_STAMP = st.tuples(st.integers(-2 ** 31, 2 ** 31 - 1), st.integers(0, 999_999_999))


@settings(max_examples=500, deadline=None, suppress_health_check=list(HealthCheck))
@given(_NAMES, _VALUES, _VALUES, _VALUES, _STAMP)
def test_any_joint_state_is_taken_or_rejected_never_raised(harness, names, position,
                                                           velocity, effort, stamp):
    msg = JointState(name=names, position=position, velocity=velocity, effort=effort)
    msg.header.stamp.sec, msg.header.stamp.nanosec = stamp
    before = harness.drops()['internal_error']
    harness.state(msg)
    harness.command(msg)
    assert harness.drops()['internal_error'] == before  # a counted reason, never a crash
    latest = harness.node._buffer.latest_state()
    assert np.isfinite(latest[1]).all() and np.isfinite(latest[2]).all()


@settings(max_examples=500, deadline=None, suppress_health_check=list(HealthCheck))
@given(_NAMES, st.lists(st.tuples(_FLOATS, _VALUES, _VALUES), max_size=4), _STAMP)
def test_any_joint_trajectory_is_taken_or_rejected_never_raised(harness, names, points,
                                                                stamp):
    msg = JointTrajectory(joint_names=names)
    msg.header.stamp.sec, msg.header.stamp.nanosec = stamp
    for t, positions, velocities in points:
        point = JointTrajectoryPoint(positions=positions, velocities=velocities)
        if math.isfinite(t) and abs(t) < 2 ** 30:
            point.time_from_start.sec = int(math.floor(t))
            point.time_from_start.nanosec = int((t - math.floor(t)) * 1e9) % 1_000_000_000
        msg.points.append(point)
    before = harness.drops()['internal_error']
    harness.node._on_reference(msg)
    assert harness.drops()['internal_error'] == before

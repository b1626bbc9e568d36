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
The parts of the identifier node (:mod:`rkgnn_ros.identification`), each on its own.

The parameter table and its snapshots, the ingest thread on real subscriptions with no
executor, the predictor's inputs and latency bookkeeping, the outbox, the worker's error
handling and the shared parameter row type. The node's behaviour through its topics and
services is in ``test_identifier.py`` and ``test_reliability.py``.
"""

import json
import math
import os
import random
import subprocess
import sys
import threading

import numpy as np
import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.serialization import deserialize_message, serialize_message
from rkgnn_ros.core.differentiate import causal_derivative
from rkgnn_ros.core.fitting.identify import Evolution
from rkgnn_ros.core.fitting.online import LogLine, OnlineIdentification, Status
from rkgnn_ros.core.model.spec import NetworkSpec
from rkgnn_ros.core.sim.plant import PDController, PlanarArm
from rkgnn_ros.core.sim.simulate import simulate
from rkgnn_ros.core.sim.trajectories import paper_reference
from rkgnn_ros.identification import prediction as prediction_module
from rkgnn_ros.identification.ingest import Ingestion, PolledGroup
from rkgnn_ros.identification.parameters import (ConfigurationError, IdentifierParameters,
                                                 make_config, PARAMETERS)
from rkgnn_ros.identification.prediction import Prediction, Predictor
from rkgnn_ros.identification.publishing import Outbox
from rkgnn_ros.identification.worker import SearchWorker
from rkgnn_ros.node.parameters import Change, ParameterSpec
from rkgnn_ros.wire.conversions import make_joint_state, make_joint_trajectory
from ros_helpers import wait_for
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory

pytestmark = pytest.mark.ros

DOMAIN_ID = int(os.environ.get('ROS_DOMAIN_ID', random.randint(150, 230)))
JOINTS = ('j1', 'j2', 'j3')
T0 = 1000.0


@pytest.fixture(scope='module')
def data():
    """3 s at 100 Hz of the paper's arm under its PD."""
    return simulate(PlanarArm.paper(), PDController.paper(), paper_reference(3), 3.0,
                    rate=100.0, joint_names=JOINTS)


@pytest.fixture
def context():
    """Yield a private rclpy context on this run's domain."""
    ctx = Context()
    rclpy.init(context=ctx, domain_id=DOMAIN_ID)
    try:
        yield ctx
    finally:
        rclpy.try_shutdown(context=ctx)


def _feed(ingestion, data, k0, k1, t0=T0):
    for k in range(k0, k1):
        stamp = t0 + data.t[k]
        ingestion.handle_state(serialize_message(make_joint_state(
            stamp, JOINTS, data.theta[k], data.theta_dot[k], data.tau[k])), 1000 + k)
        ingestion.handle_command(serialize_message(make_joint_state(
            stamp, JOINTS, data.theta_d[k], data.theta_d_dot[k])))


# ------------------------------------------------------------------ parameter rows

def test_a_parameter_row_declares_checks_and_says_what_a_change_does(context):
    live = ParameterSpec('gain', 0.5, 'A gain.', 0.0, 1.0, low_open=True)
    start = ParameterSpec('names', ['a', 'b'], 'Names.', change=Change.START)
    assert live.kind == Parameter.Type.DOUBLE and not live.read_only
    assert start.kind == Parameter.Type.STRING_ARRAY and start.read_only
    assert live.check(0.0) == 'gain must be a finite number in (0.0, 1.0], got 0.0'
    assert live.check(math.nan) and live.check(1) and live.check(1.0) is None
    assert start.check(['a', 'a']) and start.check(['a', '']) and start.check(('x',)) is None
    node = rclpy.create_node('rows', context=context)
    try:
        assert live.declare(node) == 0.5 and list(start.declare(node)) == ['a', 'b']
        described = node.describe_parameter('gain')
        assert described.floating_point_range[0].to_value == 1.0
        assert node.describe_parameter('names').read_only
    finally:
        node.destroy_node()


def test_every_identifier_parameter_says_what_a_change_does():
    by_name = {spec.name: spec.change for spec in PARAMETERS}
    for name in ('case', 'joints', 'model_step'):  # a new timeline: data and search anew
        assert by_name[name] == Change.RESTART | Change.BUFFER
    assert by_name['window'] == by_name['gap_threshold'] == Change.BUFFER
    assert all(by_name[name] == Change.RESTART for name in by_name
               if name.startswith('network.') or name in ('kp', 'kd', 'substeps'))
    assert {name for name, change in by_name.items() if change == Change.ES} == {
        'es.algorithm', 'es.population_size', 'es.tournament_size', 'es.crossover_rate',
        'es.mutation_rate', 'es.sigma', 'es.sigma_min'}
    assert by_name['max_rate_hz'] == Change.START
    assert by_name['prediction.rate'] == by_name['es.seed'] == Change.LIVE


def test_applied_parameters_make_one_new_snapshot_and_name_their_changes(context):
    node = rclpy.create_node('identifier_parameters', context=context,
                             parameter_overrides=[Parameter('case', value='unknown')])
    try:
        params = IdentifierParameters(node)
        before = params.config
        assert before.case == 'unknown' and before.settings.version == 0
        changed, effects = params.apply([Parameter('es.sigma', value=0.25),
                                         Parameter('window', value=10.0)])
        after = params.config
        assert changed == ('es.sigma', 'window') and effects == Change.ES | Change.BUFFER
        assert after.settings.optimizer_settings['sigma'] == 0.25 and after['window'] == 10.0
        assert after.settings.version == 0  # no restart
        assert before['window'] == 20.0  # the old snapshot is untouched
        assert params.apply([Parameter('es.sigma', value=0.25)]) == ((), Change(0))
        changed, effects = params.apply([Parameter('network.theta_units', value=4)])
        assert effects & Change.RESTART and params.config.settings.version == 1
        assert params.config.settings.spec(3).theta_units == 4
    finally:
        node.destroy_node()


def test_invalid_values_at_start_refuse_naming_the_parameter():
    with pytest.raises(ConfigurationError, match='min_window'):
        make_config(min_window=30.0)  # > window
    with pytest.raises(ConfigurationError, match='kp and kd'):
        make_config(case='pd_gains')
    assert make_config(case='2', kp=[1.0], kd=[1.0]).case == 'pd_gains'
    with pytest.raises(ConfigurationError, match='network.basis must be one of'):
        make_config(**{'network.basis': 'fourier'})


def test_network_basis_selects_the_features_of_the_identified_network():
    # case 'auto' resolves to a case from the streams; the spec is the resolved case's
    assert make_config(case='torque').settings.spec(3).basis == 'rbf'
    spec = make_config(case='torque', **{'network.basis': 'trig+rbf'}).settings.spec(3)
    assert spec.basis == 'trig+rbf' and spec.n_features == 12 + spec.theta_units


# ------------------------------------------------------------------ ingestion

def test_the_ingest_thread_takes_the_streams_without_any_executor(context, data):
    # the subscriptions sit in a group no executor runs; the ingest thread takes what
    # the middleware queued on them, states and commands
    node = rclpy.create_node('ingest_only', context=context)
    publisher = rclpy.create_node('streamer', context=context)
    lines = []
    ingestion = Ingestion(make_config(joints=list(JOINTS)),
                          lambda level, text: lines.append(text))
    polled = PolledGroup()
    subs = [node.create_subscription(JointState, topic, lambda raw: None, 100,
                                     callback_group=polled, raw=True)
            for topic in ('joint_states', 'joint_commands')]
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    assert not any(executor.can_execute(sub) for sub in subs)
    ingestion.start(*subs)
    try:
        states = publisher.create_publisher(JointState, 'joint_states', 100)
        commands = publisher.create_publisher(JointState, 'joint_commands', 100)
        assert wait_for(lambda: states.get_subscription_count() >= 1
                        and commands.get_subscription_count() >= 1, 60.0), 'no discovery'
        for k in range(60):
            stamp = T0 + data.t[k]
            states.publish(make_joint_state(stamp, JOINTS, data.theta[k], data.theta_dot[k],
                                            data.tau[k]))
            commands.publish(make_joint_state(stamp, JOINTS, data.theta_d[k],
                                              data.theta_d_dot[k]))
        # the default reliable QoS of these publishers against a best-effort reader:
        # loopback may still lose a few of the burst
        assert wait_for(lambda: ingestion.samples_buffered() >= 30
                        and ingestion.buffer.stats()['command_samples'] >= 30, 60.0)
        assert ingestion.drops.counts()['internal_error'] == 0
        assert ingestion.latest_state.received_ns > 0
    finally:
        assert ingestion.stop()
        executor.shutdown(timeout_sec=2.0)
        publisher.destroy_node()
        node.destroy_node()


def test_joints_are_learned_from_the_first_state_and_a_rebuild_keeps_the_counters(data):
    lines = []
    ingestion = Ingestion(make_config(), lambda level, text: lines.append(text))
    assert ingestion.joints is None
    ingestion.handle_command(serialize_message(make_joint_state(
        T0, JOINTS, data.theta_d[0], data.theta_d_dot[0])))
    assert ingestion.drops.counts()['no_joints'] == 1
    _feed(ingestion, data, 0, 50)
    assert ingestion.joints == JOINTS and ingestion.samples_buffered() == 50
    assert 'joints from the first joint_states message' in lines[-1]
    ingestion.handle_state(b'\x00\x01\x00\x00 not a JointState')
    ingestion.reconfigure(make_config(window=6.0), rebuild=True)
    assert ingestion.samples_buffered() == 0 and ingestion.joints == JOINTS
    assert ingestion.drops.counts()['malformed'] == 1  # counted before the rebuild, kept


def test_a_prediction_is_asked_for_on_accepted_states_at_most_once_per_model_step(data):
    clock = [0.0]
    requests = []
    ingestion = Ingestion(make_config(joints=list(JOINTS), **{'prediction.on_state': True}),
                          lambda level, text: None, on_state=lambda: requests.append(clock[0]),
                          clock=lambda: clock[0])
    for k in range(40):
        clock[0] += 0.004  # states every 4 ms, model_step 10 ms
        ingestion.handle_state(serialize_message(make_joint_state(
            T0 + 0.004 * k, JOINTS, data.theta[k], data.theta_dot[k], data.tau[k])))
    assert 13 <= len(requests) <= 16
    assert np.all(np.diff(requests) >= 0.01 - 1e-12)


# ------------------------------------------------------------------ what the driver publishes

def _state(data, k, velocity=True, effort=True):
    return serialize_message(make_joint_state(
        T0 + data.t[k], JOINTS, data.theta[k], data.theta_dot[k] if velocity else None,
        data.tau[k] if effort else None))


def test_case_auto_follows_the_effort_with_a_second_of_hysteresis(data):
    clock = [0.0]
    lines = []
    ingestion = Ingestion(make_config(joints=list(JOINTS)),
                          lambda level, text: lines.append(text), clock=lambda: clock[0])
    assert ingestion.sources.describe()['case_in_effect'] == 'auto: waiting for joint_states'
    for k in range(50):  # effort in joint_states: case 1 at once
        clock[0] += 0.01
        ingestion.handle_state(_state(data, k))
    config, _, buffer, _ = ingestion.view()
    assert config.settings.case == 'torque' and buffer.need_tau
    assert 'auto -> torque (effort in joint_states)' in ingestion.sources.describe()[
        'case_in_effect']
    for k in range(50, 140):  # the driver stops publishing effort: dropped for 1 s ...
        clock[0] += 0.01
        ingestion.handle_state(_state(data, k, effort=False))
    assert ingestion.view()[0].settings.case == 'torque'
    assert ingestion.drops.counts()['missing_effort'] == 90
    for k in range(140, 160):  # ... then case 3 (no gains given), the buffer rebuilt
        clock[0] += 0.01
        ingestion.handle_state(_state(data, k, effort=False))
    assert ingestion.view()[0].settings.case == 'unknown'
    assert [t for t in lines if t.startswith('case auto: unknown (no effort in joint_states')]
    assert 0 < ingestion.samples_buffered() <= 11
    ingestion.handle_state(_state(data, 160))  # one message with effort changes nothing
    assert ingestion.view()[0].settings.case == 'unknown'
    # a set case stays whatever the streams do
    ingestion.reconfigure(make_config(joints=list(JOINTS), case='torque'), rebuild=True)
    assert ingestion.view()[0].settings.case == 'torque'


def test_without_velocity_the_start_state_gets_the_causal_estimate(data):
    ingestion = Ingestion(make_config(joints=list(JOINTS)), lambda level, text: None)
    ingestion.handle_state(_state(data, 0, velocity=False))
    assert ingestion.latest_state is None   # nothing to start a prediction from yet
    for k in range(1, 300):
        ingestion.handle_state(_state(data, k, velocity=False))
    latest = ingestion.latest_state
    assert latest.velocity_estimated and ingestion.velocity_estimated
    expected = causal_derivative(data.theta[285:300], 0.01)
    np.testing.assert_allclose(latest.theta_dot, expected, rtol=1e-9, atol=1e-12)
    # the documented delay (a few ms) and gain (a few %) of the causal fit
    assert np.abs(latest.theta_dot - data.theta_dot[299]).max() < 0.05 * np.ptp(
        data.theta_dot)
    assert 'estimated from position' in ingestion.sources.describe()['velocity_source']
    assert ingestion.drops.counts()['missing_velocity'] == 0


def test_without_joint_commands_the_plan_gives_the_commands(data):
    clock = [0.0]
    ingestion = Ingestion(make_config(joints=list(JOINTS), case='unknown'),
                          lambda level, text: None, clock=lambda: clock[0])
    ingestion.handle_state(_state(data, 0))
    _plan(ingestion, data, 0, 3.0)
    for k in range(1, 200):
        clock[0] += 0.01
        ingestion.handle_state(_state(data, k))
    # joint_commands is given stale_timeout (1 s) after the first state is taken: the
    # plausibility filter takes a stream's first samples once RUN of them agree (state 2)
    count = ingestion.buffer.stats()['command_samples']
    assert count in (97, 98)  # states 103 (or 102, the clock's rounding) to 199
    assert ingestion.sources.describe()['commands_source'].startswith('reference_trajectory')
    np.testing.assert_allclose(ingestion.latest_command, data.theta_d[199], atol=1e-3)
    commands = [item for item in ingestion.feed if item[0] == 'command']
    assert len(commands) == count and commands[-1][1] == T0 + data.t[199]
    segments = ingestion.capture().segments(10)
    assert segments and segments[0].theta_d is not None


# ------------------------------------------------------------------ prediction

@pytest.fixture(scope='module')
def unknown_model(data):
    """Return a case-3 model of the arm (start genome)."""
    return Evolution(NetworkSpec.recommended(3, 'unknown'), [data], seed=0).best_model(JOINTS)


def _predictor(config, model, holder=None):
    """Return ingestion, predictor and what it published; ``holder['config']`` is read."""
    holder = {} if holder is None else holder
    holder.setdefault('config', config)
    ingestion = Ingestion(config, lambda level, text: None)
    published = []

    def publish(item):  # what the node's executor does with a prediction
        if isinstance(item, Prediction):
            published.append(item.data)
            predictor.published(item)
    predictor = Predictor(ingestion, publish, lambda: holder['config'])
    predictor.set_model(model)
    predictor.warm_up(model)
    return ingestion, predictor, published


def _plan(ingestion, data, k, seconds):
    """Send the plan from sample ``k`` over ``seconds`` (points every 0.1 s)."""
    ahead = slice(k, k + int(round(seconds * 100)) + 1, 10)
    ingestion.handle_reference(make_joint_trajectory(
        T0 + data.t[k], JOINTS, data.t[ahead] - data.t[k], data.theta_d[ahead],
        data.theta_d_dot[ahead]), T0)


def test_latency_counts_the_first_prediction_from_each_state(data, unknown_model):
    # a timer predicting again from the same state (the stream stopped) is not a latency
    config = make_config(case='unknown', joints=list(JOINTS))
    ingestion, predictor, published = _predictor(config, unknown_model)
    assert not predictor.predict()  # no state yet
    _feed(ingestion, data, 0, 100)
    _plan(ingestion, data, 99, 3.0)
    assert predictor.predict() and predictor.predict()
    assert len(published) == 2 and predictor.latencies().size == 1
    _feed(ingestion, data, 100, 101)
    assert predictor.predict() and predictor.latencies().size == 2


def test_predictions_closer_than_score_every_s_are_published_not_scored(data, unknown_model,
                                                                        monkeypatch):
    # at 1 kHz with prediction.on_state, scoring every prediction held up the next one
    monkeypatch.setattr(prediction_module, 'SCORE_EVERY_S', 0.025)
    config = make_config(case='unknown', joints=list(JOINTS))
    ingestion, predictor, published = _predictor(config, unknown_model)
    _feed(ingestion, data, 0, 100)
    _plan(ingestion, data, 99, 3.0)
    for k in range(100, 110):  # states 10 ms apart, a prediction from each
        _feed(ingestion, data, k, k + 1)
        assert predictor.predict()
    assert len(published) == 10 and predictor.latencies().size == 10
    # the self-check recorded those 25 ms apart: from the states 0, 30, 60 and 90 ms on
    recorded = predictor._check._predictions.t - T0  # noqa: SLF001 - what it scores
    np.testing.assert_allclose(recorded, data.t[[100, 103, 106, 109]], atol=1e-9)


def _times(msg):
    return np.array([p.time_from_start.sec + 1e-9 * p.time_from_start.nanosec
                     for p in msg.points])


def test_no_prediction_point_lies_past_the_plans_end_unless_marked(data, unknown_model):
    config = make_config(case='unknown', joints=list(JOINTS), **{'prediction.horizon': 0.5})
    holder = {}
    ingestion, predictor, published = _predictor(config, unknown_model, holder)
    _feed(ingestion, data, 0, 100)
    # joint_commands but no plan: with beyond_plan 'stop' nothing is predicted
    assert not predictor.predict() and 'no plan' in predictor.inputs
    _plan(ingestion, data, 99, 2.0)
    assert predictor.predict() and predictor.inputs == 'reference'
    msg = deserialize_message(published[-1], JointTrajectory)
    assert len(msg.points) == 51 and msg.header.frame_id == 'baseline:follow_reference'
    np.testing.assert_array_equal(msg.points[0].positions, data.theta[99])
    # a plan that ends 0.3 s ahead: the prediction ends there
    _plan(ingestion, data, 99, 0.3)
    assert predictor.predict()
    msg = deserialize_message(published[-1], JointTrajectory)
    assert _times(msg)[-1] == pytest.approx(0.3) and 'beyond_plan' not in msg.header.frame_id
    # 'hold': the whole horizon, the points past the plan's end marked from where they start
    holder['config'] = make_config(case='unknown', joints=list(JOINTS),
                                   **{'prediction.horizon': 0.5,
                                      'prediction.beyond_plan': 'hold'})
    assert predictor.predict()
    msg = deserialize_message(published[-1], JointTrajectory)
    assert len(msg.points) == 51
    assert msg.header.frame_id == 'baseline:follow_reference;beyond_plan_from=0.300'
    theta_end = data.theta_d[99 + 30]
    for point in msg.points[31:]:  # following the plan past its end: its last point held
        np.testing.assert_allclose(point.positions, theta_end)
    ingestion.clear()  # ~/reset drops the plan: the newest command held, marked from 0
    _feed(ingestion, data, 100, 110)
    assert predictor.predict() and predictor.inputs == 'held command'
    msg = deserialize_message(published[-1], JointTrajectory)
    assert msg.header.frame_id.endswith(';beyond_plan_from=0.000')


# ------------------------------------------------------------------ outbox and worker

def test_the_outbox_keeps_order_wakes_the_executor_and_stays_bounded():
    outbox = Outbox(limit=3)
    wakes = []
    outbox.log('info', 'queued before anyone listens')
    outbox.connect(lambda: wakes.append(1))
    assert wakes == [1]  # woken at once: something was waiting
    for k in range(4):
        outbox.put(k)
    assert len(wakes) == 5 and outbox.take() == [1, 2, 3] and outbox.take() == []

    def broken():
        raise RuntimeError('the guard condition is gone (shutdown)')
    outbox.connect(broken)
    outbox.put('after shutdown')  # never raises into the thread that puts
    assert outbox.take() == ['after shutdown']


class _Failing(OnlineIdentification):
    """A policy whose steps fail."""

    def step(self, obs):
        raise FloatingPointError('injected')


def test_the_worker_logs_counts_and_survives_a_failing_step(data):
    outbox = Outbox()
    ingestion = Ingestion(make_config(joints=list(JOINTS)), outbox.log)
    predictor = Predictor(ingestion, lambda raw: None, make_config)
    worker = SearchWorker(ingestion, predictor, outbox, policy=_Failing)
    worker.start()
    try:
        assert wait_for(lambda: ingestion.drops.counts()['worker_error'] >= 2, 60.0)
        assert worker.status.state == 'error' and 'injected' in worker.status.detail
    finally:
        assert worker.stop()
    lines = [e for e in outbox.take() if isinstance(e, LogLine)]
    failures = [e.text for e in lines if e.level == 'error']
    assert 'identification worker failed (1 in a row), retrying in 0.5 s' in failures[0]
    assert 'Traceback' in failures[0] and 'injected' in failures[0]
    assert 'retrying in 1.0 s' in failures[1]  # backing off


def test_the_worker_runs_blas_on_its_own_thread_only(data, monkeypatch):
    from rkgnn_ros.identification import worker as worker_module
    threads = []
    monkeypatch.setattr(worker_module, 'single_threaded_blas',
                        lambda: threads.append(threading.current_thread().name))
    outbox = Outbox()
    ingestion = Ingestion(make_config(joints=list(JOINTS)), outbox.log)
    worker = SearchWorker(ingestion, Predictor(ingestion, lambda raw: None, make_config),
                          outbox, policy=_Failing)
    worker.start()
    try:
        assert wait_for(lambda: threads, 60.0)
    finally:
        assert worker.stop()
    assert threads == ['rkgnn_identifier']


def test_single_threaded_blas_set_from_a_thread_holds_for_the_process():
    pytest.importorskip('threadpoolctl')
    if (os.cpu_count() or 1) < 2:
        pytest.skip('one core: BLAS runs one thread anyway')
    script = (
        'import json, threading, numpy, scipy.linalg, threadpoolctl\n'
        'from rkgnn_ros.identification.worker import single_threaded_blas\n'
        'info = lambda: [lib["num_threads"] for lib in threadpoolctl.threadpool_info()\n'
        '                if lib["user_api"] == "blas"]\n'
        'before = info()\n'
        'thread = threading.Thread(target=single_threaded_blas)\n'
        'thread.start()\n'
        'thread.join()\n'
        'print(json.dumps([before, info()]))\n')
    env = dict(os.environ)
    env.pop('OPENBLAS_NUM_THREADS', None)
    env.pop('OMP_NUM_THREADS', None)
    out = subprocess.run([sys.executable, '-c', script], capture_output=True, text=True,
                         timeout=120, env=env, check=True).stdout
    before, after = json.loads(out.strip().splitlines()[-1])
    assert before and max(before) > 1  # numpy's default: a thread per core
    assert after == [1] * len(before)


def test_the_worker_reports_status_and_pause(data):
    outbox = Outbox()
    ingestion = Ingestion(make_config(), outbox.log)
    predictor = Predictor(ingestion, lambda raw: None, make_config)
    worker = SearchWorker(ingestion, predictor, outbox)
    assert worker.status == Status()
    assert not worker.step()
    assert worker.status.detail == 'no joint_states yet (joints unknown)'
    assert worker.pause(True) == 0
    assert not worker.step() and worker.status.state == 'paused'
    worker.pause(False)
    worker.request_reset()
    assert not worker.step() and worker.status.state == 'waiting for data'

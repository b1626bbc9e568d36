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
The identifier's parameters under fuzz, against a running node.

Every declared parameter is set through ``~/set_parameters`` (what ``ros2 param set``
calls) to values drawn to break it: subnormal, huge, NaN, infinite, the bounds and their
neighbours, wrong types, long texts and arrays. The node's on-set validation decides and
its apply path runs. Every value it accepts must be one it can run with: the test runs
each through what the node does with it (the prediction timer's period, the stream buffer,
the network, an optimizer generation, the prediction's size), then sets it back. The
boundary values of the parameters that size timers, optimizers and rollouts then run for
5 s each against a live node fed at 100 Hz, which must still publish finite predictions.
Nothing may print a traceback or count an internal error.
"""

import math
import os
import random
import threading
import time

from diagnostic_msgs.msg import DiagnosticArray
from hypothesis import event, given, HealthCheck, settings, strategies as st
import numpy as np
import pytest
from rcl_interfaces.srv import GetParameters, SetParameters
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter, parameter_value_to_python
from rclpy.serialization import serialize_message
from rkgnn_ros.core.fitting.identify import Evolution
from rkgnn_ros.core.fitting.optimizers import make_optimizer
from rkgnn_ros.core.model.network import NetworkSpec
from rkgnn_ros.core.sim.plant import PDController, PlanarArm
from rkgnn_ros.core.sim.simulate import simulate
from rkgnn_ros.core.sim.trajectories import paper_reference
from rkgnn_ros.identification.model_file import save_model_file
from rkgnn_ros.identification.parameters import (make_config, MAX_POPULATION,
                                                 MAX_PREDICTION_POINTS, network_spec, PARAMETERS)
from rkgnn_ros.identifier import IdentifierNode
from rkgnn_ros.streams.buffer import StreamBuffer
from rkgnn_ros.wire.conversions import make_joint_state
from ros_helpers import Rosout, Spinner, wait_for
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory

pytestmark = pytest.mark.ros

DOMAIN_ID = int(os.environ.get('ROS_DOMAIN_ID', random.randint(150, 230)))
JOINTS = ('j1', 'j2', 'j3')
PATIENCE = 60.0
LIVE_SECONDS = 5.0
BASE = {'joints': list(JOINTS), 'window': 4.0, 'min_window': 1.0, 'stale_timeout': 0.5,
        'model_publish_period': 0.5, 'prediction.horizon': 0.5, 'prediction.rate': 10.0,
        'prediction.on_state': True, 'es.population_size': 8, 'es.seed': 3,
        # the feed has joint_commands but no plan: predict past it as the arm holding them
        'prediction.beyond_plan': 'hold'}
_T = Parameter.Type
_BY_NAME = {spec.name: spec for spec in PARAMETERS}


@pytest.fixture(scope='module')
def data():
    return simulate(PlanarArm.paper(), PDController.paper(), paper_reference(3), 6.0,
                    rate=100.0, joint_names=JOINTS)


class LiveNode:
    """An identifier with a loaded model, spun in a thread, and a client that feeds it."""

    def __init__(self, model_path):
        self.context = Context()
        rclpy.init(context=self.context, domain_id=DOMAIN_ID)
        self.ns = f'/fuzz{os.getpid()}_{random.randint(0, 10 ** 6)}'
        self.logger = f'{self.ns[1:]}.identifier'
        overrides = dict(BASE, model_file=str(model_path))
        self.node = IdentifierNode(context=self.context, namespace=self.ns,
                                   parameter_overrides=[Parameter(k, value=v)
                                                        for k, v in overrides.items()])
        self.client = rclpy.create_node('fuzz_client', context=self.context,
                                        namespace=self.ns)
        self.rosout = Rosout(self.client)
        self.lock = threading.Lock()
        self.predictions = []  # (receipt time, finite)
        self.diagnostics = []
        base = f'{self.ns}/identifier'
        self.client.create_subscription(JointTrajectory, f'{base}/prediction',
                                        self._on_prediction, 100)
        self.client.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 10)
        self.set_client = self.client.create_client(SetParameters, f'{base}/set_parameters')
        self.get_client = self.client.create_client(GetParameters, f'{base}/get_parameters')
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.executor.add_node(self.client)
        self.spinner = Spinner(self.executor)

    def _on_prediction(self, msg):
        values = np.array([list(p.positions) + list(p.velocities) for p in msg.points])
        with self.lock:
            self.predictions.append((time.monotonic(), bool(np.isfinite(values).all())))

    def _on_diag(self, msg):
        for status in msg.status:
            if status.hardware_id == f'{self.ns}/identifier':
                with self.lock:
                    self.diagnostics.append({kv.key: kv.value for kv in status.values})

    def call(self, client, request):
        assert client.wait_for_service(timeout_sec=PATIENCE), client.srv_name
        future = client.call_async(request)
        assert wait_for(future.done, PATIENCE), f'{client.srv_name} did not answer'
        return future.result()

    def set_one(self, param):
        request = SetParameters.Request(parameters=[param.to_parameter_msg()])
        return self.call(self.set_client, request).results[0]

    def values(self):
        names = [spec.name for spec in PARAMETERS]
        response = self.call(self.get_client, GetParameters.Request(names=names))
        return {name: parameter_value_to_python(v) for name, v in zip(names, response.values)}

    def feed(self, data):
        """Publish states and commands at 100 Hz until the returned stop is called."""
        states = self.client.create_publisher(JointState, 'joint_states', 100)
        commands = self.client.create_publisher(JointState, 'joint_commands', 100)
        stop = threading.Event()

        def run():
            t_base, k = time.time(), 0
            while not stop.is_set():
                i = k % data.n_samples
                stamp = t_base + 0.01 * k
                states.publish(serialize_message(make_joint_state(
                    stamp, JOINTS, data.theta[i], data.theta_dot[i], data.tau[i])))
                commands.publish(serialize_message(make_joint_state(
                    stamp, JOINTS, data.theta_d[i], data.theta_d_dot[i])))
                k += 1
                stop.wait(max(0.0, stamp + 0.01 - time.time()))
        thread = threading.Thread(target=run, daemon=True)
        thread.start()

        def halt():
            stop.set()
            thread.join(5.0)
        return halt

    def close(self):
        self.spinner.stop()
        self.node.stop()
        # the fuzz accepts generations that take minutes (10,000 candidates): stop() still
        # ends the worker within a chunk of one, never leaving it running past the node
        assert not any(t.name == 'rkgnn_identifier' and t.is_alive()
                       for t in threading.enumerate())
        self.node.destroy_node()
        self.client.destroy_node()
        rclpy.try_shutdown(context=self.context)


@pytest.fixture(scope='module')
def live(data, tmp_path_factory):
    model = Evolution(NetworkSpec.recommended(3, 'torque'), [data], seed=0).best_model(JOINTS)
    model.info['cost'] = 1.0
    path = tmp_path_factory.mktemp('fuzz_model') / 'model.yaml'
    ok, message = save_model_file(str(path), model)
    assert ok, message
    node = LiveNode(path)
    try:
        yield node
    finally:
        node.close()


# ------------------------------------------------------------------ values that break things

_FLOAT_EXTREMES = [0.0, -0.0, 5e-324, -5e-324, 2.2250738585072014e-308, 1e-300, 1e-9, 1e-6,
                   0.1, 1.0, 1e6, 1e9, 1e308, -1e308, math.inf, -math.inf, math.nan]
_TEXT = st.text(st.characters(blacklist_characters='\x00', blacklist_categories=('Cs',)),
                max_size=40)


def _neighbours(value):
    return [value, math.nextafter(value, -math.inf), math.nextafter(value, math.inf)]


def _values(spec):
    """Return a strategy of values that should break ``spec``: typed, then wrong types."""
    kind = spec.kind
    bounds = [b for b in (spec.low, spec.high, spec.off_below) if b is not None]
    floats = st.one_of(st.sampled_from(_FLOAT_EXTREMES + [v for b in bounds
                                                          for v in _neighbours(float(b))]),
                       st.floats(allow_subnormal=True))
    if kind == _T.DOUBLE:
        typed = floats
    elif kind == _T.INTEGER:
        edges = [0, 1, 2, -1, 2 ** 31 - 1, 2 ** 63 - 1, -2 ** 63] + [
            int(b) + d for b in bounds for d in (-1, 0, 1)]
        typed = st.one_of(st.sampled_from(edges), st.integers(-2 ** 63, 2 ** 63 - 1))
    elif kind == _T.BOOL:
        typed = st.booleans()
    elif kind == _T.STRING:
        typed = st.one_of(st.sampled_from(list(spec.choices) + [
            '', ' ', 'x' * 5000, '/dev/zero', '/tmp', '~', '1', '3', 'TORQUE']), _TEXT)
    elif kind == _T.DOUBLE_ARRAY:
        typed = st.lists(floats, max_size=70)
    else:
        typed = st.lists(st.one_of(_TEXT, st.sampled_from(['', 'x' * 300, 'j1'])),
                         max_size=70)
    wrong = st.one_of(st.booleans(), st.integers(-5, 5), st.sampled_from([1.5, math.nan]),
                      _TEXT, st.lists(st.integers(0, 3), max_size=3))
    return st.one_of(typed, typed, typed, wrong)


def _parameter(name, value):
    kind = _BY_NAME[name].kind
    if isinstance(value, list) and not value and kind in (_T.DOUBLE_ARRAY, _T.STRING_ARRAY):
        return Parameter(name, kind, [])
    try:
        return Parameter(name, value=value)
    except Exception:  # noqa: B902 - rclpy cannot even build it: send no value at all
        return Parameter(name, _T.NOT_SET)


def _runs(values):
    """Run accepted parameter values through what the node does with each; fail if any can't."""
    config = make_config(**values)  # the snapshot the parts read
    rate = config['prediction.rate']
    if rate:  # rclpy's create_timer: int(period * 1e9) must be a positive int64
        period_ns = int(float(1.0 / rate) * 1e9)
        assert 0 < period_ns < 2 ** 63 and period_ns <= 10 * 10 ** 9
    joints = config['joints'] or JOINTS
    buffer = StreamBuffer(joints, config['model_step'], config['window'],
                          config['gap_threshold'], need_tau=config.case == 'torque',
                          need_desired=config.case != 'torque',
                          max_rate_hz=config['max_rate_hz'])
    assert buffer.max_samples <= 2 ** 20
    spec = network_spec(config.values, len(joints))
    settings_ = config.settings
    optimizer = make_optimizer(settings_.optimizer, spec.genome_size, x0=spec.initial_genome(),
                               rng=0, **dict(settings_.optimizer_settings))
    assert optimizer.population_size <= MAX_POPULATION
    for _ in range(2):
        X = optimizer.ask()
        optimizer.tell(X, np.square(X).sum(axis=1))
    assert np.isfinite(optimizer.best_x).all()
    points = round(config['prediction.horizon'] / config['model_step'])
    assert 1 <= points <= MAX_PREDICTION_POINTS


@pytest.fixture(scope='module')
def accepted():
    """Count the values the node accepted during the fuzz (what it says is worth running)."""
    return {'sets': 0, 'accepted': 0}


@settings(max_examples=600, deadline=None, suppress_health_check=list(HealthCheck))
@given(draw=st.data())
def test_every_accepted_value_is_one_the_node_can_run_with(live, accepted, draw):
    spec = draw.draw(st.sampled_from(PARAMETERS))
    value = draw.draw(_values(spec))
    before = live.values()
    result = live.set_one(_parameter(spec.name, value))
    accepted['sets'] += 1
    event('accepted' if result.successful else 'refused')  # --hypothesis-show-statistics
    assert result.successful or result.reason  # a refusal says why
    if not result.successful:
        assert live.values()[spec.name] == before[spec.name]  # the stored value stands
        return
    accepted['accepted'] += 1
    now = live.values()
    try:
        _runs(now)
    finally:  # back to the running configuration
        assert live.set_one(_parameter(spec.name, before[spec.name])).successful
    assert not live.rosout.lines(live.logger, 'Traceback')


def test_the_fuzz_met_the_node(live, accepted):
    # whatever hypothesis drew, the on-set path was hit and some values passed
    assert accepted['sets'] >= 500 and accepted['accepted'] > 0, accepted
    with live.lock:
        seen = list(live.diagnostics)
    assert seen and all(int(d['drops.internal_error']) == 0 for d in seen)
    assert not live.rosout.lines(live.logger, 'Traceback')


#: Boundary values of the parameters that size timers, optimizers, buffers and rollouts.
LIVE_VALUES = [
    ('prediction.rate', 1000.0), ('prediction.rate', 0.1), ('es.sigma', 1e-6),
    ('es.sigma', 10.0), ('es.population_size', MAX_POPULATION), ('window', 1.0),
    ('model_step', 0.1), ('prediction.horizon', 60.0), ('es.algorithm', 'paper'),
]


@pytest.mark.parametrize('name, value', LIVE_VALUES)
def test_boundary_values_run_for_five_seconds_and_the_node_still_predicts(live, data, name,
                                                                          value):
    before = live.values()[name]
    halt = live.feed(data)
    try:
        assert wait_for(lambda: live.predictions, PATIENCE), 'no prediction before the set'
        result = live.set_one(_parameter(name, value))
        assert result.successful, result.reason
        start = time.monotonic()
        time.sleep(LIVE_SECONDS)
        with live.lock:
            after = [finite for t, finite in live.predictions if t > start]
        # predictions go on (model_step 0.1 rebuilds the buffer: its first states still
        # predict, on_state), every one finite
        assert after and all(after), (len(after), name, value)
    finally:
        halt()
        assert live.set_one(_parameter(name, before)).successful
    assert not live.rosout.lines(live.logger, 'Traceback')

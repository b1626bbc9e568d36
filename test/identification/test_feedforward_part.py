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
The identifier's feed-forward part on its own: models that must never produce an effort.

:class:`~rkgnn_ros.identification.feedforward.FeedforwardSender` is driven pass by pass
(``step()``) on a real node and publisher, with the joint data of a simulated run handed
in by a stand-in for the ingest part and the model injected: a model that gives NaN on
the validation samples, one whose rollout diverges, one that turns non-finite on the plan
after passing. What leaves is read from ``~/feedforward`` by a subscriber. The node
through its topics and parameters is in ``test_identifier_feedforward.py``.
"""

import math
import os
import random
import time

import numpy as np
import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rkgnn_ros.core.control.feedforward import plan_feedforward
from rkgnn_ros.core.sim.plant import PDController, PlanarArm
from rkgnn_ros.core.sim.simulate import simulate
from rkgnn_ros.core.sim.trajectories import paper_reference
from rkgnn_ros.identification.feedforward import FeedforwardSender, RAMP_S
from rkgnn_ros.identification.parameters import ConfigurationError, make_config
from rkgnn_ros.streams.capture import PlannedReference
from trajectory_msgs.msg import JointTrajectory

pytestmark = pytest.mark.ros

DOMAIN_ID = int(os.environ.get('ROS_DOMAIN_ID') or random.SystemRandom().randint(150, 199))
JOINTS = ('j1', 'j2', 'j3')
ARM = PlanarArm.paper()


class ArmModel:
    """The simulated arm as a fitted model, with ways to go wrong."""

    def __init__(self, nan_on_data=False, diverges=False):
        self.n_joints, self.case_ = 3, 'torque'
        self.nan_on_data, self.diverges, self.nan_on_plan = nan_on_data, diverges, False

    def inverse_dynamics(self, theta, theta_dot, theta_ddot):
        tau = ARM.inverse_dynamics(theta, theta_dot, theta_ddot)
        if self.nan_on_data or self.nan_on_plan:
            tau = np.full_like(tau, math.nan)
        return tau

    def simulate(self, x0, t, tau=None, **_):
        out = np.tile(x0, (len(t), 1))
        return out * math.nan if self.diverges else out


class FakeCapture:
    """A buffer capture that always holds the same segments."""

    def __init__(self, segments):
        self._segments = segments

    def segments(self, min_samples, pair):
        return list(self._segments)


class FakeIngestion:
    """What the part reads from the ingest part: joints, freshness, data, the reference."""

    def __init__(self, config, data):
        self.config, self.joints, self.data = config, JOINTS, data
        self.plan = None
        self.errors = 0
        self.drops = self  # its drop accounting: internal_error

    def view(self):
        return self.config, self.joints, None, {'state': self.seconds()}

    def seconds(self):  # the ingestion's clock: the data always just arrived
        return time.monotonic()

    def capture(self):
        return FakeCapture([self.data])

    def reference(self):
        return self.plan

    def new_plan(self, now):
        times = np.arange(0.0, 3.0 + 1e-9, 0.02)
        theta_d, theta_d_dot = paper_reference(3).evaluate(times)
        self.plan = PlannedReference(now, times, theta_d, theta_d_dot)

    def internal_error(self, where):
        self.errors += 1


@pytest.fixture(scope='module')
def data():
    """8 s of the paper's arm under its PD, recorded from 1 s in."""
    run = simulate(ARM, PDController.paper(), paper_reference(3), 9.0, joint_names=JOINTS)
    return run.slice(100, run.n_samples)


@pytest.fixture
def rig(data):
    """Yield (sender, ingestion, received messages, spin) on a private context."""
    context = Context()
    rclpy.init(context=context, domain_id=DOMAIN_ID)
    node = rclpy.create_node(f'ff_part_{random.getrandbits(32):08x}', context=context)
    received = []
    node.create_subscription(JointTrajectory, f'{node.get_name()}/feedforward',
                             received.append, 10)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    # case 1 set (the node hands the part the case in effect: 'auto' resolved)
    config = make_config(case='torque', **{'feedforward.enabled': True,
                                           'feedforward.max_effort': (30.0, 20.0, 5.0)})
    ingestion = FakeIngestion(config, data)
    senders = []

    def make(model):
        sender = FeedforwardSender(node, ingestion, lambda: ingestion.config,
                                   lambda *a: model)
        senders.append(sender)
        return sender

    def spin(passes=20):
        for _ in range(passes):
            executor.spin_once(timeout_sec=0.01)
    try:
        yield make, ingestion, received, spin, node
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)


def run_passes(sender, ingestion, node, spin, passes=3):
    for _ in range(passes):
        ingestion.new_plan(node.get_clock().now().nanoseconds * 1e-9)
        sender.step()
        spin()


def test_the_true_model_is_sent_clipped_with_a_ramp(rig):
    make, ingestion, received, spin, node = rig
    sender = make(ArmModel())
    run_passes(sender, ingestion, node, spin)
    with_points = [m for m in received if m.points]
    assert with_points, 'the true model passes the gate'
    first = with_points[0]
    effort = np.array([p.effort for p in first.points])
    times = np.array([p.time_from_start.sec + 1e-9 * p.time_from_start.nanosec
                      for p in first.points])
    plan = plan_feedforward(ARM, times, [p.positions for p in first.points],
                            [p.velocities for p in first.points])
    limit = np.array([30.0, 20.0, 5.0])
    assert np.all(np.abs(effort) <= limit)
    assert np.all(effort[0] == 0.0)  # the ramp starts from zero at the switch-on
    # a plan made after the switch-on (the last pass's) is past the ramp from RAMP_S on
    last = with_points[-1]
    assert last is not first
    effort = np.array([p.effort for p in last.points])
    times = np.array([p.time_from_start.sec + 1e-9 * p.time_from_start.nanosec
                      for p in last.points])
    plan = plan_feedforward(ARM, times, [p.positions for p in last.points],
                            [p.velocities for p in last.points])
    full = times >= RAMP_S
    assert np.any(full) and np.all(np.abs(effort) <= limit)
    np.testing.assert_allclose(effort[full], np.clip(plan.effort[full], -limit, limit),
                               rtol=1e-12, atol=1e-9)
    assert sender.diagnostics().status[0].message == 'on'


@pytest.mark.parametrize('quick_fit_s, passes_to_on', [(60.0, 1), (0.0, 2)])
def test_a_quick_fit_is_judged_in_its_own_pass_a_slow_one_in_the_next(
        rig, monkeypatch, quick_fit_s, passes_to_on):
    # every fit is quick with a 60 s bound, and slow with 0: after a slow fit the ingest
    # thread must catch up before the data's freshness is judged, a pass later
    from rkgnn_ros.identification import feedforward
    monkeypatch.setattr(feedforward, 'QUICK_FIT_S', quick_fit_s)
    make, ingestion, received, spin, node = rig
    sender = make(ArmModel())
    states = []
    for _ in range(2):
        ingestion.new_plan(node.get_clock().now().nanoseconds * 1e-9)
        sender.step()
        spin()
        states.append(sender.diagnostics().status[0].message)
    assert states.index('on') == passes_to_on - 1, states
    assert any(m.points for m in received)


@pytest.mark.parametrize('model, reason', [
    (ArmModel(nan_on_data=True), 'non-finite torque on the validation samples'),
    (ArmModel(diverges=True), 'diverges on the validation samples'),
])
def test_a_non_finite_or_diverging_model_never_produces_an_effort(rig, model, reason):
    make, ingestion, received, spin, node = rig
    sender = make(model)
    run_passes(sender, ingestion, node, spin, passes=4)
    assert not received and sender.published == 0
    status = sender.diagnostics().status[0]
    assert status.message.startswith('off') and reason in status.message, status.message


def test_a_model_that_turns_non_finite_on_the_plan_is_stopped(rig):
    make, ingestion, received, spin, node = rig
    model = ArmModel()
    sender = make(model)
    run_passes(sender, ingestion, node, spin)
    assert any(m.points for m in received)
    count = len(received)
    model.nan_on_plan = True
    run_passes(sender, ingestion, node, spin, passes=2)
    new = received[count:]
    assert new and not any(m.points for m in new)  # only the stop (an empty trajectory)
    assert all(np.all(np.isfinite(p.effort)) for m in received for p in m.points)
    assert 'non-finite torque on the plan' in sender.diagnostics().status[0].message


def test_the_clip_parameter_takes_one_value_per_joint_one_for_all_or_none():
    for clip in ((), (5.0,), (30.0, 20.0, 5.0)):
        make_config(joints=list(JOINTS), **{'feedforward.max_effort': clip})
    for clip in ((30.0, 20.0), (30.0, 0.0, 5.0)):
        with pytest.raises(ConfigurationError, match='feedforward.max_effort'):
            make_config(joints=list(JOINTS), **{'feedforward.max_effort': clip})


def test_case_auto_sends_nothing_until_the_streams_decide(rig):
    make, ingestion, received, spin, node = rig
    # the node hands the part the case in effect: 'auto' while no joint_states came
    ingestion.config = make_config(**{'feedforward.enabled': True,
                                      'feedforward.max_effort': (30.0, 20.0, 5.0)})
    sender = make(ArmModel())
    run_passes(sender, ingestion, node, spin)
    assert not received and sender.published == 0
    assert 'case auto: not decided yet' in sender.diagnostics().status[0].message


def test_the_forward_topic_must_be_a_topic_name():
    make_config(**{'feedforward.forward_topic': '/sim_arm/feedforward'})
    for topic in ('a b', '/a//b', '{x}/feedforward', 'x' * 300):
        with pytest.raises(ConfigurationError, match='feedforward.forward_topic'):
            make_config(**{'feedforward.forward_topic': topic})

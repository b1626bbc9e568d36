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
Finite garbage among joint_states (issue 31, probe break 1): dropped before any fit.

Two garbage messages a second among a 100 Hz stream made the feed-forward's refit ask for
37 GiB (a model stiffness of 7e9 1/s) and poisoned the search's model. The
:class:`~rkgnn_ros.identification.plausibility.PlausibilityFilter` in the ingestion drops
them (counted per reason, logged), loses no good sample (not with noise, drops, bursts,
jumps the stream then keeps, nor at its start), and a rollout bounds its substeps.
"""

import tracemalloc

import numpy as np
import pytest
from rclpy.serialization import serialize_message
from rkgnn_ros.core.control.model import feedforward_model
from rkgnn_ros.core.data import Dataset
from rkgnn_ros.core.fitting.validation import MIN_SEGMENT_SAMPLES, split_validation
from rkgnn_ros.core.model.trig_dynamics import MAX_SUBSTEPS
from rkgnn_ros.core.sim.plant import PDController, PlanarArm
from rkgnn_ros.core.sim.simulate import simulate
from rkgnn_ros.core.sim.trajectories import paper_reference
from rkgnn_ros.identification.feedforward import rollout_error
from rkgnn_ros.identification.ingest import Ingestion
from rkgnn_ros.identification.parameters import make_config
from rkgnn_ros.identification.plausibility import PLAUSIBILITY_REASONS, PlausibilityFilter
from rkgnn_ros.wire.conversions import make_joint_state

JOINTS = ('j1', 'j2', 'j3')
T0 = 1000.0


@pytest.fixture(scope='module')
def data():
    """20 s at 100 Hz of the paper's arm under its PD."""
    return simulate(PlanarArm.paper(), PDController.paper(), paper_reference(3), 20.0,
                    rate=100.0, joint_names=JOINTS)


def garbage(rng, n=3):
    """Return finite garbage within ±1e6: random signs, magnitudes 1e-2 ... 1e6."""
    return rng.uniform(-1.0, 1.0, n) * 10.0 ** rng.uniform(-2.0, 6.0, n)


def ingest(data, every=None, rng=None):
    """Feed the run (and a garbage state every ``every`` samples); return the ingestion."""
    lines = []
    ingestion = Ingestion(make_config(joints=list(JOINTS), window=30.0, case='torque'),
                          lambda level, text: lines.append((level, text)), clock=lambda: 0.0)
    for k in range(data.n_samples):
        stamp = T0 + data.t[k]
        if every and k % every == every // 2:  # on the stamp a good sample has: it replaces it
            ingestion.handle_state(serialize_message(make_joint_state(
                stamp, JOINTS, garbage(rng), garbage(rng), garbage(rng))))
        ingestion.handle_state(serialize_message(make_joint_state(
            stamp, JOINTS, data.theta[k], data.theta_dot[k], data.tau[k])))
    ingestion.lines = lines
    return ingestion


def fitted(ingestion):
    segments = ingestion.capture().segments(MIN_SEGMENT_SAMPLES, False)
    train, validation, _ = split_validation(segments, 0.25, MIN_SEGMENT_SAMPLES)
    return feedforward_model(train, 'torque'), validation


def test_garbage_among_the_stream_is_dropped_counted_and_fits_as_clean_data(data):
    clean = ingest(data)
    dirty = ingest(data, every=50, rng=np.random.default_rng(0))  # 2 messages a second
    drops = dirty.drops.counts()
    assert sum(drops[reason] for reason in PLAUSIBILITY_REASONS) == 40
    assert drops['duplicate_stamp'] == 0  # no garbage took a good sample's place
    assert dirty.samples_buffered() == clean.samples_buffered() == data.n_samples
    assert any('joint_states: dropped a message (implausible_' in text and 'no arm' in text
               for level, text in dirty.lines if level == 'warning')
    (model, validation), (reference, _) = fitted(dirty), fitted(clean)
    np.testing.assert_array_equal(model.coef_, reference.coef_)
    assert rollout_error(model, validation, 'torque') < 0.01


def test_a_rollout_of_a_model_fitted_to_garbage_stays_within_its_substeps(data):
    # what the feed-forward's refit met: a model fitted with garbage inside its data
    rng = np.random.default_rng(1)
    theta, theta_dot, tau = data.theta.copy(), data.theta_dot.copy(), data.tau.copy()
    for k in range(25, data.n_samples, 50):
        theta[k], theta_dot[k], tau[k] = garbage(rng), garbage(rng), garbage(rng)
    poisoned = Dataset(t=data.t, theta=theta, theta_dot=theta_dot, tau=tau)
    train, validation, _ = split_validation([poisoned], 0.25, MIN_SEGMENT_SAMPLES)
    model = feedforward_model(train, 'torque')
    tracemalloc.start()
    try:
        error = rollout_error(model, validation, 'torque')
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert error > 0.0  # inf when it diverges at the bound: the gate refuses it
    steps = min(validation[-1].n_samples, 101)
    assert peak < 64 * steps * MAX_SUBSTEPS * 2 * 3 * 8 + 2 ** 20  # stage inputs at the bound


def stream(data, rng, noise=1e-4, drop=0.02, bursts=True):
    """Yield (t, θ, θ̇, τ) of the run at 1 kHz-like stamps with noise, drops and bursts."""
    k = 0
    while k < data.n_samples:
        if rng.random() < drop:  # a gap of up to 0.3 s
            k += int(rng.integers(1, 30))
            continue
        repeat = int(rng.integers(1, 4)) if bursts and rng.random() < 0.05 else 1
        for _ in range(repeat):  # a burst: the same sample again (a driver resending)
            yield (T0 + data.t[k], data.theta[k] + rng.normal(0.0, noise, 3),
                   data.theta_dot[k] + rng.normal(0.0, noise / 0.01, 3), data.tau[k])
        k += 1


def test_a_good_stream_with_noise_drops_and_bursts_loses_nothing(data):
    rng = np.random.default_rng(2)
    gate = PlausibilityFilter(JOINTS)
    offered = passed = 0
    for t, theta, theta_dot, tau in stream(data, rng):
        out, dropped = gate.offer(offered, t, theta, theta_dot, tau)
        assert not dropped, dropped
        offered += 1
        passed += len(out)
    assert passed == offered - gate.held


def test_a_jump_the_stream_keeps_is_let_through_after_a_run(data):
    gate = PlausibilityFilter(JOINTS)
    passed = []
    for k in range(200):
        shift = 2.0 if k >= 100 else 0.0  # an encoder re-homed: θ jumps by 2 rad for good
        out, dropped = gate.offer(k, T0 + data.t[k], data.theta[k] + shift,
                                  data.theta_dot[k], data.tau[k])
        assert not dropped
        passed += out
    assert passed == list(range(200 - gate.held))
    assert passed[:3] == [0, 1, 2]  # the first samples: held until three agree


def test_garbage_first_does_not_become_the_anchor(data):
    gate = PlausibilityFilter(JOINTS)
    rng = np.random.default_rng(3)
    out, _ = gate.offer('garbage', T0 - 0.01, garbage(rng), garbage(rng), garbage(rng))
    assert out == []
    passed, reasons = [], []
    for k in range(10):
        out, dropped = gate.offer(k, T0 + data.t[k], data.theta[k], data.theta_dot[k],
                                  data.tau[k])
        passed += out
        reasons += [reason for payload, reason, _ in dropped if payload == 'garbage']
    assert passed == list(range(10)) and reasons and reasons[0] in PLAUSIBILITY_REASONS


@pytest.mark.parametrize('field, reason', [(0, 'implausible_jump'),
                                           (1, 'implausible_velocity'),
                                           (2, 'implausible_effort')])
def test_each_field_has_its_reason(data, field, reason):
    gate = PlausibilityFilter(JOINTS)
    for k in range(50):
        gate.offer(k, T0 + data.t[k], data.theta[k], data.theta_dot[k], data.tau[k])
    values = [data.theta[50].copy(), data.theta_dot[50].copy(), data.tau[50].copy()]
    values[field][1] = 1e5
    out, _ = gate.offer('bad', T0 + data.t[50], *values)
    assert out == []
    out, dropped = gate.offer(51, T0 + data.t[51], data.theta[51], data.theta_dot[51],
                              data.tau[51])
    assert out == [51] and [(p, r) for p, r, _ in dropped] == [('bad', reason)]
    assert "'j2'" in dropped[0][2] or 'j2' in dropped[0][2]

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

"""The excitation-aware data memory (core/fitting/memory.py)."""

import math

import numpy as np
import pytest
from rkgnn_ros.core.fitting.linear import (default_window, LinearDynamics, Samples,
                                           samples_from_datasets, torque_nrmse)
from rkgnn_ros.core.fitting.memory import ExcitationMemory, MemoryFeed
from rkgnn_ros.core.model.trig import TrigBasis
from rkgnn_ros.core.model.trig_dynamics import regressor
from rkgnn_ros.core.sim.plant import PDController, PlanarArm
from rkgnn_ros.core.sim.simulate import simulate
from rkgnn_ros.core.sim.trajectories import hanging_pose, paper_reference, SumOfSines

ARM = PlanarArm.paper()
PD = PDController.paper()
BASIS = TrigBasis(3, planar=True)


def run(reference, duration, seed=0):
    data = simulate(ARM, PD, reference, duration + 1.0, rate=100.0, t0=-1.0, rng=seed)
    return samples_from_datasets(data.slice(100, data.n_samples), 'torque', window=7)


@pytest.fixture(scope='module')
def tasks():
    """Task A: wide swings about the hanging pose; task B: small motion about another pose."""
    first = run(paper_reference(3), 8.0)
    pose = hanging_pose(3) + np.array([1.0, -0.8, 0.8])
    second = run(SumOfSines.random(3, np.random.default_rng(12), n_terms=2, amplitude=0.05,
                                   min_frequency_hz=0.2, max_frequency_hz=0.5,
                                   offsets=pose), 20.0, seed=1)
    again = run(SumOfSines.random(3, np.random.default_rng(11), n_terms=3, amplitude=0.5),
                4.0, seed=2)
    return first, second, again


def stream(memory, *parts, batch=100):
    logdets = []
    for part in parts:
        for start in range(0, part.n_samples, batch):
            memory.offer(part.take(slice(start, start + batch)))
            logdets.append(memory.log_det())
    return logdets


def test_the_model_keeps_what_it_learned_when_the_arm_moves_elsewhere(tasks):
    first, second, again = tasks
    weights = 1.0 / np.sqrt(np.mean(first.tau ** 2, axis=0))
    memory = ExcitationMemory(BASIS, capacity=150, weights=weights)
    logdets = stream(memory, first, second)
    assert memory.size == 150 and memory.offered == first.n_samples + second.n_samples
    # most of what it keeps comes from the task the arm left, which excites far more
    kept = memory.samples
    from_first = np.isin(kept.theta[:, 0], first.theta[:, 0]).mean()
    assert from_first > 0.5
    assert np.all(np.diff(logdets) >= -1e-9)
    # the newest window alone against the same window plus the memory, on task A again
    window = second.take(slice(second.n_samples - 500, None))
    errors = {}
    for name, samples in (('window', window),
                          ('memory', Samples.concatenate([kept, window]))):
        model = LinearDynamics(BASIS, certify=False).fit_samples(samples, 'torque')
        errors[name] = torque_nrmse(
            model.inverse_dynamics(again.theta, again.theta_dot, again.theta_ddot), again.tau)
    assert errors['memory'] < 0.002
    assert errors['memory'] < 0.2 * errors['window']
    # and the regressor the memory holds is far better conditioned than the newest samples
    fifo = ExcitationMemory(BASIS, capacity=150, weights=weights)
    fifo.offer(window.take(slice(-150, None)))
    assert memory.condition_number() < 1e-3 * fifo.condition_number()


def test_diagnostics_are_those_of_the_stacked_regressor(tasks):
    first, _, _ = tasks
    memory = ExcitationMemory(BASIS, capacity=80)
    stream(memory, first.take(slice(0, 300)), batch=50)
    kept = memory.samples
    rows = regressor(BASIS, kept.theta, kept.theta_dot, kept.theta_ddot, 0.05)
    rows = rows.reshape(-1, rows.shape[-1])
    rows = rows / np.sqrt(np.mean(regressor(BASIS, first.theta[:50], first.theta_dot[:50],
                                            first.theta_ddot[:50], 0.05).reshape(
        -1, rows.shape[-1]) ** 2, axis=0)).clip(min=1e-300)
    sv = np.linalg.svd(rows, compute_uv=False)
    assert memory.min_singular_value() == pytest.approx(sv.min(), rel=1e-6)
    assert memory.condition_number() == pytest.approx(sv.max() / sv.min(), rel=1e-6)


def test_a_repeated_sample_is_not_taken_once_the_memory_is_full(tasks):
    first, _, _ = tasks
    memory = ExcitationMemory(BASIS, capacity=60)
    stream(memory, first.take(slice(0, 400)))
    before = memory.log_det()
    copy = memory.samples.take(slice(0, 1))
    assert memory.offer(Samples.concatenate([copy] * 20)) == 0
    assert memory.log_det() == before


def test_starts_empty_and_refuses_bad_settings():
    memory = ExcitationMemory(BASIS, capacity=10)
    assert memory.size == 0 and memory.samples is None
    assert memory.condition_number() == float('inf')
    with pytest.raises(ValueError, match='capacity'):
        ExcitationMemory(BASIS, capacity=0)
    with pytest.raises(ValueError, match='weights'):
        ExcitationMemory(BASIS, weights=[1.0, -1.0, 1.0])
    with pytest.raises(TypeError, match='TrigBasis'):
        ExcitationMemory(3)


def test_the_feed_offers_each_sample_once_away_from_the_ends():
    data = simulate(ARM, PD, paper_reference(3), 6.0, rate=100.0)
    feed = MemoryFeed(capacity=1000, every=5)
    assert feed.size == 0 and math.isnan(feed.condition_number()) and feed.samples is None
    first = feed.feed([data.slice(0, 301)], 50.0, 'torque')
    edge = default_window(data.dt) // 2
    # stamps 50 + k / 100 s: every 5th by stamp, half a Savitzky-Golay window from the ends
    assert first == len([k for k in range(edge, 301 - edge) if k % 5 == 0])
    assert feed.feed([data.slice(0, 301)], 50.0, 'torque') == 0      # nothing new
    grown = feed.feed([data.slice(0, 501)], 50.0, 'torque')          # only the new samples
    assert grown == len([k for k in range(301 - edge, 501 - edge) if k % 5 == 0])
    kept = feed.samples.theta
    assert len({tuple(row) for row in kept}) == kept.shape[0] == first + grown
    offered = [k for k in range(edge, 501 - edge) if k % 5 == 0]
    assert np.isin(kept[:, 0], data.theta[offered, 0]).all()
    assert feed.condition_number() >= 1.0
    # another kind of regressor (the arm's, then the closed loop's) starts over
    assert feed.feed([data.slice(0, 301)], 50.0, 'unknown') == first
    assert feed.size == first
    feed.reset()
    assert feed.size == 0

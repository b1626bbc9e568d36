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

"""The feed-forward gate: each refusal with its reason, the clip, never a NaN effort."""

from dataclasses import replace

import numpy as np
import pytest
from rkgnn_ros.core.control.feedforward import plan_feedforward
from rkgnn_ros.core.control.gate import FeedforwardGate, GateSettings, torque_scale_problem
from rkgnn_ros.core.data import Dataset
from rkgnn_ros.core.fitting.torque_check import torque_scale_from_effort
from rkgnn_ros.core.model.model import RKGNNModel
from rkgnn_ros.core.model.scales import Scales
from rkgnn_ros.core.model.spec import NetworkSpec
from rkgnn_ros.core.sim.parameters import ArmParameters
from rkgnn_ros.core.sim.plant import PDController, PlanarArm
from rkgnn_ros.core.sim.simulate import simulate
from rkgnn_ros.core.sim.trajectories import heldout_reference, paper_reference

N = 3
ARM = PlanarArm.paper()
PD = PDController.paper()
KP, KD = np.diag(PD.kp).copy(), np.diag(PD.kd).copy()


class FakeClock:
    """A clock the test moves by hand."""

    def __init__(self, now=0.0):
        self.now = now

    def __call__(self):
        return self.now


class ArmModel:
    """The simulated arm (or a distorted copy) dressed as an identified model."""

    def __init__(self, arm=ARM, case='torque', unit=1.0, poison=None):
        self.arm, self.case, self.unit, self.poison = arm, case, unit, poison
        self.n_joints = arm.n_joints
        self.kp, self.kd = KP, KD

    def inverse_dynamics(self, theta, theta_dot, theta_ddot):
        tau = self.arm.inverse_dynamics(theta, theta_dot, theta_ddot) / self.unit
        if self.poison is not None:
            tau = tau.copy()
            tau[..., 1] = self.poison
        return tau

    def controller_torque(self, theta, theta_dot, theta_d, theta_d_dot):
        return PD.torque(theta, theta_dot, theta_d, theta_d_dot) / self.unit


@pytest.fixture(scope='module')
def validation():
    """Return 3 s of held-out data (the newest validation samples) of the paper's arm."""
    return [simulate(ARM, PD, heldout_reference(N), 3.0, t0=10.0)]


def make_gate(clock, max_error=0.05, max_effort=(20.0, 10.0, 2.0), stale_after=0.5):
    gate = FeedforwardGate(GateSettings(max_error, np.array(max_effort), stale_after), clock)
    gate.data_received(clock())
    return gate


def test_the_true_model_passes_and_a_wrong_one_is_refused(validation):
    clock = FakeClock(10.0)
    gate = make_gate(clock)
    assert gate.status() == (False, 'no model assessed yet')
    verdict = gate.assess(ArmModel(), validation)
    assert verdict.passed and gate.on, verdict
    assert np.max(verdict.error) < 0.01 and verdict.samples >= 250
    # 30 % too heavy: the held-out torque error says so, and the gate switches off
    params = ArmParameters.paper()
    heavy = PlanarArm(replace(params, masses=1.3 * params.masses))
    verdict = gate.assess(ArmModel(heavy), validation)
    assert not verdict.passed and not gate.on
    assert 'exceeds max_error 0.05' in verdict.reason and 'held-out torque error' in verdict.reason
    assert gate.status() == (False, verdict.reason)
    # the known PD law stands for the torque in case 2
    assert gate.assess(ArmModel(case='pd_gains'), validation).passed and gate.on


def test_case_3_needs_a_torque_scale_fixed_by_a_measurement(validation):
    clock = FakeClock(10.0)
    gate = make_gate(clock)
    normalised = ArmModel(case='unknown', unit=2.5)     # the model's torque unit is 2.5 N m
    verdict = gate.assess(normalised, validation)
    assert not verdict.passed and 'not identifiable' in verdict.reason, verdict
    assert not gate.on
    scale = torque_scale_from_effort(normalised, validation)
    assert scale == pytest.approx(2.5, rel=1e-3)
    assert gate.assess(normalised, validation, torque_scale=scale).passed and gate.on
    assert gate.torque_scale == scale
    assert 'must be finite' in torque_scale_problem('unknown', float('nan'))
    assert 'would distort' in torque_scale_problem('torque', 2.0)
    assert torque_scale_problem('pd_gains', None) is None
    with pytest.raises(ValueError, match='no samples with measured effort'):
        torque_scale_from_effort(normalised, [replace(validation[0], tau=None)])


def test_a_diverged_or_non_finite_model_switches_off_at_once(validation):
    clock = FakeClock(10.0)
    gate = make_gate(clock)
    assert gate.assess(ArmModel(), validation).passed
    gate.model_diverged('the best model diverged on the newest data')
    assert gate.status() == (False, 'the best model diverged on the newest data')
    for poison in (np.nan, np.inf):
        verdict = gate.assess(ArmModel(poison=poison), validation)
        assert not verdict.passed and 'non-finite torque' in verdict.reason
    verdict = gate.assess(ArmModel(), validation, rollout_nrmse=float('inf'))
    assert not verdict.passed and 'diverges' in verdict.reason
    # a model whose plan turns non-finite after it passed: refused whole, gate off
    assert gate.assess(ArmModel(), validation).passed
    release = gate.release([10.0, 10.1], [[1.0, np.nan, 0.0], [1.0, 1.0, 0.0]])
    assert release.effort is None and 'non-finite' in release.reason and not gate.on


def test_too_little_or_unsuitable_validation_data_is_refused(validation):
    gate = make_gate(FakeClock(10.0))
    short = [validation[0].slice(0, 40)]
    verdict = gate.assess(ArmModel(), short)
    assert not verdict.passed and 'at least 50 are needed' in verdict.reason
    assert 'at least' in gate.assess(ArmModel(), []).reason
    no_torque = Dataset(validation[0].t, validation[0].theta, validation[0].theta_dot)
    assert 'no measured torque' in gate.assess(ArmModel(), [no_torque]).reason
    assert 'no desired trajectory' in gate.assess(ArmModel(case='pd_gains'), [no_torque]).reason
    assert 'joints' in gate.assess(ArmModel(PlanarArm(ArmParameters([1.0, 1.0], [0.1, 0.1]))),
                                   validation).reason


def test_stale_data_switches_off_until_the_gate_passes_again(validation):
    clock = FakeClock(10.0)
    gate = make_gate(clock, stale_after=0.5)
    assert gate.assess(ArmModel(), validation).passed
    clock.now = 10.4
    assert gate.on
    clock.now = 10.6                                      # 0.6 s without joint data
    on, reason = gate.status()
    assert not on and reason.startswith('stale: no joint data for 0.6 s')
    assert gate.release([11.0, 12.0], np.zeros((2, N))).effort is None
    gate.data_received(10.6)                              # data again: still off ...
    assert not gate.on
    assert gate.assess(ArmModel(), validation).passed and gate.on     # ... until it passes
    # the clock running backwards is not fresh data
    clock.now = 5.0
    on, reason = gate.status()
    assert not on and 'jumped back' in reason
    # passing while the data is stale does not switch on
    fresh = make_gate(FakeClock(0.0))
    fresh._clock.now = 3.0
    assert fresh.assess(ArmModel(), validation).passed and not fresh.on
    assert 'stale' in fresh.status()[1]


def test_release_clips_per_joint_and_refuses_an_ended_plan(validation):
    clock = FakeClock(10.0)
    gate = make_gate(clock, max_effort=(20.0, 10.0, 2.0))
    assert gate.assess(ArmModel(), validation).passed
    effort = np.array([[25.0, -3.0, 1.0], [-30.0, 12.0, -2.5], [1.0, 1.0, 1.0]])
    release = gate.release([10.0, 10.5, 11.0], effort)
    np.testing.assert_array_equal(release.effort, [[20.0, -3.0, 1.0], [-20.0, 10.0, -2.0],
                                                   [1.0, 1.0, 1.0]])
    assert release.clipped == 4 and release.reason == ''
    ended = gate.release([9.0, 9.5], effort[:2])
    assert ended.effort is None and 'ended' in ended.reason and gate.on
    wrong = gate.release([10.0, 10.5], effort[:2, :2])
    assert wrong.effort is None and 'expected' in wrong.reason


def test_settings_are_validated():
    for kwargs, reason in (({'max_error': 0.0}, 'max_error'),
                           ({'max_error': float('nan')}, 'max_error'),
                           ({'max_effort': np.array([1.0, -1.0])}, 'max_effort'),
                           ({'max_effort': np.array([1.0, np.inf])}, 'max_effort'),
                           ({'stale_after': -1.0}, 'stale_after'),
                           ({'min_samples': 0}, 'min_samples')):
        settings = {'max_error': 0.1, 'max_effort': np.array([1.0, 1.0]), 'stale_after': 0.5}
        settings.update(kwargs)
        with pytest.raises(ValueError, match=reason):
            GateSettings(**settings)
    assert GateSettings.for_joints(3, 0.1, 5.0, 0.5).max_effort.tolist() == [5.0] * 3
    with pytest.raises(ValueError, match='3 entries'):
        GateSettings.for_joints(3, 0.1, [5.0, 1.0], 0.5)


def test_no_nan_effort_whatever_the_model(validation):
    # random identified models (wide genomes: some give huge or non-finite torques), and
    # models that return NaN or inf: what leaves the gate is None or finite and clipped
    clock = FakeClock(10.0)
    data = simulate(ARM, PD, paper_reference(N), 2.0)
    t = np.arange(0.0, 2.0, 0.02) + 10.0
    theta_d, theta_d_dot = heldout_reference(N).evaluate(t)
    rng = np.random.default_rng(5)
    models = [ArmModel(poison=np.nan), ArmModel(poison=np.inf), ArmModel(poison=-np.inf)]
    for case, gains in (('torque', {}), ('pd_gains', {'kp': KP, 'kd': KD})):
        spec = NetworkSpec.recommended(N, case)
        scales = Scales.from_datasets([data], case, gains.get('kp'), gains.get('kd'))
        for sigma in (0.1, 3.0, 30.0):
            genome = spec.initial_genome() + sigma * rng.standard_normal(spec.genome_size)
            models.append(RKGNNModel(spec, scales, genome, **gains))
    limit = np.array([20.0, 10.0, 2.0])
    released = 0
    for model in models:
        gate = make_gate(clock, max_error=1e9, max_effort=limit)   # the error never refuses
        gate.assess(model, validation)
        with np.errstate(all='ignore'):
            effort = plan_feedforward(model, t, theta_d, theta_d_dot).effort
        release = gate.release(t, effort)
        if release.effort is not None:
            released += 1
            assert np.all(np.isfinite(release.effort))
            assert np.all(np.abs(release.effort) <= limit)
        else:
            assert release.reason
    assert released >= 3                     # the finite random models got through, clipped

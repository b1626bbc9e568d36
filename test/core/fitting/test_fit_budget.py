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
The offline fits keep their wall-time budgets and say when they have nothing better.

No test times a fit: the budget runs on an injected clock the test moves, or is 0, and
the assertions are about which stages ran.
"""

from dataclasses import replace
import math
import threading

import numpy as np
import pytest
from rkgnn_ros.core.fitting import global_fit
from rkgnn_ros.core.fitting.budget import Budget, process_age
from rkgnn_ros.core.fitting.fitness import FitnessProblem, Interrupted
from rkgnn_ros.core.fitting.identify import fit_best
from rkgnn_ros.core.fitting.offline import heldout_baselines, identify_offline, judge
from rkgnn_ros.core.fitting.online import OnlineIdentification, OnlineSettings
from rkgnn_ros.core.sim.plant import PDController, PlanarArm
from rkgnn_ros.core.sim.simulate import simulate
from rkgnn_ros.core.sim.trajectories import paper_reference
from rkgnn_ros.streams.buffer import StreamBuffer

JOINTS = ('joint1', 'joint2', 'joint3')


class Clock:
    """A clock that moves only when told."""

    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now


@pytest.fixture(scope='module')
def data():
    """5 s of the paper's arm under its PD, torque measured (case 1)."""
    return simulate(PlanarArm.paper(), PDController.paper(), paper_reference(3), 5.0,
                    rate=100.0, joint_names=JOINTS)


def test_a_budget_of_zero_returns_the_closed_form_at_once(data):
    result = fit_best(data, 'torque', time_budget=0.0)
    assert [h['phase'] for h in result.history] == ['linear']
    assert result.history[0].get('interrupted')      # not even scored
    assert result.generations == 0
    assert result.model.info['selected'] == 'linear'
    assert 'unscored' in result.model.info['warning']
    # it is the closed form: the model predicts the arm
    predicted = result.model.predict(data.slice(0, 101))
    assert np.all(np.isfinite(predicted))


def test_the_stages_stop_when_the_injected_clock_says_the_budget_is_spent(data):
    clock = Clock()

    def jump(entry):
        if entry['phase'] == 'lm':
            clock.now += 100.0    # the first LM stage took the whole budget
    result = fit_best(data, 'torque', time_budget=50.0, clock=clock, callback=jump,
                      shootings=(10, 0), lm_nfev=3)
    assert [h['phase'] for h in result.history] == ['linear', 'lm']
    assert result.generations == 0                    # CMA-ES never started
    assert result.wall_s == pytest.approx(100.0)
    assert result.model.info['selected'] in ('linear', 'lm')
    assert math.isfinite(result.model.info['validation_nrmse'])


def test_a_generation_that_would_not_fit_in_what_is_left_is_not_started(data):
    clock = Clock()

    def tick(entry):
        if entry['phase'] == 'cmaes':
            clock.now += 4.0      # every generation takes 4 s of the budget
    result = fit_best(data, 'torque', time_budget=10.0, clock=clock, callback=tick,
                      shootings=(), max_generations=100)
    # generations at 0-4 and 4-8 s; 2 s left is less than one generation
    assert result.generations == 2


def test_no_finite_cost_returns_the_closed_form_with_a_warning(data, monkeypatch):
    # before: ValueError('min() arg is an empty sequence') at the selection
    monkeypatch.setattr(global_fit.CoefficientProblem, 'cost',
                        lambda self, x: np.full(np.atleast_2d(x).shape[0], np.inf))
    result = fit_best(data, 'torque', time_budget=1e6, shootings=(), max_generations=2)
    assert result.model.info['selected'] == 'linear'
    assert 'every rollout diverged' in result.model.info['warning']
    assert result.final_cost == math.inf
    assert np.all(np.isfinite(result.model.genome))


def test_a_closed_form_that_cannot_be_fitted_is_a_clear_error(data):
    with pytest.raises(ValueError, match='fit_best: the closed-form fit .* too few samples'):
        fit_best([data.slice(0, 2)], 'torque', time_budget=10.0)
    with pytest.raises(ValueError, match='fit_best: no data'):
        fit_best([], 'torque')
    with pytest.raises(ValueError, match='time budget'):
        fit_best(data, 'torque', time_budget=float('nan'))


def test_the_rbf_pipeline_keeps_a_budget_of_zero(data):
    result = fit_best(data, 'torque', time_budget=0.0, basis='rbf')
    assert [h['phase'] for h in result.history] == ['budget']
    assert 'no stage had a finite cost' in result.model.info['warning']
    assert result.generations == 0


def test_a_spent_budget_interrupts_the_rollouts_of_its_thread(data):
    spec = global_fit.global_spec(3, 'torque')
    problem = FitnessProblem(spec, [data], substeps=2)
    population = np.tile(spec.initial_genome(), (3, 1))
    clock = Clock()
    budget = Budget(1.0, clock)
    out = {}

    def body():
        with budget.interrupting():
            out['before'] = problem.cost(population)     # within the budget
            clock.now = 2.0
            for name, call in (('cost', problem.cost), ('rollouts', problem.rollouts)):
                try:
                    call(population)
                except Interrupted:
                    out[name] = 'interrupted'
        out['after'] = problem.cost(population)          # outside: as before
    thread = threading.Thread(target=body)
    thread.start()
    thread.join()
    assert out['cost'] == out['rollouts'] == 'interrupted'
    np.testing.assert_array_equal(out['before'], out['after'])
    assert budget.spent() and budget.left() == 0.0
    assert Budget(float('inf')).left() == math.inf and not Budget(float('inf')).spent()


def capture_of(data):
    """Return a capture of ``data`` as the identifier's buffer holds it (case 1)."""
    buffer = StreamBuffer(JOINTS, 0.01, 20.0, 0.1, need_tau=True, need_desired=False)
    for k in range(data.n_samples):
        buffer.add_state(100.0 + data.t[k], data.theta[k], data.theta_dot[k], data.tau[k])
        buffer.add_command(100.0 + data.t[k], data.theta_d[k], data.theta_d_dot[k])
    return buffer.capture()


SETTINGS = OnlineSettings(case='torque', min_window=2.0, validation_fraction=0.2,
                          optimizer_settings={'population_size': 8}, seed=3)


def test_identify_offline_starts_no_step_the_last_one_says_would_not_fit(data, monkeypatch):
    clock = Clock()
    real = OnlineIdentification.step

    def four_seconds(self, obs):
        clock.now += 4.0          # every step takes 4 s of the budget
        return real(self, obs)
    monkeypatch.setattr(OnlineIdentification, 'step', four_seconds)
    result = identify_offline(SETTINGS, capture_of(data), JOINTS, budget_s=10.0, wall=clock)
    # steps at 0-4 and 4-8 s; the 2 s left are less than a step
    assert result.generations == 2 and result.seconds == pytest.approx(8.0)
    assert result.model is not None


def test_identify_offline_with_a_budget_of_zero_publishes_its_first_model(data):
    result = identify_offline(SETTINGS, capture_of(data), JOINTS, budget_s=0.0, wall=Clock())
    assert result.generations == 1 and result.model is not None


def test_a_model_is_judged_against_holding_the_state_and_following_the_reference(data):
    held = [data.slice(0, 201), data.slice(250, 451)]
    baselines = heldout_baselines(held)
    assert set(baselines) == {'hold_last_state', 'follow_reference'}
    # following a reference the servo tracks is better than standing still
    assert baselines['follow_reference'] < baselines['hold_last_state']
    worse = judge(2.0 * baselines['follow_reference'], baselines)
    assert worse.judged and worse.worse and worse.baseline == 'follow_reference'
    assert 'worse than follow reference' in worse.text
    better = judge(0.5 * baselines['follow_reference'], baselines)
    assert better.judged and not better.worse
    assert judge(math.inf, baselines).worse             # a diverged prediction
    assert not judge(math.nan, {}).judged               # nothing held out
    torque_only = [replace(seg, theta_d=None, theta_d_dot=None) for seg in held]
    assert set(heldout_baselines(torque_only)) == {'hold_last_state'}


def test_a_chunk_the_budget_has_no_time_for_is_not_started(data, monkeypatch):
    from rkgnn_ros.core.model import kernels
    spec = global_fit.global_spec(3, 'torque')
    problem = FitnessProblem(spec, [data], substeps=2)
    problem.seconds_per_candidate = 5.0     # what a rollout took before
    calls = []
    real = kernels.population_cost

    def counting(*args):
        calls.append(args[2].weights.shape[0])
        return real(*args)
    monkeypatch.setattr(kernels, 'population_cost', counting)
    clock = Clock()
    outer, inner = Budget(100.0, clock), Budget(4.0, clock)   # 4 s left of the inner one
    out = {}

    def body():
        with outer.interrupting(), inner.interrupting():
            try:
                problem.cost(spec.initial_genome()[None])
            except Interrupted:
                out['inner'] = 'interrupted'
        with outer.interrupting():
            out['outer'] = problem.cost(spec.initial_genome()[None])
    thread = threading.Thread(target=body)
    thread.start()
    thread.join()
    assert out['inner'] == 'interrupted' and calls[0] == 1 and len(calls) == 1
    assert out['outer'].shape == (1,)


def test_the_age_of_this_process_is_known_on_linux():
    import sys
    age = process_age()
    assert age > 0.0 if sys.platform.startswith('linux') else age == 0.0

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

"""The global network: closed form, coefficient map, refinement, selection (global_fit.py)."""

import math

import numpy as np
import pytest
from rkgnn_ros.core.fitting.fitness import FitnessProblem
from rkgnn_ros.core.fitting.global_fit import (coefficient_map, CoefficientProblem,
                                               global_spec, is_global, linear_fit,
                                               trig_table, variable_unit)
from rkgnn_ros.core.fitting.identify import fit_best
from rkgnn_ros.core.model.model import RKGNNModel
from rkgnn_ros.core.model.scales import Scales
from rkgnn_ros.core.model.spec import NetworkSpec
from rkgnn_ros.core.scoring import nrmse
from rkgnn_ros.core.sim.plant import PDController, PlanarArm
from rkgnn_ros.core.sim.simulate import simulate
from rkgnn_ros.core.sim.trajectories import hanging_pose, paper_reference, SumOfSines

ARM = PlanarArm.paper()
PD = PDController.paper()
KP, KD = np.diag(PD.kp), np.diag(PD.kd)
GAINS = {'torque': (None, None), 'pd_gains': (KP, KD), 'unknown': (None, None)}


def run(reference, duration, seed=0):
    data = simulate(ARM, PD, reference, duration + 1.0, rate=100.0, t0=-1.0, rng=seed)
    return data.slice(100, data.n_samples)


@pytest.fixture(scope='module')
def training():
    return run(paper_reference(3), 6.0)


@pytest.fixture(scope='module')
def heldout():
    """Motion about another pose, at other frequencies: nothing of it is in the training."""
    pose = hanging_pose(3) + np.array([0.6, -0.5, 0.6])
    ref = SumOfSines.random(3, np.random.default_rng(5), n_terms=4, amplitude=0.4,
                            min_frequency_hz=0.15, max_frequency_hz=0.7, offsets=pose)
    return run(ref, 4.0, seed=1)


def far_configurations(count=300, seed=3):
    return np.random.default_rng(seed).uniform(-np.pi, np.pi, (count, 3))


def test_global_spec_is_linear_in_a_trigonometric_basis():
    for case in ('torque', 'pd_gains', 'unknown'):
        spec = global_spec(3, case)
        assert is_global(spec) and spec.basis == 'trig' and spec.inertia == 'penalty'
        assert spec.velocity == 'christoffel' and spec.torque_units == 0
    assert is_global(global_spec(3, 'torque', 'trig+rbf'))
    assert not is_global(NetworkSpec.recommended(3, 'torque'))
    with pytest.raises(ValueError, match='trigonometric basis first'):
        global_spec(3, 'torque', 'rbf')


@pytest.mark.parametrize('case', ['torque', 'pd_gains', 'unknown'])
def test_the_mapped_genome_is_the_closed_form_model_everywhere(case, training):
    """The network of the mapped coefficients has the linear fit's M, G, F off the data too."""
    kp, kd = GAINS[case]
    spec = global_spec(3, case)
    table = trig_table(spec)
    arm = linear_fit([training], case, table, kp, kd)
    scales = Scales.from_datasets([training], case, kp, kd)
    cmap = coefficient_map(spec, scales, table, arm.layout_)
    model = RKGNNModel(spec, scales, cmap.genome(arm.full_coefficients), kp=kp, kd=kd)
    theta = far_configurations()
    rng = np.random.default_rng(4)
    theta_dot, theta_ddot = rng.normal(0, 2, theta.shape), rng.normal(0, 5, theta.shape)
    scale = np.abs(arm.inverse_dynamics(theta, theta_dot, theta_ddot)).max()
    np.testing.assert_allclose(model.inverse_dynamics(theta, theta_dot, theta_ddot),
                               arm.inverse_dynamics(theta, theta_dot, theta_ddot),
                               atol=1e-9 * scale)
    np.testing.assert_allclose(model.mass_matrix(theta), arm.raw_mass_matrix(theta),
                               atol=1e-9 * np.abs(arm.raw_mass_matrix(theta)).max())
    if case == 'unknown':
        # the scale is fixed by the mean Kp of the servo (only ratios are identifiable)
        implied_kp = model.implied_gains()[0]
        assert np.mean(implied_kp) == pytest.approx(1.0, rel=1e-6)
        np.testing.assert_allclose(implied_kp / implied_kp.mean(), KP / KP.mean(), rtol=0.05)


def test_a_basis_that_does_not_span_the_arm_is_refused(training):
    spec = global_spec(3, 'torque')
    scales = Scales.from_datasets([training], 'torque')
    wide = trig_table(global_spec(3, 'torque', 'trig3d'))      # modes the planar basis lacks
    arm = linear_fit([training], 'torque', wide)
    with pytest.raises(ValueError, match='does not span'):
        coefficient_map(spec, scales, wide, arm.layout_)


def test_the_coefficient_problem_is_the_network_problem(training):
    spec = global_spec(3, 'pd_gains')
    table = trig_table(spec)
    arm = linear_fit([training], 'pd_gains', table, KP, KD)
    scales = Scales.from_datasets([training], 'pd_gains', KP, KD)
    cmap = coefficient_map(spec, scales, table, arm.layout_)
    problem = FitnessProblem(spec, [training], scales=scales, substeps=4, kp=KP, kd=KD,
                             torque_interpolation='linear')
    coef = arm.full_coefficients
    unit = variable_unit(coef)
    wrapped = CoefficientProblem(problem, cmap, unit)
    x = np.vstack([coef / unit, 1.01 * coef / unit])
    np.testing.assert_array_equal(wrapped.cost(x), problem.cost(cmap.genomes(x * unit)))
    assert wrapped.cost(x)[0] < wrapped.cost(x)[1]


@pytest.mark.parametrize('case', ['torque', 'unknown'])
def test_fit_best_selects_on_validation_and_holds_far_from_the_data(case, training, heldout):
    kp, kd = GAINS[case]
    res = fit_best(training, case, time_budget=1e6, kp=kp, kd=kd, shootings=(10, 0),
                   lm_nfev=8, max_generations=3)
    model, hist = res.model, res.history
    assert is_global(model.spec)
    assert [h['phase'] for h in hist][:3] == ['linear', 'lm', 'lm']
    assert all(h['phase'] == 'cmaes' for h in hist[3:]) and len(hist) <= 6
    best = math.inf
    for h in hist:
        assert h['kept'] == (h['cost'] < best)
        best = min(best, h['cost'])
        assert h['best_cost'] == best
        assert ('validation_nrmse' in h) == h['kept']
    kept = [h for h in hist if h['kept']]
    chosen = min(kept, key=lambda h: h['validation_nrmse'])
    assert model.info['selected'] == chosen['phase']
    assert model.info['validation_nrmse'] == chosen['validation_nrmse']
    assert res.final_cost == chosen['cost'] <= hist[0]['cost']
    assert model.info['validation_s'] == pytest.approx(0.2 * training.duration, abs=0.02)
    # the refinement on rollouts beat the closed form on the held-out part
    assert model.info['validation_nrmse'] < hist[0]['validation_nrmse']
    # motion about another pose: within 2 % of the θ spread over 4 s of open loop
    assert nrmse(model.predict(heldout)[:, :3], heldout.theta) < 0.02
    # M symmetric positive definite far from any data
    mass = model.mass_matrix(far_configurations(seed=9))
    np.testing.assert_allclose(mass, np.swapaxes(mass, -1, -2), atol=1e-12)
    assert np.linalg.eigvalsh(mass)[:, 0].min() > 0.0


def test_fit_best_keeps_the_rbf_pipeline_on_request(training):
    res = fit_best(training, 'pd_gains', time_budget=1e6, kp=KP, kd=KD, basis='rbf',
                   shootings=(), equation_nfev=5, max_generations=1)
    assert res.model.spec.basis == 'rbf' and not is_global(res.model.spec)
    assert [h['phase'] for h in res.history] == ['start', 'equation', 'cmaes']

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

"""Case 3 online: the servo's gains from the linear closed-loop fit start the search."""

import numpy as np
import pytest
from rkgnn_ros.core.fitting.case_three import fit_gains, start_genome
from rkgnn_ros.core.fitting.identify import Evolution
from rkgnn_ros.core.model.model import RKGNNModel
from rkgnn_ros.core.model.spec import NetworkSpec
from rkgnn_ros.core.scoring import range_normalised_rmse
from rkgnn_ros.core.sim.plant import ArmParameters, PDController, PlanarArm
from rkgnn_ros.core.sim.sensors import SensorModel
from rkgnn_ros.core.sim.servo import Servo
from rkgnn_ros.core.sim.simulate import simulate
from rkgnn_ros.core.sim.trajectories import paper_reference

KP = np.array([32.84, 42.05, 42.31])
KD = np.array([42.44, 0.19, 4.86])
ARM = PlanarArm.paper()


def test_the_gains_ratios_and_a_start_that_predicts_the_closed_loop():
    servo = Servo(KP, KD, gravity='measured', arm=ARM)
    data = simulate(ARM, servo, paper_reference(3), 22.0, rate=100.0)
    train, test = data.slice(0, 1601), data
    kp, kd = fit_gains([train])
    np.testing.assert_allclose(kp / kp.mean(), KP / KP.mean(), rtol=0.03)
    e, de = train.theta_d - train.theta, train.theta_d_dot - train.theta_dot
    torque = np.mean(np.sqrt(np.mean((kp * e + kd * de) ** 2, axis=0)))
    assert torque == pytest.approx(1.0)   # the case-3 network's unit torque
    evo = Evolution(NetworkSpec.recommended(3, 'unknown'), [train], seed=0)
    start = start_genome(evo, [train], budget_s=600.0, nfev=100)  # bounded by evaluations
    assert start is not None and np.isfinite(start.cost)
    assert start.cost < float(evo.problem.cost(evo.optimizer.best_x[None])[0])
    model = RKGNNModel(evo.spec, evo.scales, start.genome)
    errors, follow = [], []
    for k in range(1650, 1950, 30):  # 2 s ahead on data the fit did not see
        states = model.simulate(test.state[k], test.t[k:k + 201],
                                theta_d=test.theta_d[k:k + 201],
                                theta_d_dot=test.theta_d_dot[k:k + 201])
        errors.append(states[-1, :3] - test.theta[k + 200])
        follow.append(test.theta_d[k + 200] - test.theta[k + 200])
    span = np.ptp(data.theta, axis=0)
    mine, theirs = range_normalised_rmse(errors, span), range_normalised_rmse(follow, span)
    assert mine < theirs / 3, (mine, theirs)


def test_gains_the_data_do_not_determine_are_not_given():
    noisy = simulate(ARM, Servo(KP, KD), paper_reference(3), 4.0, rate=100.0,
                     noise=SensorModel.differenced(1e-4), rng=3)
    assert fit_gains([noisy]) is None
    assert fit_gains([noisy.slice(0, 40)]) is None   # too short to fit at all


def test_the_gains_of_a_six_joint_servo():
    # the general trigonometric basis has 3,611 features at 6 joints (its fit held a UR5's
    # search for minutes); the gains come from the tied planar one there
    n = 6
    kp, kd = np.linspace(30.0, 50.0, n), np.linspace(6.0, 3.0, n)
    arm = PlanarArm(ArmParameters(masses=np.linspace(6.0, 2.0, n),
                                  lengths=np.linspace(0.3, 0.1, n),
                                  viscous=np.full(n, 0.3), coulomb=np.full(n, 0.1)))
    data = simulate(arm, PDController(kp, kd), paper_reference(n), 12.0, rate=100.0)
    fitted_kp, fitted_kd = fit_gains([data])
    scale = fitted_kp.mean()
    np.testing.assert_allclose(fitted_kp / scale, kp / kp.mean(), rtol=0.05)
    np.testing.assert_allclose(fitted_kd / scale, kd / kp.mean(), rtol=0.1)


def test_the_search_gains_place_the_arm_where_the_linear_gains_are_not_found(monkeypatch):
    # a spatial arm's closed loop is not the trigonometric fit's; the search's own linear
    # PD then takes the gains' place: the arm is fitted again under them
    from rkgnn_ros.core.fitting import case_three, search_starts
    servo = Servo(KP, KD, gravity='measured', arm=ARM)
    train = simulate(ARM, servo, paper_reference(3), 12.0, rate=100.0)
    evo = Evolution(NetworkSpec.recommended(3, 'unknown'), [train], seed=0)
    case_two = Evolution(NetworkSpec.recommended(3, 'pd_gains'), [train], seed=0, kp=KP, kd=KD)
    assert case_three.search_gains(case_two) is None  # the gains are known there
    scale = np.sqrt(np.mean((KP * (train.theta_d - train.theta)) ** 2))
    placed = start_genome(evo, [train], budget_s=600.0, nfev=60, gains=(KP / scale, KD / scale))
    assert placed is not None and "the search's gains" in placed.origin
    evo.optimizer.seed_best(placed.genome, placed.cost)
    kp, kd = case_three.search_gains(evo)
    np.testing.assert_allclose(kp, KP / scale, rtol=1e-9)
    np.testing.assert_allclose(kd, KD / scale, rtol=1e-9)
    monkeypatch.setattr(case_three, 'fit_gains', lambda segments: None)
    given, place = [], case_three.start_genome

    def spy(evo, train, budget_s, nfev, gains=None):
        given.append(gains)
        return place(evo, train, budget_s, nfev, gains)
    monkeypatch.setattr(case_three, 'start_genome', spy)
    before = float(evo.optimizer.best_cost)
    line = search_starts.rewarm(evo, [train], 12.0, budget_s=600.0, nfev=60)
    assert given[0] is None and len(given) == 2, given  # the linear gains, then the search's
    np.testing.assert_allclose(given[1][0], KP / scale, rtol=1e-9)
    assert float(evo.optimizer.best_cost) <= before, line

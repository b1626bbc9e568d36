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
The arm on the trigonometric basis closed with a servo law.

Case 1 (the law learned from the torque) and case 3 (arm and servo fitted together):
rollout, accuracy, when it holds.
"""

import copy
from dataclasses import replace

import numpy as np
import pytest
from rkgnn_ros.core.fitting.case_one import fit_law, LawKeeper
from rkgnn_ros.core.fitting.case_three import ArmKeeper
from rkgnn_ros.core.fitting.policy import (MAX_LOOP_ERROR, MIN_SEGMENT_SAMPLES, REFIT_S,
                                           RETRY_S, TRIG_FIRST_RETRY_S, TRIG_MAX_TORQUE_ERROR,
                                           TRIG_MIN_SAMPLES, TRIG_RETRY_S, YOUNG_DATA_S)
from rkgnn_ros.core.fitting.trig_loop import (closed_loop_error, fit_closed_trig_loop,
                                              fit_trig_loop, trig_torque_error)
from rkgnn_ros.core.fitting.validation import split_validation
from rkgnn_ros.core.integration.inputs import stage_inputs
from rkgnn_ros.core.sim.plant import PlanarArm
from rkgnn_ros.core.sim.sensors import SensorModel
from rkgnn_ros.core.sim.servo import Servo
from rkgnn_ros.core.sim.simulate import simulate
from rkgnn_ros.core.sim.trajectories import paper_reference

KP = np.array([32.84, 42.05, 42.31])
KD = np.array([42.44, 0.19, 4.86])
ARM = PlanarArm.paper()


def run(servo, seconds, noise=None):
    return simulate(ARM, servo, paper_reference(3), seconds, rate=100.0,
                    noise=noise or SensorModel.exact(), rng=3)


def ahead_error(loop, data, starts, fitted_until=None, steps=200):
    """
    Mean over starts of the 2 s-ahead θ RMSE / range, mean over joints.

    The law's integral term holds at sample ``fitted_until``; at a start it has grown by
    Ki ∫ (θd − θ) since, as the node carries it on.
    """
    span = data.theta.max(axis=0) - data.theta.min(axis=0)
    law, errors = loop.law, []
    for k in starts:
        integral = None
        if fitted_until is not None:
            e = data.theta_d[fitted_until:k + 1] - data.theta[fitted_until:k + 1]
            integral = law.integral_term + law.ki * np.trapezoid(e, dx=data.dt, axis=0)
        x0 = np.concatenate([data.theta[k], data.theta_dot[k]])
        states = loop.simulate(x0, data.t[k:k + steps + 1] - data.t[k],
                               data.theta_d[k:k + steps + 1], data.theta_d_dot[k:k + steps + 1],
                               integral)
        rmse = np.sqrt(np.mean((states[:, :3] - data.theta[k:k + steps + 1]) ** 2, axis=0))
        errors.append(np.mean(rmse / span))
    return float(np.mean(errors))


@pytest.fixture(scope='module')
def pd_data():
    return run(Servo(KP, KD), 30.0)


def test_the_compiled_rollout_is_the_numpy_models_closed_loop(pd_data):
    train = pd_data.slice(0, 1500)
    law = fit_law([train])
    loop = fit_trig_loop([train], [pd_data.slice(1500, 1800)], law)
    arm = copy.copy(loop.arm)                    # the numpy model with the law's gains
    arm.kp_, arm.kd_ = law.kp, law.kd
    k = 2000
    x0 = np.concatenate([pd_data.theta[k], pd_data.theta_dot[k]])
    t = pd_data.t[k:k + 101] - pd_data.t[k]
    shifted = pd_data.theta_d[k:k + 101] + law.shift(pd_data.theta_d[k:k + 101],
                                                     pd_data.theta_d_dot[k:k + 101])
    loop.substeps = 4
    mine = loop.simulate(x0, t, pd_data.theta_d[k:k + 101], pd_data.theta_d_dot[k:k + 101])
    theirs = arm.simulate(x0, t, theta_d=shifted, theta_d_dot=pd_data.theta_d_dot[k:k + 101],
                          substeps=4)
    np.testing.assert_allclose(mine, theirs, rtol=1e-7, atol=1e-9)


def test_theta_terms_on_the_measured_theta_are_evaluated_in_the_kernel():
    # a gravity compensation on the measured θ: the compiled rollout evaluates the law's
    # θ-terms at every stage; against RK4 in numpy on θ̈ = M⁻¹(law torque - V - G - F)
    data = run(Servo(KP, KD, gravity='measured', arm=ARM), 20.0)
    train = data.slice(0, 1500)
    law = fit_law([train], theta_input='measured')
    assert law.theta_input == 'measured' and law.theta_weights.size
    assert np.all(np.isinf(law.tau_limit))
    loop = fit_trig_loop([train], [data.slice(1500, 1800)], law)
    arm, reference = loop.arm, paper_reference(3)
    k, steps, substeps = 1600, 50, 20
    x0 = np.concatenate([data.theta[k], data.theta_dot[k]])
    t = data.t[k:k + steps + 1]
    theta_d, theta_d_dot = reference.evaluate(t)
    loop.substeps = substeps
    compiled = loop.simulate(x0, t - t[0], theta_d, theta_d_dot)

    # the commands at the stages as the kernel sees them (θd shifted by the law's constant)
    shifted = theta_d + law.shift(theta_d, theta_d_dot)
    u = stage_inputs('pd_gains', t, substeps, theta_d=shifted, theta_d_dot=theta_d_dot)

    def rate(command, x):
        tau = law.torque(x[:3], x[3:], command[:3], command[3:]) - law.kp * law.shift(
            theta_d_dot=command[3:])           # the constant is in the shifted θd already
        return np.concatenate([x[3:], arm.forward_dynamics(x[:3], x[3:], tau)])

    x, h, theirs = x0.copy(), (t[1] - t[0]) / substeps, [x0]
    for i in range(steps):
        for s in range(substeps):
            start, middle, end = u[i, s]
            k1 = rate(start, x)
            k2 = rate(middle, x + h / 2 * k1)
            k3 = rate(middle, x + h / 2 * k2)
            k4 = rate(end, x + h * k3)
            x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        theirs.append(x)
    np.testing.assert_allclose(compiled, np.array(theirs), rtol=0, atol=1e-8)


@pytest.mark.parametrize('servo,noise', [
    ('pd', None), ('pid', None), ('gravity', SensorModel.differenced(1e-4))])
def test_it_predicts_the_servo_far_better_than_following_the_reference(servo, noise):
    servos = {'pd': Servo(KP, KD), 'pid': Servo(KP, KD, ki=[20.0, 20.0, 20.0]),
              'gravity': Servo(KP, KD, gravity='measured', arm=ARM)}
    data = run(servos[servo], 30.0, noise)
    train, validation, _ = split_validation([data.slice(0, 2000)], 0.2)
    law = fit_law(train)
    loop = fit_trig_loop(train, validation, law)
    assert loop.torque_error <= TRIG_MAX_TORQUE_ERROR
    starts = range(2000, 2800, 50)
    span = data.theta.max(axis=0) - data.theta.min(axis=0)
    follow = np.mean([np.mean(np.sqrt(np.mean(
        (data.theta_d[k:k + 201] - data.theta[k:k + 201]) ** 2, axis=0)) / span)
        for k in starts])
    until = train[-1].n_samples - 1
    assert ahead_error(loop, data, starts, until) <= follow / 4


def test_the_keeper_predicts_with_it_only_where_the_basis_holds_the_arm(pd_data):
    keeper = LawKeeper()
    train = [pd_data.slice(0, 1500)]
    keeper.refit(train, 0.0, None)
    assert keeper.law is not None
    fraction = 300 / 1800    # the newest 300 samples held out
    ran, line = keeper.fit_trig([pd_data.slice(0, 1800)], fraction, 0.0)
    assert ran and keeper.trig is not None and 'trigonometric' in line[1]
    # a torque the arm's dynamics do not explain: a random torque added to the measured
    rng = np.random.default_rng(0)
    wrong = pd_data.slice(1500, 1800)
    wrong = replace(wrong, tau=wrong.tau + rng.normal(0.0, 3.0 * wrong.tau.std(axis=0),
                                                      wrong.tau.shape))
    ran, line = keeper.fit_trig(train + [wrong], fraction, 1.0)
    assert ran and keeper.trig is None and 'back' in line[1]
    # an arm it did not hold is fitted again 1 s later, then after 2, 4, ... at most
    # TRIG_RETRY_S: a spatial arm does not pay the fit at every refresh
    tried, wait = 1.0, TRIG_FIRST_RETRY_S
    for _ in range(6):
        assert keeper.fit_trig(train + [wrong], fraction, tried + 0.9 * wait) == (False, None)
        tried += wait
        assert keeper.fit_trig(train + [wrong], fraction, tried)[0] and keeper.trig is None
        wait = min(TRIG_RETRY_S, 2.0 * wait)
    assert wait == TRIG_RETRY_S


def test_the_keeper_retries_every_second_while_the_data_are_young(pd_data):
    # the first seconds of motion: a fit that does not hold is retried every
    # TRIG_FIRST_RETRY_S, not after a doubling wait, since each second of data helps it hold
    keeper = LawKeeper()
    keeper.refit([pd_data.slice(0, 1500)], 0.0, None)
    young = pd_data.slice(0, 800)
    assert young.t[-1] - young.t[0] < YOUNG_DATA_S
    rng = np.random.default_rng(1)
    wrong = [replace(young, tau=young.tau + rng.normal(0.0, 3.0 * young.tau.std(axis=0),
                                                       young.tau.shape))]
    fraction = 0.2
    for k in range(5):
        now = k * TRIG_FIRST_RETRY_S
        if k:
            assert keeper.fit_trig(wrong, fraction, now - 0.01) == (False, None)
        assert keeper.fit_trig(wrong, fraction, now)[0] and keeper.trig is None
    ran, line = keeper.fit_trig([young], fraction, 5 * TRIG_FIRST_RETRY_S)
    assert ran and keeper.trig is not None and 'trigonometric' in line[1]


def test_the_keeper_keeps_the_arm_in_use_while_it_explains_the_newest_data(pd_data):
    keeper = LawKeeper()
    keeper.refit([pd_data.slice(0, 1500)], 0.0, None)
    fraction = 300 / 1800
    assert keeper.fit_trig([pd_data.slice(0, 1800)], fraction, 0.0)[0]
    in_use = keeper.trig
    # a refit whose training torque is spoiled fails on the clean newest samples, which
    # the arm in use still explains: it stays, and nothing is logged
    rng = np.random.default_rng(2)
    older = pd_data.slice(0, 1500)
    spoiled = replace(older, tau=older.tau + rng.normal(0.0, 3.0 * older.tau.std(axis=0),
                                                        older.tau.shape))
    data = [spoiled, pd_data.slice(1500, 1800)]
    assert fit_trig_loop(*split_validation(data, fraction, 5)[:2], keeper.law).torque_error \
        > TRIG_MAX_TORQUE_ERROR  # the refit alone would not hold
    assert trig_torque_error(in_use, [pd_data.slice(1500, 1800)]) <= TRIG_MAX_TORQUE_ERROR
    assert keeper.fit_trig(data, fraction, 10.0) == (True, None)
    assert keeper.trig is in_use


def test_after_a_change_the_arm_fitted_since_stays_and_refits_come_at_every_call(pd_data):
    # the alternative to an arm fitted after a change is the model of the arm before it
    keeper = LawKeeper()
    keeper.refit([pd_data.slice(0, 1500)], 0.0, None)
    assert keeper.fit_trig([pd_data.slice(0, 1800)], 300 / 1800, 0.0)[0]
    rng = np.random.default_rng(3)
    young = pd_data.slice(0, 800)
    wrong = [replace(young, tau=young.tau + rng.normal(0.0, 3.0 * young.tau.std(axis=0),
                                                       young.tau.shape))]
    for now, after_change in ((10.0, True), (20.0, False)):
        keeper.changed()
        keeper.after_change = after_change      # False: the search published since
        assert keeper.trig is None
        ran, line = keeper.fit_trig([young], 0.2, now)
        in_use = keeper.trig
        assert ran and in_use is not None
        ran, line = keeper.fit_trig(wrong, 0.2, now + 0.1)   # neither the refit nor it holds
        assert ran and (keeper.trig is in_use) == after_change
        assert (line is None) == after_change
        # none in use: tried again at once after a change, after TRIG_FIRST_RETRY_S else
        keeper.trig = None
        assert keeper.fit_trig(wrong, 0.2, now + 0.2)[0] == after_change


def test_an_arm_that_holds_is_fitted_again_on_all_the_data(pd_data):
    # the newest samples judge the fit, then join it: after a change they are a fifth of
    # the few seconds there are
    keeper = LawKeeper()
    keeper.refit([pd_data.slice(0, 1500)], 0.0, None)
    data, fraction = [pd_data.slice(0, 1800)], 300 / 1800
    assert keeper.fit_trig(data, fraction, 0.0)[0]
    held = fit_trig_loop(*split_validation(data, fraction, MIN_SEGMENT_SAMPLES)[:2],
                         keeper.law)
    whole = fit_trig_loop(data, [], keeper.law)
    coefficients = keeper.trig.arm.full_coefficients
    np.testing.assert_allclose(coefficients, whole.arm.full_coefficients)
    assert not np.allclose(coefficients, held.arm.full_coefficients)
    assert keeper.trig.torque_error == held.torque_error <= TRIG_MAX_TORQUE_ERROR


def test_the_keeper_waits_for_enough_samples_without_starting_its_retry_clock(pd_data):
    keeper = LawKeeper()
    keeper.refit([pd_data.slice(0, 1500)], 0.0, None)
    few = pd_data.slice(0, TRIG_MIN_SAMPLES // 2)
    assert keeper.fit_trig([few], 0.2, 0.0) == (False, None)
    ran, line = keeper.fit_trig([pd_data.slice(0, 1800)], 300 / 1800, 0.1)   # at once
    assert ran and keeper.trig is not None and 'trigonometric' in line[1]


@pytest.mark.parametrize('servo,noise', [
    ('pd', SensorModel.differenced(1e-4)), ('pid', None), ('pid', SensorModel.differenced(1e-4)),
    ('gravity', SensorModel.differenced(1e-4))])
def test_case_three_fits_the_arm_and_its_servo_together(servo, noise):
    ki = 20.0
    servos = {'pd': Servo(KP, KD), 'pid': Servo(KP, KD, ki=[ki, ki, ki]),
              'gravity': Servo(KP, KD, gravity='measured', arm=ARM)}
    data = run(servos[servo], 30.0, noise)
    fitted = replace(data.slice(0, 2000), tau=None)     # case 3: no torque
    loop = fit_closed_trig_loop([fitted], 0.2)
    assert loop.torque_error <= MAX_LOOP_ERROR
    law = loop.law
    # the servo up to one factor: Kp's ratios, and Ki / Kp where there is an integral
    np.testing.assert_allclose(law.kp / law.kp.mean(), KP / KP.mean(), rtol=0.03)
    if servo == 'pid':
        np.testing.assert_allclose(law.ki / law.kp, ki / KP, rtol=0.05)
    else:
        assert np.all(law.ki == 0.0)
    starts = range(2000, 2800, 50)
    span = data.theta.max(axis=0) - data.theta.min(axis=0)
    follow = np.mean([np.mean(np.sqrt(np.mean(
        (data.theta_d[k:k + 201] - data.theta[k:k + 201]) ** 2, axis=0)) / span)
        for k in starts])
    assert ahead_error(loop, data, starts, 1999) <= follow / 4


def test_case_threes_keeper_predicts_only_while_the_loop_explains_held_out_data(pd_data):
    keeper = ArmKeeper()
    good = [replace(pd_data.slice(0, 1800), tau=None)]
    ran, line = keeper.fit(good, 0.2, 50.0, 0.0)
    assert ran and keeper.loop is not None and 'linear' in line[1]
    assert keeper.time == pytest.approx(50.0 + good[-1].t[-1])
    assert keeper.fit(good, 0.2, 50.0, REFIT_S - 0.1) == (False, None)   # not due yet
    # commands unrelated to the motion: no servo law explains it
    rng = np.random.default_rng(0)
    wrong = [replace(seg, theta_d=seg.theta_d + rng.normal(0.0, 0.5, seg.theta_d.shape))
             for seg in good]
    ran, line = keeper.fit(wrong, 0.2, 50.0, REFIT_S)
    assert ran and keeper.loop is None and 'back' in line[1]
    assert keeper.close(object()) is None
    # tried again RETRY_S later, then after twice as long
    assert keeper.fit(wrong, 0.2, 50.0, REFIT_S + RETRY_S - 0.1) == (False, None)
    assert keeper.fit(wrong, 0.2, 50.0, REFIT_S + RETRY_S) == (True, None)
    later = REFIT_S + RETRY_S + 2.0 * RETRY_S
    assert keeper.fit(good, 0.2, 50.0, later - 0.1) == (False, None)
    assert keeper.fit(good, 0.2, 50.0, later)[0] and keeper.loop is not None


def test_case_threes_keeper_retries_every_second_while_the_data_are_young(pd_data):
    # the first seconds of motion: a fit that does not hold is retried every RETRY_S, not
    # after a doubling wait, since each second more of data is what makes it hold
    young = [replace(pd_data.slice(0, 800), tau=None)]
    assert young[0].t[-1] - young[0].t[0] < YOUNG_DATA_S
    rng = np.random.default_rng(1)
    wrong = [replace(seg, theta_d=seg.theta_d + rng.normal(0.0, 0.5, seg.theta_d.shape))
             for seg in young]
    keeper = ArmKeeper()
    for k in range(4):
        assert keeper.fit(wrong, 0.2, 0.0, k * RETRY_S - 0.01 if k else 0.0)[0] == (k == 0)
        if k:
            assert keeper.fit(wrong, 0.2, 0.0, k * RETRY_S) == (True, None)
        assert keeper.loop is None
    assert keeper.fit(young, 0.2, 0.0, 4 * RETRY_S)[0] and keeper.loop is not None


def test_case_threes_keeper_keeps_the_loop_in_use_while_it_explains_the_newest_data(
        pd_data):
    keeper = ArmKeeper()
    good = [replace(pd_data.slice(0, 1800), tau=None)]
    assert keeper.fit(good, 0.2, 50.0, 0.0)[0] and keeper.loop is not None
    in_use = keeper.loop
    # a refit whose older commands are spoiled fails on the clean newest samples, which
    # the loop in use still explains: it stays (its integral moved on), nothing is logged
    rng = np.random.default_rng(4)
    older = replace(pd_data.slice(0, 1440), tau=None)
    spoiled = replace(older, theta_d=older.theta_d + rng.normal(0.0, 0.5, older.theta_d.shape))
    data = [spoiled, replace(pd_data.slice(1440, 1800), tau=None)]
    assert fit_closed_trig_loop(data, 0.2).torque_error > MAX_LOOP_ERROR  # alone: no
    assert closed_loop_error(in_use, data, 0.2) <= MAX_LOOP_ERROR
    assert keeper.fit(data, 0.2, 50.0, REFIT_S)[1] is None
    assert keeper.loop is in_use
    # newest samples it does not explain either: it goes
    wrong = [replace(seg, theta_d=seg.theta_d + rng.normal(0.0, 0.5, seg.theta_d.shape))
             for seg in good]
    assert closed_loop_error(in_use, wrong, 0.2) > MAX_LOOP_ERROR
    ran, line = keeper.fit(wrong, 0.2, 50.0, 2.0 * REFIT_S)
    assert ran and keeper.loop is None and 'loop in use' in line[1]


def test_case_threes_keeper_moves_the_integral_on_between_fits():
    data = run(Servo(KP, KD, ki=[20.0, 20.0, 20.0]), 24.0)
    data = replace(data, tau=None)
    keeper = ArmKeeper()
    assert keeper.fit([data.slice(0, 2000)], 0.2, 0.0, 0.0)[0]
    law = keeper.loop.law
    assert np.all(law.ki > 0.0) and keeper.time == pytest.approx(data.t[1999])
    # 2 s later (not due for a refit): the integral term grows by Ki ∫e over the new samples
    ran, line = keeper.fit([data.slice(0, 2200)], 0.2, 0.0, 1.0)
    assert ran and line is None and keeper.time == pytest.approx(data.t[2199])
    e = data.theta_d[2000:2200] - data.theta[2000:2200]
    np.testing.assert_allclose(keeper.loop.law.integral_term,
                               law.integral_term + law.ki * e.sum(axis=0) * data.dt)
    assert keeper.loop.arm is not None and keeper.loop.law.kp is law.kp


def test_the_closed_loop_keeps_what_the_memory_holds_when_the_arm_moves_little():
    # wide swings, then small motion about another pose: the loop fitted on the newest
    # window alone, or with samples of the swings (as the excitation memory keeps them)
    # beside it, predicts the swings of a third task
    from rkgnn_ros.core.differentiate import centred_derivative
    from rkgnn_ros.core.fitting.linear import samples_from_datasets
    from rkgnn_ros.core.sim.trajectories import hanging_pose, SumOfSines
    wide = run(Servo(KP, KD), 8.0)
    pose = hanging_pose(3) + np.array([1.0, -0.8, 0.8])
    small = simulate(ARM, Servo(KP, KD), SumOfSines.random(
        3, np.random.default_rng(12), n_terms=2, amplitude=0.05, min_frequency_hz=0.2,
        max_frequency_hz=0.5, offsets=pose), 10.0, rate=100.0, rng=1)
    third = simulate(ARM, Servo(KP, KD), SumOfSines.random(
        3, np.random.default_rng(11), n_terms=3, amplitude=0.5), 6.0, rate=100.0, rng=2)
    smooth = replace(wide, theta_dot=centred_derivative(wide.theta, wide.dt))
    prior = samples_from_datasets([smooth], 'unknown').take(slice(10, -10, 5))
    alone = fit_closed_trig_loop([small], 0.2)
    kept = fit_closed_trig_loop([small], 0.2, prior=prior)
    starts = range(0, 350, 50)
    with_memory, window_alone = ahead_error(kept, third, starts), ahead_error(alone, third, starts)
    assert with_memory < 0.005          # 0.11 % of the range here
    # the window alone diverges on the swings (NaN here), or is at least 5x worse
    assert not np.isfinite(window_alone) or window_alone > 5 * with_memory
    np.testing.assert_allclose(kept.law.kp / kept.law.kp.mean(), KP / KP.mean(), rtol=0.03)


def test_a_refit_with_gains_no_servo_has_keeps_the_law(pd_data, monkeypatch):
    # after a change of the dynamics the law is refitted on a few seconds: one that explains
    # the torque with a negative Kd is undetermined, not a servo that stopped explaining it
    # (the paper arm's release dropped its law so, and no model could predict)
    import rkgnn_ros.core.fitting.case_one as case_one
    keeper = LawKeeper()
    keeper.refit([pd_data.slice(0, 1500)], 0.0, None)
    law = keeper.law
    assert law is not None
    odd = replace(law, kd=-np.abs(law.kd), fit_ratio=np.full_like(law.fit_ratio, 0.001))
    monkeypatch.setattr(case_one, 'fit_law', lambda *args, **kwargs: odd)
    refit = keeper.refit([pd_data.slice(1500, 2100)], 15.0, None, after_change=True)
    assert refit.kind == 'keep' and refit.line is None and keeper.law is law
    # a law that no longer explains the torque still goes
    bad = replace(law, fit_ratio=np.full_like(law.fit_ratio, 0.5))
    monkeypatch.setattr(case_one, 'fit_law', lambda *args, **kwargs: bad)
    refit = keeper.refit([pd_data.slice(1500, 2100)], 15.0, None, after_change=True)
    assert refit.kind == 'changed' and keeper.law is None and 'no longer' in refit.line[1]

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

"""Servos as real arms run them: PD, gravity compensation, PID, torque limits."""

from dataclasses import replace

import numpy as np
import pytest
from rkgnn_ros.core.control.feedforward import plan_feedforward
from rkgnn_ros.core.sim.parameters import ArmParameters
from rkgnn_ros.core.sim.plant import PDController, PlanarArm
from rkgnn_ros.core.sim.servo import (FeedforwardTrack, Servo, servo_integral_rate_into,
                                      servo_torque_into)
from rkgnn_ros.core.sim.simulate import simulate
from rkgnn_ros.core.sim.trajectories import hanging_pose, paper_reference, SumOfSines

N = 3
ARM = PlanarArm.paper()
KP = np.array([32.84, 42.05, 42.31])
KD = np.array([42.44, 0.19, 4.86])


def hold(pose):
    """Return a constant reference at ``pose`` (n,)."""
    zeros = np.zeros((N, 1))
    return SumOfSines(pose, zeros, zeros, zeros)


def random_states(rng, count=50):
    theta = hanging_pose(N) + rng.uniform(-1.0, 1.0, (count, N))
    return (theta, rng.normal(0.0, 1.0, (count, N)), theta + rng.normal(0.0, 0.3, (count, N)),
            rng.normal(0.0, 1.0, (count, N)), rng.normal(0.0, 3.0, (count, N)))


def test_default_servo_is_the_papers_pd():
    rng = np.random.default_rng(0)
    theta, theta_dot, theta_d, theta_d_dot, _ = random_states(rng)
    servo = Servo.paper()
    assert servo.describe() == 'PD' and not servo.has_integral and not servo.limited
    np.testing.assert_allclose(servo.torque(theta, theta_dot, theta_d, theta_d_dot),
                               PDController.paper().torque(theta, theta_dot, theta_d,
                                                           theta_d_dot), rtol=1e-14)


@pytest.mark.parametrize('gravity', ['none', 'measured', 'desired'])
def test_compiled_servo_equals_numpy(gravity):
    rng = np.random.default_rng(1)
    servo = Servo(KP, KD, ki=[5.0, 0.0, 2.0], tau_limit=[8.0, np.inf, 1.5], gravity=gravity,
                  arm=ARM, windup_time=0.05)
    c = servo.constants()
    raw, out, rate = np.empty(N), np.empty(N), np.empty(N)
    for theta, theta_dot, theta_d, theta_d_dot, integral in zip(*random_states(rng)):
        servo_torque_into(c, theta, theta_dot, theta_d, theta_d_dot, integral, raw, out)
        expected_raw, expected = servo.torques(theta, theta_dot, theta_d, theta_d_dot, integral)
        np.testing.assert_allclose(raw, expected_raw, rtol=1e-13, atol=1e-12)
        np.testing.assert_allclose(out, expected, rtol=1e-13, atol=1e-12)
        servo_integral_rate_into(c, theta, theta_d, raw, out, rate)
        np.testing.assert_allclose(rate, servo.integral_rate(theta, theta_d, raw, out),
                                   rtol=1e-13, atol=1e-12)
    assert rate[1] == 0.0                      # no integral gain: the integral stays 0


def test_gravity_compensation_is_the_arms_own_gravity():
    rng = np.random.default_rng(2)
    theta, theta_dot, theta_d, theta_d_dot, _ = random_states(rng)
    pd = Servo(KP, KD).torque(theta, theta_dot, theta_d, theta_d_dot)
    on_theta = Servo(KP, KD, gravity='measured', arm=ARM)
    on_desired = Servo(KP, KD, gravity='desired', arm=ARM)
    np.testing.assert_allclose(on_theta.torque(theta, theta_dot, theta_d, theta_d_dot) - pd,
                               ARM.gravity_terms(theta), rtol=1e-12)
    np.testing.assert_allclose(on_desired.torque(theta, theta_dot, theta_d, theta_d_dot) - pd,
                               ARM.gravity_terms(theta_d), rtol=1e-12)


def test_gravity_compensation_tracks_better_and_records_its_torque():
    reference = paper_reference(N)
    pd = simulate(ARM, Servo(KP, KD), reference, 5.0)
    servo = Servo(KP, KD, gravity='measured', arm=ARM)
    comp = simulate(ARM, servo, reference, 5.0)
    rms = [np.sqrt(np.mean((d.theta_d - d.theta) ** 2, axis=0)) for d in (pd, comp)]
    assert np.all(rms[1] < 0.5 * rms[0]), rms
    np.testing.assert_allclose(comp.tau, servo.torque(comp.theta, comp.theta_dot, comp.theta_d,
                                                      comp.theta_d_dot), atol=1e-9)


@pytest.mark.parametrize('control_rate', [None, 1000.0])
def test_integral_term_removes_the_steady_state_error(control_rate):
    # held still away from the hanging pose, a PD sags by G / Kp; a PID does not
    pose = hanging_pose(N) + np.array([0.4, -0.3, 0.2])
    pd = simulate(ARM, Servo(KP, KD), hold(pose), 8.0, control_rate=control_rate)
    pid = simulate(ARM, Servo(KP, KD, ki=[40.0, 40.0, 40.0]), hold(pose), 8.0,
                   control_rate=control_rate)
    sag = np.abs(pd.theta[-1] - pose)
    expected = np.abs(np.linalg.solve(np.diag(KP), ARM.gravity_terms(pd.theta[-1])))
    np.testing.assert_allclose(sag, expected, rtol=0.05)
    # the integral time Kp / Ki is about 1 s, slowed by the coupling: 8 s leave 2 %
    assert np.linalg.norm(pid.theta[-1] - pose) < 0.05 * np.linalg.norm(sag)


@pytest.mark.parametrize('control_rate', [None, 1000.0])
def test_torque_limit_saturates_and_back_calculation_limits_the_overshoot(control_rate):
    # without gravity, a 0.5 rad step saturates every drive at first; an integral that
    # winds up meanwhile overshoots afterwards
    arm = PlanarArm(replace(ArmParameters.paper(), gravity=0.0))
    pose = np.full(N, 0.5)
    limit = np.array([4.0, 3.0, 1.0])
    overshoot = {}
    for windup_time in (0.05, 1e6):                        # 1e6 s: no anti-windup at all
        servo = Servo(KP, KD, ki=[20.0, 20.0, 20.0], tau_limit=limit, windup_time=windup_time)
        data = simulate(arm, servo, hold(pose), 4.0, x0=np.zeros(2 * N),
                        control_rate=control_rate)
        assert np.all(np.abs(data.tau) <= limit + 1e-12)
        assert np.all(np.isclose(np.abs(data.tau), limit, rtol=1e-12).sum(axis=0) >= 1)
        overshoot[windup_time] = np.max(data.theta - pose, axis=0)
    assert np.all(overshoot[1e6] > 0.03), overshoot       # wound up: overshoots
    assert np.all(overshoot[0.05] < 0.5 * overshoot[1e6]), overshoot


def test_invalid_servos_are_refused():
    with pytest.raises(ValueError, match='needs the arm'):
        Servo(KP, KD, gravity='measured')
    with pytest.raises(ValueError, match='gravity must be one of'):
        Servo(KP, KD, gravity='feedforward', arm=ARM)
    with pytest.raises(ValueError, match='kd must'):
        Servo(KP, [1.0, -1.0, 1.0])
    with pytest.raises(ValueError, match='tau_limit must be > 0'):
        Servo(KP, KD, tau_limit=[1.0, 0.0, 1.0])
    with pytest.raises(ValueError, match='windup_time'):
        Servo(KP, KD, ki=1.0, windup_time=0.0)
    with pytest.raises(ValueError, match='ki must'):
        Servo(KP, KD, ki=[np.nan, 0.0, 0.0])


# ----- the feed-forward input of a servo with an effort interface


def true_feedforward(reference, duration, spacing=0.02, arm=ARM):
    """Return the true arm's feed-forward along ``reference`` on points ``spacing`` apart."""
    t = np.arange(0.0, duration + spacing / 2, spacing)
    theta_d, theta_d_dot = reference.evaluate(t)
    return FeedforwardTrack(t, plan_feedforward(arm, t, theta_d, theta_d_dot).effort)


@pytest.mark.parametrize('gravity', ['none', 'desired'])
def test_compiled_servo_with_feedforward_equals_numpy(gravity):
    rng = np.random.default_rng(3)
    servo = Servo(KP, KD, ki=[5.0, 0.0, 2.0], tau_limit=[8.0, np.inf, 1.5], gravity=gravity,
                  arm=ARM)
    c = servo.constants()
    raw, out = np.empty(N), np.empty(N)
    saturated = 0
    for theta, theta_dot, theta_d, theta_d_dot, integral in zip(*random_states(rng)):
        ff = rng.normal(0.0, 4.0, N)
        servo_torque_into(c, theta, theta_dot, theta_d, theta_d_dot, integral, raw, out, ff)
        expected_raw, expected = servo.torques(theta, theta_dot, theta_d, theta_d_dot,
                                               integral, ff)
        np.testing.assert_allclose(raw, expected_raw, rtol=1e-13, atol=1e-12)
        np.testing.assert_allclose(out, expected, rtol=1e-13, atol=1e-12)
        # the feed-forward adds before saturation
        np.testing.assert_allclose(expected_raw - servo.torques(
            theta, theta_dot, theta_d, theta_d_dot, integral)[0], ff, rtol=1e-12, atol=1e-12)
        saturated += int(np.any(out != raw))
    assert saturated > 0                            # the limits were exercised


def test_feedforward_track_interpolates_like_a_trajectory_controller():
    t = np.array([1.0, 1.5, 2.5])
    effort = np.array([[0.0, 2.0], [1.0, -2.0], [3.0, 0.0]])
    track = FeedforwardTrack(t, effort)
    np.testing.assert_allclose(track.evaluate(1.25), [0.5, 0.0])
    np.testing.assert_allclose(track.evaluate(2.0), [2.0, -1.0])
    np.testing.assert_array_equal(track.evaluate(t), effort)
    # before the first point and after the last (stale): no feed-forward
    np.testing.assert_array_equal(track.evaluate(np.array([0.99, 2.51])), np.zeros((2, 2)))
    assert track.covers(2.5) and not track.covers(2.5001)
    assert track.evaluate(np.array([1.0, 2.0])).shape == (2, 2)


def test_malformed_feedforward_is_refused_with_the_reason():
    t = np.array([0.0, 0.1, 0.2])
    good = np.ones((3, N))
    cases = [
        ((t, np.where(np.eye(3, N, dtype=bool), np.nan, 1.0)), 'NaN or inf effort'),
        ((t, np.full((3, N), np.inf)), 'NaN or inf effort'),
        ((np.array([0.0, 0.2, 0.1]), good), 'strictly increasing'),
        ((np.array([0.0, np.nan, 0.2]), good), 'NaN or inf'),
        ((t[:1], good[:1]), 'at least 2 points'),
        ((t, good[:2]), 'shape'),
        ((t, 'abc'), 'not numeric'),
    ]
    for args, reason in cases:
        with pytest.raises(ValueError, match=reason):
            FeedforwardTrack(*args)
    with pytest.raises(ValueError, match='beyond its limit'):
        FeedforwardTrack(t, good * [1.0, 5.0, 1.0], tau_limit=[2.0, 4.0, 2.0])
    FeedforwardTrack(t, good, tau_limit=[2.0, 4.0, 2.0])      # within the limits


@pytest.mark.parametrize('control_rate', [None, 1000.0])
def test_simulated_servo_applies_the_feedforward_and_records_it(control_rate):
    reference = paper_reference(N)
    servo = Servo(KP, KD, gravity='desired', arm=ARM)
    track = true_feedforward(reference, 3.0)
    pd = simulate(ARM, servo, reference, 3.0, control_rate=control_rate)
    with_ff = simulate(ARM, Servo(KP, KD), reference, 3.0, control_rate=control_rate,
                       feedforward=track)
    rmse = [np.sqrt(np.mean((d.theta_d - d.theta) ** 2)) for d in (pd, with_ff)]
    # the true model's feed-forward leaves the PD almost nothing to correct, far less than
    # gravity compensation alone does
    assert rmse[1] < 0.01 * rmse[0], rmse
    # the recorded torque is the applied one, feed-forward included (every sample is a tick)
    feedforward = track.evaluate(with_ff.t)
    np.testing.assert_allclose(with_ff.tau, Servo(KP, KD).torque(
        with_ff.theta, with_ff.theta_dot, with_ff.theta_d, with_ff.theta_d_dot, None,
        feedforward), rtol=1e-12, atol=1e-9)
    assert np.max(np.abs(with_ff.tau - feedforward)) < 0.05 * np.max(np.abs(feedforward))


def test_ended_feedforward_leaves_the_servo_alone():
    reference = paper_reference(N)
    servo = Servo(KP, KD)
    ended = FeedforwardTrack(np.array([-2.0, -1.0]), np.full((2, N), 5.0))
    pd = simulate(ARM, servo, reference, 1.0)
    stale = simulate(ARM, servo, reference, 1.0, feedforward=ended)
    np.testing.assert_array_equal(stale.theta, pd.theta)
    np.testing.assert_array_equal(stale.tau, pd.tau)
    with pytest.raises(TypeError, match='needs a Servo'):
        simulate(ARM, PDController.paper(), reference, 1.0, feedforward=ended)
    with pytest.raises(ValueError, match='2 joints'):
        simulate(PlanarArm(ArmParameters([1.0, 1.0], [0.2, 0.2])), Servo([1.0, 1.0], [1.0, 1.0]),
                 paper_reference(2), 1.0, feedforward=ended)

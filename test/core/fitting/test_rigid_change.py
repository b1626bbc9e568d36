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

"""A described arm picks up a payload: the change is seen, the payload identified."""

import dataclasses
import math

import numpy as np
import pytest

pytest.importorskip('pinocchio')

from rkgnn_ros.core.fitting import rigid_change, rigid_online  # noqa: E402
from rkgnn_ros.core.fitting.change import Change, ChangeDetector  # noqa: E402
from rkgnn_ros.core.fitting.online import OnlineIdentification  # noqa: E402
from rkgnn_ros.core.fitting.online_records import (DynamicsChange, ModelUpdate,  # noqa: E402
                                                   Observation, OnlineSettings, PayloadEstimate)
from rkgnn_ros.core.fitting.rigid_change import fit_last_body, payload_of  # noqa: E402
from rkgnn_ros.core.fitting.rigid_change import point_mass_inertia  # noqa: E402
from rkgnn_ros.core.fitting.rigid_online import fit_rigid  # noqa: E402
from rkgnn_ros.core.rigid.structure import RigidStructure  # noqa: E402
from rkgnn_ros.core.sim.payload import with_payload  # noqa: E402
from rkgnn_ros.core.sim.servo import Servo  # noqa: E402
from rkgnn_ros.core.sim.simulate import simulate  # noqa: E402
from rkgnn_ros.core.sim.trajectories import SumOfSines  # noqa: E402
from rkgnn_ros.core.sim.urdf_arm import UrdfArm  # noqa: E402
from rkgnn_ros.streams.buffer import StreamBuffer  # noqa: E402

UR5 = 'example-robot-data:ur_description/urdf/ur5_robot.urdf'
KP = np.array([400.0, 400.0, 200.0, 40.0, 40.0, 10.0])
KD = np.array([40.0, 40.0, 20.0, 3.0, 3.0, 0.3])
HOME = np.array([0.0, -1.57, 1.57, -1.57, -1.57, 0.0])
AT, MASS, COM = 20.0, 3.0, np.array([0.0, 0.02, 0.05])
T0 = 1000.0


@pytest.fixture(scope='module')
def picked_up():
    """30 s of a UR5 under PD that picks up 3 kg at 20 s (its servo does not know)."""
    arm = UrdfArm(UR5, viscous=[2, 2, 1, 0.3, 0.3, 0.1], coulomb=[1, 1, 0.5, 0.2, 0.2, 0.05])
    servo = Servo(KP, KD)
    ref = SumOfSines.random(6, np.random.default_rng(1), n_terms=3, amplitude=0.5,
                            offsets=HOME)
    before = simulate(arm, servo, ref, AT, rate=100.0, joint_names=arm.joint_names)
    x0 = np.concatenate([before.theta[-1], before.theta_dot[-1]])
    after = simulate(with_payload(arm, MASS, COM), servo, ref, 10.0, rate=100.0, x0=x0,
                     t0=AT, joint_names=arm.joint_names)
    return RigidStructure(arm.urdf, arm.joint_names), before, after


def identify(picked_up, model_publish_period, until=29.9):
    """Return the online policy's events (arm's time, event) on the arm's data."""
    structure, before, after = picked_up
    joints = tuple(structure.joint_names)
    buffer = StreamBuffer(joints, 0.01, 20.0, 0.1, need_tau=True, need_desired=True)
    clock = [100.0]
    policy = OnlineIdentification(lambda: clock[0])
    cfg = OnlineSettings(case='torque', min_window=2.0, validation_fraction=0.2,
                         model_publish_period=model_publish_period)
    samples = [(d, k) for d in (before, after) for k in range(d.n_samples - (d is before))]
    events, fed = [], 0
    for step in range(int(until / 0.05)):
        now = step * 0.05                        # seconds of the arm's time
        while fed < len(samples) and samples[fed][0].t[samples[fed][1]] <= now:
            d, k = samples[fed]
            buffer.add_state(T0 + d.t[k], d.theta[k], d.theta_dot[k], d.tau[k])
            buffer.add_command(T0 + d.t[k], d.theta_d[k], d.theta_d_dot[k])
            fed += 1
        clock[0] = 100.0 + now
        obs = Observation(cfg, joints, {'state': clock[0], 'command': clock[0]},
                          structure=structure)
        if policy.data_due(obs):
            obs = obs._replace(data=buffer.capture())
        for event in policy.step(obs).events:
            events.append((now, event))
    return events


@pytest.fixture(scope='module')
def identified(picked_up):
    """Return the online policy's events on the 30 s, ~/model every 0.5 s at most."""
    return identify(picked_up, 0.5)


def test_a_payload_is_detected_within_a_second_and_identified(identified):
    events = identified
    changes = [(now, e) for now, e in events if isinstance(e, DynamicsChange)]
    assert len(changes) == 1, changes                 # no false alarm before, one after
    said_at, change = changes[0]
    assert AT - 0.05 <= change.time - T0 <= AT + 0.5 and said_at - AT <= 1.0
    assert 'shoulder_lift_joint' in change.joints
    payloads = [(now, e) for now, e in events if isinstance(e, PayloadEstimate)]
    assert payloads and payloads[0][0] - said_at <= 0.5   # refitted as soon as data suffice
    late = [e for now, e in payloads if now >= AT + 5.0]
    assert late, payloads
    assert late[-1].mass == pytest.approx(MASS, rel=0.05)
    assert np.linalg.norm(np.array(late[-1].com) - COM) <= 0.01
    # after 8 s of new data the whole model is refitted on them alone
    updates = [e for now, e in events if isinstance(e, ModelUpdate) and now >= AT + 8.5]
    assert updates and 'payload' not in updates[-1].model.info


def test_after_a_change_every_refit_of_the_last_body_goes_out(picked_up):
    # ~/model at most every 5 s, but after the change each refit of the last body (one a
    # second) is offered: the predictor judges each on the motion since the change
    events = identify(picked_up, 5.0, until=AT + 6.0)
    said_at = next(now for now, e in events if isinstance(e, DynamicsChange))
    refits = [now for now, e in events if isinstance(e, ModelUpdate) and now >= said_at
              and 'payload' in e.model.info]
    assert len(refits) >= 4 and refits[0] - said_at <= 1.0, refits


def test_the_refit_after_a_change_takes_no_row_from_before_it(picked_up, identified,
                                                              monkeypatch):
    # the onset is found on filtered rows, which rise before the change (here 0.04 s): rows
    # from 2 filter widths after it still held samples of the arm before; from 8, none
    def com_error(events):
        said = next(e.time - T0 for _, e in events if isinstance(e, DynamicsChange))
        assert AT - 0.1 <= said < AT
        payload = next(e for now, e in events
                       if isinstance(e, PayloadEstimate) and now >= AT + 1.5)
        return float(np.linalg.norm(np.array(payload.com) - COM))

    monkeypatch.setattr(rigid_online, 'CHANGE_MARGIN_SIGMAS', 2.0)
    assert com_error(identified) < 0.6 * com_error(identify(picked_up, 0.5, until=AT + 2.5))


def test_a_residual_at_its_normal_level_is_no_change():
    detector = ChangeDetector()
    detector.set_normal([0.1, 0.2], [10.0, 10.0])
    rng = np.random.default_rng(0)
    for block in range(200):
        times = block + np.arange(20) * 0.05
        residual = rng.normal(0.0, [0.1, 0.2], (20, 2)) * 2.0   # twice as bad: new motion
        assert detector.check(residual, times) is None
    jump = rng.normal(0.0, [0.1, 0.2], (20, 2))
    jump[8:, 1] += 5.0
    change = detector.check(jump, 300.0 + np.arange(20) * 0.05)
    assert change is not None and change.joints == (1,)
    assert change.time == pytest.approx(300.4)


def test_a_change_at_the_end_of_a_late_check_is_not_averaged_away():
    # a check that came 3 s late (the worker was busy with a fit): the change is in its
    # last 0.15 s, its residual 20 times the normal level; over the 3 s it averages to less
    # than the alarm, in its own block it passes it
    detector = ChangeDetector()
    detector.set_normal([0.1], [10.0])
    rng = np.random.default_rng(3)
    times = 50.0 + np.arange(300) * 0.01
    residual = rng.normal(0.0, 0.1, (300, 1))
    residual[285:, 0] += 2.0
    assert np.mean((residual / 0.1) ** 2) < 25.0
    assert detector.check(residual, times) is None       # a suspect: the next block says
    assert detector.suspect is not None
    change = detector.check(rng.normal(0.0, 0.1, (25, 1)) + 2.0, 53.0 + np.arange(25) * 0.01)
    assert change is not None and change.joints == (0,)
    assert change.time == pytest.approx(52.85, abs=0.02)


def test_a_refit_that_took_in_the_start_of_a_change_cannot_hide_it():
    # a refit's held-out residual five times the level before (its newest data held the
    # first samples of a change): the level rises only twice, and the change still shows
    detector = ChangeDetector()
    detector.set_normal([0.1, 0.1], [10.0, 10.0])
    detector.set_normal([0.5, 0.1], [10.0, 10.0])
    assert detector.level == pytest.approx([0.2, 0.1])
    detector.set_normal([0.05, 0.05], [10.0, 10.0])        # a better fit lowers it at once
    assert detector.level == pytest.approx([0.1, 0.1])
    rng = np.random.default_rng(4)
    residual = rng.normal(0.0, 0.1, (50, 2))
    residual[:, 0] += 2.0
    assert detector.check(residual, 10.0 + np.arange(50) * 0.01).joints == (0,)


def test_one_block_over_the_alarm_is_a_suspect_the_next_one_clears():
    detector = ChangeDetector()
    detector.set_normal([0.1], [10.0])
    rng = np.random.default_rng(6)
    spike = rng.normal(0.0, 0.1, (25, 1))
    spike[10:15, 0] += 1.5                         # one block's statistic over 25, alone
    assert detector.check(spike, 20.0 + np.arange(25) * 0.01) is None
    assert detector.suspect is not None
    assert detector.check(rng.normal(0.0, 0.1, (25, 1)), 20.25 + np.arange(25) * 0.01) is None
    assert detector.suspect is None


def _blocks_at(detector, z, start, rng):
    """Check one 0.25 s block of 25 samples whose normalised residual has RMS ``z``."""
    residual = rng.normal(0.0, 0.1, (25, 1))
    residual *= z / np.sqrt(np.mean((residual / 0.1) ** 2))
    return detector.check(residual, start + np.arange(25) * 0.01)


def test_a_burst_of_the_residual_is_no_change_a_lasting_rise_is():
    # a model's residual comes in bursts: three blocks at 40, 160 and 60 times its normal
    # square (evidence 1.6 * 6.4 * 2.4 = 25) are no change; a rise of 40 times that lasts
    # is one, after enough blocks (1.6 ** 10 > 100), at the first block of its run
    detector = ChangeDetector()
    detector.set_normal([0.1], [10.0])
    rng = np.random.default_rng(8)
    t = 10.0
    for square in (1.0, 40.0, 160.0, 60.0, 1.0, 1.0):
        assert _blocks_at(detector, math.sqrt(square), t, rng) is None
        t += 0.25
    assert detector.suspect is None
    declared = None
    for block in range(20):
        declared = _blocks_at(detector, math.sqrt(40.0), t + 0.25 * block, rng)
        if declared is not None:
            break
    assert declared is not None and block == 9 and declared.joints == (0,)
    assert t - 0.01 <= declared.time <= t + 0.25


def test_a_large_change_is_declared_on_its_second_block_a_huge_one_on_its_first():
    detector = ChangeDetector()
    detector.set_normal([0.1, 0.1], [10.0, 10.0])
    rng = np.random.default_rng(9)
    residual = rng.normal(0.0, 0.1, (75, 2))
    residual[25:, 1] += 3.0                       # 900 times the normal square
    assert detector.check(residual[:25], 5.0 + np.arange(25) * 0.01) is None
    assert detector.check(residual[25:50], 5.25 + np.arange(25) * 0.01) is None
    assert detector.suspect is not None           # one block: a suspect
    change = detector.check(residual[50:], 5.5 + np.arange(25) * 0.01)
    assert change is not None and change.joints == (1,)
    assert change.time == pytest.approx(5.25, abs=0.015)
    # a block alone 40,000 times the normal square (evidence 1,600) is a change at once
    again = ChangeDetector()
    again.set_normal([0.1, 0.1], [10.0, 10.0])
    jump = rng.normal(0.0, 0.1, (50, 2))
    jump[25:, 0] += 20.0
    assert again.check(jump[:25], 8.0 + np.arange(25) * 0.01) is None
    change = again.check(jump[25:], 8.25 + np.arange(25) * 0.01)
    assert change is not None and change.joints == (0,)
    assert change.time == pytest.approx(8.25, abs=0.015)


def test_no_refit_while_a_suspect_waits_for_its_confirmation(picked_up):
    structure, before, _ = picked_up
    joints = tuple(structure.joint_names)
    buffer = StreamBuffer(joints, 0.01, 20.0, 0.1, need_tau=True, need_desired=True)
    for k in range(before.n_samples):
        buffer.add_state(T0 + before.t[k], before.theta[k], before.theta_dot[k], before.tau[k])
        buffer.add_command(T0 + before.t[k], before.theta_d[k], before.theta_d_dot[k])
    clock = [200.0]
    policy = OnlineIdentification(lambda: clock[0])
    cfg = OnlineSettings(case='torque', min_window=2.0, validation_fraction=0.2)

    def step():
        clock[0] += 1.5          # a refit is due at every step
        obs = Observation(cfg, joints, {'state': clock[0], 'command': clock[0]},
                          structure=structure)
        policy.step(obs._replace(data=buffer.capture()))
        return policy._rigid.keeper

    keeper = step()
    refits = keeper.refits
    assert refits >= 1
    keeper.detector.suspect = Change(T0 + 19.0, (1,), np.zeros(len(joints)))
    keeper.detector.last_time = math.inf          # nothing new to judge: it stays a suspect
    assert step().refits == refits
    keeper.detector.suspect = None
    assert step().refits == refits + 1


def test_the_first_payload_fit_takes_its_filter_support_from_before_the_change(picked_up):
    # noisy encoders need a wide filter (here 0.08 s): cut at the change, 0.8 s of data
    # leave too few rows; with the support before it, the rows after it are fitted at once
    from rkgnn_ros.core.data import Dataset
    from rkgnn_ros.core.fitting.rigid_change import fit_last_body, payload_of
    from rkgnn_ros.core.fitting.rigid_fit import fit_torque
    structure, before, after = picked_up
    arm = fit_torque(structure, [before.slice(0, 1500)], [before.slice(1500, 1999)]).arm
    m = before.n_samples - 1
    both = Dataset(*(np.concatenate([getattr(before, f)[:m], getattr(after, f)])
                     for f in ('t', 'theta', 'theta_dot')),
                   tau=np.concatenate([before.tau[:m], after.tau]))
    k = int(np.searchsorted(both.t, AT + 0.05))
    assert fit_last_body(arm, None, [both.slice(k, k + 80)], 0.08) is None
    refit = fit_last_body(arm, None, [both.slice(k - 40, k + 80)], 0.08, start=both.t[k])
    assert refit is not None
    assert payload_of(arm, refit)['mass'] == pytest.approx(MASS, rel=0.15)


def test_changes_are_judged_with_the_fit_that_armed_the_detector(picked_up):
    from rkgnn_ros.core.fitting import rigid_online
    from rkgnn_ros.core.fitting.change import ChangeDetector
    from rkgnn_ros.core.fitting.rigid_fit import RigidArm, RigidFit
    from rkgnn_ros.core.rigid.kernels import N_INERTIAL
    structure, before, _ = picked_up
    keeper = rigid_online.RigidKeeper(structure, 'torque')
    keeper.refresh('torque', [before.slice(0, 1500)], 0.2, T0, T0 + 15.0)
    good = keeper.armed
    assert good is keeper.fit and keeper.detector.level is not None
    # a refit that fits worse (here the tip body 2 kg heavier) does not arm the detector
    parameters = good.arm.parameters.copy()
    parameters[N_INERTIAL * (structure.n_joints - 1)] += 2.0
    worse = RigidFit(RigidArm(structure, parameters, dict(good.arm.info)), None,
                     good.errors * 10.0, good.samples)
    assert rigid_online._arms(good, None) and not rigid_online._arms(worse, good)
    assert rigid_online._arms(good._replace(errors=good.errors * 1.5), good)
    keeper.fit = worse                     # the newest fit; the armed one still judges
    assert keeper.check([before], T0) is None
    # judged with the worse fit against the good fit's level, the same data are a change
    keeper.armed, keeper.detector = worse, ChangeDetector()
    keeper.detector.set_normal(good.arm.info['residual_rms'], good.arm.info['torque_spread'])
    assert keeper.check([before], T0) is not None


def test_a_point_mass_prior_sharpens_the_first_moment_of_a_payload(picked_up, monkeypatch):
    # encoders with 1e-4 rad of noise, θ̇ by differences: the last body refitted on 1 s
    # after the pick-up; the change of its inertia pulled towards a point mass's lowers the
    # error of the payload's centre of mass (without: its inertia takes some of the signal)
    structure, before, after = picked_up
    rng = np.random.default_rng(0)

    def noisy(data):
        theta = data.theta + rng.normal(0.0, 1e-4, data.theta.shape)
        return dataclasses.replace(data, theta=theta,
                                   theta_dot=np.gradient(theta, data.t, axis=0))

    before, after = noisy(before), noisy(after)
    arm = fit_rigid([before], 'torque', structure).arm

    def com_error():
        refit = fit_last_body(arm, None, [after.slice(0, 100)], 0.02, AT)
        payload = payload_of(arm, refit)
        assert payload['mass'] == pytest.approx(MASS, rel=0.02)
        return float(np.linalg.norm(np.array(payload['com']) - COM))

    with_prior = com_error()
    monkeypatch.setattr(rigid_change, 'POINT_MASS_PASSES', 0)
    without = com_error()
    assert with_prior < 0.7 * without, (with_prior, without)


def test_a_point_mass_has_no_inertia_about_its_centre():
    mass, com = 2.5, np.array([0.01, -0.03, 0.08])
    inertia = point_mass_inertia(mass, mass * com)
    expected = mass * (com @ com * np.eye(3) - np.outer(com, com))
    assert inertia == pytest.approx(expected[[0, 1, 2, 0, 0, 1], [0, 1, 2, 1, 2, 2]])
    assert point_mass_inertia(-mass, -mass * com) == pytest.approx(-inertia)   # taken away

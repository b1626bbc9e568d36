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

"""The chain learned online: gathered, fitted in the background, handed over or refused."""

import os
import threading
import time

import numpy as np
import pytest

from rkgnn_ros.core.data import Dataset
from rkgnn_ros.core.fitting import chain_online
from rkgnn_ros.core.fitting.chain_fit import ChainSettings
from rkgnn_ros.core.fitting.chain_online import ChainLearner
from rkgnn_ros.core.rigid.chain import axis_errors, Chain, ChainStructure
from test_chain import arm_chain, bodies, dataset

NAMES = ('a', 'b', 'c')
#: small and seeded: the 3-joint chain is found in seconds
SETTINGS = ChainSettings(refine_blocks=40, block_length=8, max_starts=20, seed=1,
                         joint_iterations=40, refine_iterations=30)
T0 = 1000.0


def at_once(run):
    """Run the learner's fit now, in a thread of its own (its nice must not stay with pytest)."""
    thread = threading.Thread(target=run)
    thread.start()
    thread.join()


def arm_data(seconds=12.0, seed=12):
    data = dataset(ChainStructure(arm_chain()), bodies(3, np.random.default_rng(11)),
                   seconds, seed)
    return Dataset(data.t, data.theta, data.theta_dot, tau=data.tau, joint_names=NAMES)


def captures(data, window=5.0, every=1.0):
    """Yield (segments, origin) as a buffer of ``window`` s shows ``data`` every ``every`` s."""
    end = every
    while end <= data.t[-1] + 1e-9:
        keep = (data.t > end - window - 1e-9) & (data.t <= end + 1e-9)
        idx = np.flatnonzero(keep)
        yield [data.slice(idx[0], idx[-1] + 1)], T0
        end += every


def test_overlapping_captures_are_gathered_once_on_one_grid():
    data = arm_data(12.0)
    learner = ChainLearner(SETTINGS, at_once, min_data_s=100.0)
    for segments, origin in captures(data):
        learner.feed(NAMES, segments, origin)
    assert len(learner._segments) == 1
    gathered = learner._segments[0]
    assert abs(learner.gathered_s - 11.0) < 1e-9      # the last capture ends at 11 s
    np.testing.assert_allclose(gathered.t, data.t[:gathered.n_samples], atol=1e-9)
    np.testing.assert_allclose(gathered.theta, data.theta[:gathered.n_samples])
    np.testing.assert_allclose(gathered.tau, data.tau[:gathered.n_samples])
    # too few joints, or another joint list: nothing kept, or afresh
    assert not learner.wants_data(('a', 'b'))
    learner.feed(('x', 'y', 'z'), [data.slice(0, 50)], T0)
    assert learner.gathered_s < 1.0


def test_the_learner_hands_over_the_chain_of_a_small_arm():
    data = arm_data(12.0)
    learner = ChainLearner(SETTINGS, at_once, min_data_s=10.0)
    lines = []
    for segments, origin in captures(data):
        learner.feed(NAMES, segments, origin)
        lines += learner.poll('torque')
    lines += learner.poll('torque')
    assert learner.structure is not None, lines
    assert 'learning the chain' in lines[0][1]
    assert lines[-1][0] == 'info' and 'identified from now on' in lines[-1][1]
    structure = learner.structure
    assert structure.joint_names == NAMES
    assert axis_errors(structure.chain, arm_chain())['aligned_deg_max'] < 1.0
    assert learner.error < 0.05
    assert set(structure.report) >= {'chain', 'determinacy', 'held_out_errors', 'data_s'}
    assert not learner.wants_data(NAMES) and learner.poll('torque') == []


def test_the_learner_refuses_garbage_and_tries_again_later():
    data = arm_data(12.0)
    rng = np.random.default_rng(3)
    noise = Dataset(data.t, data.theta, data.theta_dot,
                    tau=rng.normal(0.0, 1.0, data.tau.shape), joint_names=NAMES)
    settings = ChainSettings(refine_blocks=20, block_length=8, max_starts=4, seed=1,
                             joint_iterations=5, refine_iterations=5, time_budget=20.0)
    learner = ChainLearner(settings, at_once, min_data_s=10.0)
    lines = []
    for segments, origin in captures(noise):
        learner.feed(NAMES, segments, origin)
        lines += learner.poll('torque')
    lines += learner.poll('torque')
    assert learner.structure is None
    assert lines[-1][0] == 'warning' and 'not used' in lines[-1][1], lines
    assert learner.wants_data(NAMES)        # a refusal: more data, another try later
    # a case whose data were not gathered (torque gathered, case 3 asked) starts no fit
    other = ChainLearner(settings, at_once, min_data_s=1.0)
    other.feed(NAMES, [data], T0)
    assert other.poll('unknown') == [] and not other.running


def test_the_fit_runs_in_the_background_at_low_priority(monkeypatch):
    release, seen = threading.Event(), {}

    def slow_fit(train, validation, settings, names, log, case='torque'):
        seen['nice'] = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
        seen['thread'] = threading.current_thread().name
        release.wait(30.0)
        log('search: done')            # a stage boundary: a cancelled fit ends here
        return None

    monkeypatch.setattr(chain_online, 'fit_chain', slow_fit)
    learner = ChainLearner(SETTINGS, min_data_s=5.0)
    learner.feed(NAMES, [arm_data(6.0)], T0)
    began = time.monotonic()
    lines = learner.poll('torque')
    for _ in range(5):
        lines += learner.poll('torque')
    assert time.monotonic() - began < 1.0           # poll never waits for the fit
    assert learner.running and len(lines) == 1
    release.set()
    job = learner._job
    assert job.done.wait(10.0)
    assert seen['thread'] == 'rkgnn_chain_learner'
    assert seen['nice'] == chain_online.FIT_NICE
    lines = learner.poll('torque')
    assert not learner.running and 'too few data' in lines[0][1]


def held_fit(monkeypatch):
    """Make the chain fit wait for the returned event, then end at its next stage line."""
    release = threading.Event()

    def slow_fit(train, validation, settings, names, log, case='torque'):
        release.wait(30.0)
        log('search: done')
        raise AssertionError('not reached: the stage line ends a cancelled fit')

    monkeypatch.setattr(chain_online, 'fit_chain', slow_fit)
    return release


def test_a_reset_abandons_the_running_fit(monkeypatch):
    release = held_fit(monkeypatch)
    learner = ChainLearner(SETTINGS, min_data_s=5.0)
    learner.feed(NAMES, [arm_data(6.0)], T0)
    learner.poll('torque')
    job = learner._job
    learner.reset()
    release.set()
    assert job.done.wait(10.0) and job.error == 'abandoned'
    assert learner.poll('torque') == [] and learner.structure is None


@pytest.fixture(scope='module')
def servoed():
    """12 s of the 3-joint chain under a PD servo, simulated on its own URDF."""
    pytest.importorskip('pinocchio')
    from rkgnn_ros.core.rigid.urdf_out import identified_urdf
    from rkgnn_ros.core.sim.servo import Servo
    from rkgnn_ros.core.sim.simulate import simulate
    from rkgnn_ros.core.sim.trajectories import SumOfSines
    from rkgnn_ros.core.sim.urdf_arm import UrdfArm
    truth = ChainStructure(arm_chain(), NAMES)
    parameters = bodies(3, np.random.default_rng(11))
    parameters[30:] = 0.0       # no rotor inertia, friction or offsets: a plain URDF
    arm = UrdfArm(identified_urdf(truth, parameters, 'test arm'), list(NAMES))
    servo = Servo(np.array([80.0, 80.0, 40.0]), np.array([8.0, 8.0, 4.0]))
    reference = SumOfSines.random(3, np.random.default_rng(1), n_terms=3, amplitude=0.5)
    return simulate(arm, servo, reference, 14.0, rate=100.0, joint_names=NAMES)


def stream(policy, now, data, cfg, steps):
    """
    Step ``policy`` ``steps`` times, 0.5 s apart on the clock list ``now``; return results.

    ``data`` reaches a buffer as the arm streams it (effort only in case 'torque').
    """
    from rkgnn_ros.core.fitting.online_records import Observation
    from rkgnn_ros.streams.buffer import StreamBuffer
    effort = cfg.case == 'torque'
    buffer = StreamBuffer(NAMES, 0.01, 20.0, 0.1, need_tau=effort, need_desired=True)
    results, k = [], 0
    for _ in range(steps):
        now[0] += 0.5
        while k < data.n_samples and data.t[k] <= now[0] - 100.0:
            buffer.add_state(T0 + data.t[k], data.theta[k], data.theta_dot[k],
                             data.tau[k] if effort else None)
            buffer.add_command(T0 + data.t[k], data.theta_d[k], data.theta_d_dot[k])
            k += 1
        obs = Observation(cfg, NAMES, {'state': now[0], 'command': now[0]})
        if policy.data_due(obs):
            obs = obs._replace(data=buffer.capture())
        results.append(policy.step(obs))
    return results


def test_the_policy_hands_the_learned_chain_to_the_rigid_body_policy(servoed):
    from rkgnn_ros.core.fitting.online import OnlineIdentification
    from rkgnn_ros.core.fitting.online_records import ModelUpdate, OnlineSettings
    from rkgnn_ros.core.fitting.rigid_model import RigidModel
    data = servoed
    now = [100.0]
    learner = ChainLearner(SETTINGS, at_once, min_data_s=10.0)
    policy = OnlineIdentification(lambda: now[0], chain_learner=learner)
    # no search is built in this test (min_window beyond the data): the chain alone
    cfg = OnlineSettings(case='torque', min_window=100.0, validation_fraction=0.2,
                         model_publish_period=0.5)
    policy._changes.since = T0 + 1.5   # a change the search saw: the rigid body starts there
    results = stream(policy, now, data, cfg, 40)
    assert not any(result.ran for result in results)
    events = [e for result in results for e in result.events]
    texts = [getattr(e, 'text', '') for e in events]
    assert any('identified from now on' in t for t in texts), texts
    updates = [e for e in events if isinstance(e, ModelUpdate)]
    assert updates, texts
    model = updates[-1].model
    assert isinstance(model, RigidModel) and model.arm.structure is learner.structure
    assert 'learned_chain' in model.info and model.info['held_out_error'] < 0.05
    assert updates[-1].loop is not None            # closed with the learned servo law
    assert any('rigid-body model of the learned chain predicts' in t for t in texts), texts
    assert policy._rigid.keeper.since == T0 + 1.5
    assert model.info['window_s'] <= data.t[-1] - 1.5 + 1e-6


def test_fit_best_and_identify_bag_learn_the_chain_when_asked(monkeypatch):
    from rkgnn_ros.core.fitting.identify import fit_best
    from rkgnn_ros.core.fitting.rigid_model import RigidModel
    quick = chain_online.learn_chain
    monkeypatch.setattr(chain_online, 'learn_chain',
                        lambda *args, **kw: quick(*args, settings=SETTINGS, **kw))
    result = fit_best([arm_data(12.0)], 'torque', learn_chain=True)
    assert result.history[0]['phase'] == 'chain' and result.history[0]['accepted']
    assert isinstance(result.model, RigidModel)
    assert 'learned_chain' in result.model.info and result.final_cost < 0.05
    # garbage: refused, the usual pipeline runs
    rng = np.random.default_rng(3)
    data = arm_data(12.0)
    noise = Dataset(data.t, data.theta, data.theta_dot,
                    tau=rng.normal(0.0, 1.0, data.tau.shape), joint_names=NAMES)
    assert quick([noise], NAMES, ChainSettings(
        refine_blocks=20, block_length=8, max_starts=4, seed=1, joint_iterations=5,
        refine_iterations=5)) is None


@pytest.mark.parametrize('learning', [True, False])
def test_no_generation_runs_while_the_fit_does(learning):
    from rkgnn_ros.core.fitting.online import OnlineIdentification
    from rkgnn_ros.core.fitting.online_records import Observation, OnlineSettings
    from rkgnn_ros.streams.buffer import StreamBuffer
    data = arm_data(8.0)
    buffer = StreamBuffer(NAMES, 0.01, 20.0, 0.1, need_tau=True, need_desired=False)
    for k in range(data.n_samples):
        buffer.add_state(T0 + data.t[k], data.theta[k], data.theta_dot[k], data.tau[k])
    now = [100.0]
    # a fit that never ends (its thread is never started), or no learner at all
    learner = ChainLearner(SETTINGS, lambda run: None, min_data_s=3.0, enabled=learning)
    policy = OnlineIdentification(lambda: now[0], chain_learner=learner,
                                  warm_start_seconds=0.5, warm_start_nfev=20)
    cfg = OnlineSettings(case='torque', min_window=2.0, validation_fraction=0.2,
                         model_publish_period=0.5, network={'basis': 'rbf'})
    ran, texts = [], []
    for _ in range(6):
        now[0] += 0.5
        obs = Observation(cfg, NAMES, {'state': now[0]})
        if policy.data_due(obs):
            obs = obs._replace(data=buffer.capture())
        result = policy.step(obs)
        ran.append(result.ran)
        texts += [getattr(e, 'text', '') for e in result.events]
    assert learner.running == learning
    assert any(ran) != learning, texts


def test_identify_bag_learns_the_chain_when_asked(servoed, tmp_path, capsys, monkeypatch):
    import yaml
    from bag_helpers import write_run
    from rkgnn_ros.identify_bag import main
    quick = chain_online.learn_chain
    monkeypatch.setattr(chain_online, 'learn_chain',
                        lambda *args, **kw: quick(*args, settings=SETTINGS, **kw))
    write_run(tmp_path / 'bag', servoed, names=NAMES)
    code = main([str(tmp_path / 'bag'), '--out', str(tmp_path / 'out'), '--heldout', '3',
                 '--learn-chain', '--budget', '60', '--quiet'])
    err = capsys.readouterr().err
    assert code == 0, err
    model = yaml.safe_load((tmp_path / 'out' / 'model.yaml').read_text())
    assert model['kind'] == 'rigid_body' and model['case'] == 'torque'
    assert model['source'] == 'the chain learned from joint data'
    assert len(model['info']['learned_chain']['chain']['modified_dh']['alpha_deg']) == 3


def test_a_change_of_the_dynamics_abandons_the_fit_and_drops_the_data_before_it(monkeypatch):
    # a payload picked up at 8 s: a chain fitted on both arms' torque fits neither; the fit
    # running on them is abandoned (not an attempt) and the next waits for 5 s after it
    release = held_fit(monkeypatch)
    learner = ChainLearner(SETTINGS, at_once, min_data_s=5.0)
    learner._spawn = lambda run: threading.Thread(target=run, daemon=True).start()
    data = arm_data(12.0)
    learner.feed(NAMES, [data.slice(0, 600)], T0)          # 6 s
    assert learner.poll('torque') and learner.running
    job = learner._job
    learner.changed(T0 + 4.0)
    release.set()
    assert job.done.wait(10.0) and job.error == 'abandoned'
    assert not learner.running and learner._attempts == 0
    assert abs(learner.gathered_s - 2.0) < 0.02              # only what came after 4 s
    assert learner.poll('torque') == []                      # 2 s of 5 after the change
    learner.feed(NAMES, [data.slice(0, 1000)], T0)         # 10 s: 6 s after the change
    assert learner.poll('torque') and learner.running
    assert min(seg.t[0] for seg in learner._job.train) >= 4.0 - 1e-9


def tilted_chain(degrees=25.0) -> Chain:
    """Return the 3-joint chain with its second axis turned by ``degrees`` about x."""
    chain = arm_chain()
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    axis = chain.axis.copy()
    axis[1] = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]]) @ axis[1]
    return chain._replace(axis=axis)


def test_a_description_is_checked_against_the_chain_the_data_show():
    from rkgnn_ros.offline.description_check import check_description
    data = arm_data(12.0)
    learned = ChainStructure(arm_chain(), NAMES)            # as a learner would find it
    right = check_description(ChainStructure(arm_chain(), NAMES), learned, [data], 0.25)
    assert right['fits_data'] and 'fits the data' in right['text']
    assert right['axis_deg_max'] < 1e-6 and right['description_error'] < 0.02
    wrong = check_description(ChainStructure(tilted_chain(), NAMES), learned, [data], 0.25)
    assert not wrong['fits_data'] and 'does not fit' in wrong['text']
    assert abs(wrong['axis_deg_max'] - 25.0) < 10.0
    assert wrong['description_error'] > 2.0 * wrong['learned_error']
    # no held-out part: no check rather than a made-up one
    assert check_description(learned, learned, [data], 0.0) is None


def test_identify_bag_checks_a_wrong_description_when_asked(servoed, tmp_path, capsys,
                                                            monkeypatch):
    import json
    from bag_helpers import write_run
    from rkgnn_ros.identify_bag import main
    quick = chain_online.learn_chain
    monkeypatch.setattr(chain_online, 'learn_chain',
                        lambda *args, **kw: quick(*args, settings=SETTINGS, **kw))
    write_run(tmp_path / 'bag', servoed, names=NAMES)
    wrong = ChainStructure(tilted_chain(), NAMES).urdf
    code = main([str(tmp_path / 'bag'), '--out', str(tmp_path / 'out'), '--heldout', '3',
                 '--learn-chain', '--robot-description', wrong, '--budget', '60'])
    out = capsys.readouterr().out
    assert code in (0, 3), out
    report = json.loads((tmp_path / 'out' / 'report.json').read_text())
    check = report['description_check']
    assert check is not None and not check['fits_data'], out
    assert 'description check' in out and 'does not fit' in out
    assert 'checked against the data' in (tmp_path / 'out' / 'report.md').read_text()


def test_an_accepted_chain_that_stops_explaining_the_torque_is_learned_again():
    from types import SimpleNamespace
    learner = ChainLearner(SETTINGS, at_once, min_data_s=10.0)
    learner.feed(NAMES, [arm_data(3.0)], T0)
    learner.structure = ChainStructure(arm_chain(), NAMES)      # as if accepted
    fit = SimpleNamespace(error=0.5)
    for _ in range(chain_online.REJUDGE_REFITS - 1):
        assert learner.judge_in_use(SimpleNamespace(error=0.5)) == []
    assert learner.judge_in_use(fit) != []      # the REJUDGE_REFITS-th in a row
    assert learner.structure is None and learner.wants_data(NAMES)
    assert learner.gathered_s == 0.0            # learned again from new data
    # the same fit twice counts once; a good refit starts the count again
    learner.structure = ChainStructure(arm_chain(), NAMES)
    bad = chain_online.REJUDGE_REFITS - 1
    for _ in range(3):
        for _ in range(bad):
            assert learner.judge_in_use(SimpleNamespace(error=0.5)) == []
        assert learner.judge_in_use(SimpleNamespace(error=0.01)) == []
    for _ in range(bad):
        assert learner.judge_in_use(fit) == []      # counted once
    assert learner.structure is not None


def test_the_policy_drops_a_wrong_chain_its_refits_cannot_fit(servoed):
    from rkgnn_ros.core.fitting.online import OnlineIdentification
    from rkgnn_ros.core.fitting.online_records import OnlineSettings
    now = [100.0]
    learner = ChainLearner(SETTINGS, at_once, min_data_s=1000.0)
    learner._joints = NAMES
    learner.structure = ChainStructure(tilted_chain(60.0), NAMES)   # as if accepted
    policy = OnlineIdentification(lambda: now[0], chain_learner=learner)
    cfg = OnlineSettings(case='torque', min_window=100.0, validation_fraction=0.2,
                         model_publish_period=0.5)
    texts = [getattr(e, 'text', '') for result in stream(policy, now, servoed, cfg, 28)
             for e in result.events]
    assert any('no longer explains the torque' in t for t in texts), texts
    assert learner.structure is None and learner.wants_data(NAMES)


def test_with_known_gains_and_no_torque_the_chain_is_learned_from_the_servos_torque(servoed):
    from rkgnn_ros.core.fitting.online import OnlineIdentification
    from rkgnn_ros.core.fitting.online_records import ModelUpdate, OnlineSettings
    from rkgnn_ros.core.fitting.rigid_model import RigidModel
    now = [100.0]
    learner = ChainLearner(SETTINGS, at_once, min_data_s=10.0)
    policy = OnlineIdentification(lambda: now[0], chain_learner=learner)
    cfg = OnlineSettings(case='pd_gains', kp=(80.0, 80.0, 40.0), kd=(8.0, 8.0, 4.0),
                         min_window=100.0, validation_fraction=0.2, model_publish_period=0.5)
    events = [e for result in stream(policy, now, servoed, cfg, 40) for e in result.events]
    texts = [getattr(e, 'text', '') for e in events]
    assert any('identified from now on' in t for t in texts), texts
    assert axis_errors(learner.structure.chain, arm_chain())['aligned_deg_max'] < 2.0
    updates = [e for e in events if isinstance(e, ModelUpdate)]
    model = updates[-1].model
    assert isinstance(model, RigidModel) and model.arm.structure is learner.structure
    assert model.case == 'pd_gains' and updates[-1].loop is not None


def test_with_nothing_known_about_the_servo_the_chain_is_learned_with_its_gains(servoed):
    # case 3: no effort, no gains: the chain and the gains' ratios from θ, θd alone
    from rkgnn_ros.core.fitting.online import OnlineIdentification
    from rkgnn_ros.core.fitting.online_records import ModelUpdate, OnlineSettings
    from rkgnn_ros.core.fitting.rigid_model import RigidModel
    now = [100.0]
    learner = ChainLearner(SETTINGS, at_once, min_data_s=10.0)
    policy = OnlineIdentification(lambda: now[0], chain_learner=learner)
    cfg = OnlineSettings(case='unknown', min_window=100.0, validation_fraction=0.2,
                         model_publish_period=0.5)
    events = [e for result in stream(policy, now, servoed, cfg, 40) for e in result.events]
    texts = [getattr(e, 'text', '') for e in events]
    assert any('closed-loop equation error' in t and 'identified from now on' in t
               for t in texts), texts
    assert axis_errors(learner.structure.chain, arm_chain())['aligned_deg_max'] < 2.0
    updates = [e for e in events if isinstance(e, ModelUpdate)]
    model = updates[-1].model
    assert isinstance(model, RigidModel) and model.arm.structure is learner.structure
    assert model.case == 'unknown' and updates[-1].loop is not None
    kp = updates[-1].loop.loop.law.kp
    np.testing.assert_allclose(kp / kp.mean(), np.array([80.0, 80.0, 40.0]) / 200.0 * 3,
                               rtol=0.05)


def test_the_servos_torque_of_known_gains():
    from rkgnn_ros.core.fitting.chain_online import servo_torque
    data = arm_data(2.0)
    paired = Dataset(data.t, data.theta, data.theta_dot, theta_d=data.theta + 0.1,
                     theta_d_dot=data.theta_dot - 0.2, joint_names=NAMES)
    out, = servo_torque([paired, data], [10.0, 20.0, 30.0], [1.0, 2.0, 3.0])  # data: no θd
    np.testing.assert_allclose(out.tau, np.tile([10 * 0.1 - 0.2, 2.0 - 0.4, 3.0 - 0.6],
                                                (data.n_samples, 1)))
    assert servo_torque([paired], [10.0, 20.0], [1.0, 2.0]) == []


@pytest.mark.parametrize('case', ['pd_gains', 'unknown'])
def test_identify_bag_learns_the_chain_without_effort(servoed, tmp_path, capsys, monkeypatch,
                                                      case):
    # the known gains in a params file (case 2), or nothing about the servo (case 3)
    import yaml
    from bag_helpers import write_run
    from rkgnn_ros.identify_bag import main
    quick = chain_online.learn_chain
    monkeypatch.setattr(chain_online, 'learn_chain',
                        lambda *args, **kw: quick(*args, settings=SETTINGS, **kw))
    write_run(tmp_path / 'bag', servoed, names=NAMES, effort=False)
    extra = []
    if case == 'pd_gains':
        params = tmp_path / 'gains.yaml'
        params.write_text("/**:\n  ros__parameters:\n    case: 'pd_gains'\n"
                          '    kp: [80.0, 80.0, 40.0]\n    kd: [8.0, 8.0, 4.0]\n')
        extra = ['--params-file', str(params)]
    code = main([str(tmp_path / 'bag'), '--out', str(tmp_path / 'out'), '--heldout', '3',
                 *extra, '--learn-chain', '--budget', '60', '--quiet'])
    err = capsys.readouterr().err
    assert code == 0, err
    model = yaml.safe_load((tmp_path / 'out' / 'model.yaml').read_text())
    assert model['kind'] == 'rigid_body' and model['case'] == case
    assert model['source'] == 'the chain learned from joint data'


def test_fit_best_learns_the_chain_with_nothing_known_about_the_servo(servoed, monkeypatch):
    from rkgnn_ros.core.fitting.identify import fit_best
    from rkgnn_ros.core.fitting.rigid_model import RigidModel
    quick = chain_online.learn_chain
    monkeypatch.setattr(chain_online, 'learn_chain',
                        lambda *args, **kw: quick(*args, settings=SETTINGS, **kw))
    data = Dataset(servoed.t, servoed.theta, servoed.theta_dot, theta_d=servoed.theta_d,
                   theta_d_dot=servoed.theta_d_dot, joint_names=NAMES)
    result = fit_best([data], 'unknown', learn_chain=True)
    assert result.history[0]['phase'] == 'chain' and result.history[0]['accepted']
    assert isinstance(result.model, RigidModel) and result.model.case == 'unknown'
    assert 'learned_chain' in result.model.info and result.final_cost < 0.05


def test_each_case_takes_only_segments_with_every_signal_it_needs(monkeypatch):
    # one rule (chain_fit.case_signals) for the learner, learn_chain and the fit: case
    # 'unknown' needs θd and θ̇d; a recording with θd but no θ̇d is not handed to the fit
    from rkgnn_ros.core.fitting.chain_fit import case_signals
    data = arm_data(6.0)
    plan = Dataset(data.t, data.theta, data.theta_dot, theta_d=data.theta,
                   joint_names=NAMES)                   # θd, no θ̇d
    assert case_signals(data, 'torque') is not None and case_signals(data, 'unknown') is None
    assert case_signals(plan, 'unknown') is None and case_signals(plan, 'torque') is None
    fits = []
    monkeypatch.setattr(chain_online, 'fit_chain', lambda *args: fits.append(args))
    assert chain_online.learn_chain([plan], case='unknown') is None
    assert not fits
    learner = ChainLearner(SETTINGS, at_once, min_data_s=100.0)
    learner.feed(NAMES, [plan], T0, case='unknown')
    assert learner.gathered_s == 0.0

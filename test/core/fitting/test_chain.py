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

"""A chain without a robot description: its Tree, its numbers, its symmetries, its recovery."""

import math

import numpy as np
import pytest

from rkgnn_ros.core.data import Dataset
from rkgnn_ros.core.fitting.chain_fit import ChainSettings, fit_chain
from rkgnn_ros.core.fitting.chain_rows import block_rows, ChainScore, torque_weights
from rkgnn_ros.core.fitting.chain_search import ChainCoding, determinacy, refine, turn_axes
from rkgnn_ros.core.rigid import consistency
from rkgnn_ros.core.rigid.chain import (axis_errors, Chain, chain_urdf, ChainStructure,
                                        dh_of_lines, from_dh, lines)

# a 3-joint arm: a vertical base joint, a shoulder across it 0.1 m up, an elbow 0.3 m on
ALPHA = [0.0, math.pi / 2, 0.2]
A = [0.0, 0.05, 0.3]
OFFSET = [0.0, 0.4, 0.0]
D = [0.0, 0.1, 0.0]
GRAVITY = [0.0, 0.0, -9.81]


def arm_chain(gravity=GRAVITY) -> Chain:
    return from_dh(ALPHA, A, OFFSET, D, gravity)


def bodies(n, rng):
    """Return full parameters of realizable bodies with friction, rotor inertia, offsets."""
    phi = np.zeros((n, 10))
    phi[:, 0] = 0.5 * np.log(rng.uniform(1.0, 4.0, n))
    phi[:, 1:4] = np.log(rng.uniform(0.03, 0.08, (n, 3)))
    phi[:, 4:7] = rng.normal(0.0, 0.01, (n, 3))
    phi[:, 7:10] = rng.normal(0.0, 0.1, (n, 3))
    joint = np.column_stack([rng.uniform(0.01, 0.05, n), rng.uniform(0.1, 0.5, n),
                             rng.uniform(0.1, 0.3, n), rng.normal(0.0, 0.1, n)])
    return np.concatenate([consistency.parameters(phi).reshape(-1), joint.reshape(-1)])


def motion(n, duration, seed, rate=100.0, centre=0.0):
    """Return t and θ, θ̇, θ̈ of sums of sines (exact derivatives)."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, duration, 1.0 / rate)
    amp = rng.uniform(0.2, 0.5, (3, n))
    freq = 2 * np.pi * rng.uniform(0.2, 0.9, (3, n))
    phase = rng.uniform(0.0, 2 * np.pi, (3, n))
    arg = t[:, None, None] * freq + phase
    theta = centre + np.sum(amp * np.sin(arg), axis=1)
    theta_dot = np.sum(amp * freq * np.cos(arg), axis=1)
    theta_ddot = -np.sum(amp * freq ** 2 * np.sin(arg), axis=1)
    return t, theta, theta_dot, theta_ddot


def dataset(structure, parameters, duration, seed, centre=0.0):
    t, q, qd, qdd = motion(structure.n_joints, duration, seed, centre=centre)
    tau = structure.inverse_dynamics(parameters, q, qd, qdd)
    return Dataset(t, q, qd, tau=tau)


def mirrored(chain: Chain) -> Chain:
    """Return the mirror image through the base's x-z plane, every axis turned."""
    axes, points = lines(chain)
    s = np.diag([1.0, -1.0, 1.0])
    return dh_of_lines(-(axes @ s), points @ s, s @ chain.gravity).chain()


def test_the_chain_tree_matches_pinocchio_on_the_chains_own_urdf():
    pytest.importorskip('pinocchio')
    from rkgnn_ros.core.rigid.structure import RigidStructure
    tilted = np.array([1.0, -2.0, -9.0])
    chain = arm_chain(9.81 * tilted / np.linalg.norm(tilted))
    names = ['a', 'b', 'c']
    ours = ChainStructure(chain, names)
    theirs = RigidStructure(chain_urdf(chain, names), names)
    rng = np.random.default_rng(4)
    p = bodies(3, rng)
    q, v, a = ours.random_states(6, rng)
    np.testing.assert_allclose(ours.inverse_dynamics(p, q, v, a),
                               theirs.inverse_dynamics(p, q, v, a), atol=1e-10)
    np.testing.assert_allclose(ours.mass_matrix(p, q), theirs.mass_matrix(p, q), atol=1e-12)
    np.testing.assert_allclose(ours.regressor(q, v, a), theirs.regressor(q, v, a), atol=1e-10)
    assert ours.base.rank == theirs.base.rank


def test_dh_numbers_give_back_the_same_lines_parallel_axes_included():
    rng = np.random.default_rng(0)
    for alpha in (rng.uniform(-3, 3, 5), np.array([0.0, 1.5, 0.0, 0.0, -1.5])):
        chain = from_dh(alpha, rng.normal(0, 0.3, 5), rng.uniform(-3, 3, 5),
                        rng.normal(0, 0.3, 5), rng.normal(0, 5, 3))
        axes, points = lines(chain)
        dh = dh_of_lines(axes, points, chain.gravity)
        back_axes, back_points = lines(dh.chain())
        back_axes = back_axes @ dh.rotation.T
        back_points = back_points @ dh.rotation.T + dh.origin
        back_points -= np.sum(back_points * back_axes, 1, keepdims=True) * back_axes
        np.testing.assert_allclose(back_axes, axes, atol=1e-12)
        np.testing.assert_allclose(back_points, points, atol=1e-12)
        np.testing.assert_allclose(dh.rotation @ dh.gravity, chain.gravity, atol=1e-12)
        assert dh.offset[-1] == 0.0 and dh.d[-1] == 0.0
        coding = ChainCoding(5)
        again = coding.chain(coding.numbers(chain))
        assert axis_errors(again, chain)['aligned_deg_max'] < 1e-6


def test_the_mirror_image_has_the_same_dynamics_and_no_axis_error():
    chain = arm_chain()
    image = mirrored(chain)
    errors = axis_errors(image, chain)
    assert errors['aligned_deg_max'] < 1e-6 and errors['mirrored']
    assert errors['pairwise_deg_max'] < 1e-6
    # torques of the chain are explained exactly by the mirror image's own parameters
    truth = ChainStructure(chain)
    data = dataset(truth, bodies(3, np.random.default_rng(1)), 4.0, 2)
    rows = block_rows([data], 20, 8, np.random.default_rng(3))
    score = ChainScore(rows, torque_weights([data]))
    from rkgnn_ros.core.rigid.chain import chain_tree
    assert score.cost(chain_tree(image)) < 1e-8
    turned = ChainCoding(3).turned(ChainCoding(3).numbers(chain), 1)
    assert score.cost(ChainCoding(3).tree(turned)) > 1e-4    # one axis turned alone is not


def test_an_axis_turned_is_turned_back():
    chain = arm_chain()
    coding = ChainCoding(3)
    x = coding.numbers(chain)
    for joint in range(3):
        turned = coding.turned(x, joint)
        errors = axis_errors(coding.chain(turned), chain)
        assert errors['pairwise_deg_max'] > 10.0
        back = coding.turned(turned, joint)
        assert axis_errors(coding.chain(back), chain)['aligned_deg_max'] < 1e-6
    data = dataset(ChainStructure(chain), bodies(3, np.random.default_rng(5)), 6.0, 6)
    rows = block_rows([data], 30, 8, np.random.default_rng(7))
    score = ChainScore(rows, torque_weights([data]))
    start = refine(score, coding, coding.turned(x, 2), max_iterations=20)
    best = turn_axes(score, coding, start, max_iterations=20)
    assert best.cost < 1e-6 and best.cost < 1e-2 * start.cost
    assert axis_errors(coding.chain(best.x), chain)['aligned_deg_max'] < 0.1


def test_a_three_joint_chain_is_recovered_from_exact_data():
    chain = arm_chain()
    truth = ChainStructure(chain)
    parameters = bodies(3, np.random.default_rng(11))
    train = dataset(truth, parameters, 12.0, 12)
    held = dataset(truth, parameters, 4.0, 13, centre=0.3)
    settings = ChainSettings(refine_blocks=40, block_length=8, max_starts=20, seed=1,
                             joint_iterations=40)
    found = fit_chain([train], [held], settings)
    assert found is not None
    assert axis_errors(found.chain, chain)['aligned_deg_max'] < 0.5
    assert found.arm.consistent()
    assert np.max(found.fit.errors) < 0.01        # held-out torque, RMSE / std per joint
    report = found.report
    assert max(report['determinacy']['axis_deg']) < 0.5
    assert len(report['chain']['modified_dh']['alpha_deg']) == 3
    # the learned URDF holds the chain and the identified inertials
    pytest.importorskip('pinocchio')
    from rkgnn_ros.core.rigid.structure import RigidStructure
    names = found.arm.joint_names
    again = RigidStructure(found.urdf(), names)
    q, v, a = truth.random_states(5, np.random.default_rng(2))
    v = np.where(np.abs(v) < 0.5, 0.5, v)    # away from the Coulomb smoothing
    joint = found.arm.parameters[30:].reshape(3, 4)
    expected = found.arm.inverse_dynamics(q, v, a) - joint[:, 0] * a - joint[:, 3]
    np.testing.assert_allclose(again.inverse_dynamics(again.prior, q, v, a), expected,
                               rtol=1e-6, atol=1e-6)


SERVO_KP, SERVO_KD = np.array([80.0, 80.0, 40.0]), np.array([8.0, 8.0, 4.0])


def servoed(ki_per_kp=0.0):
    """Return 16 s at 100 Hz of the 3-joint arm under its servo (Ki = ``ki_per_kp`` Kp)."""
    pytest.importorskip('pinocchio')
    from rkgnn_ros.core.rigid.urdf_out import identified_urdf
    from rkgnn_ros.core.sim.servo import Servo
    from rkgnn_ros.core.sim.simulate import simulate
    from rkgnn_ros.core.sim.trajectories import SumOfSines
    from rkgnn_ros.core.sim.urdf_arm import UrdfArm
    names = ('a', 'b', 'c')
    truth = ChainStructure(arm_chain(), names)
    parameters = bodies(3, np.random.default_rng(11))
    parameters[30:] = 0.0
    arm = UrdfArm(identified_urdf(truth, parameters, 'test arm'), list(names))
    servo = Servo(SERVO_KP, SERVO_KD, ki=ki_per_kp * SERVO_KP)
    reference = SumOfSines.random(3, np.random.default_rng(1), n_terms=3, amplitude=0.5)
    return simulate(arm, servo, reference, 16.0, rate=100.0, joint_names=names)


def without_effort(part):
    """Return ``part`` as joint_states without effort and the commands: case 3's data."""
    return Dataset(part.t, part.theta, part.theta_dot, theta_d=part.theta_d,
                   theta_d_dot=part.theta_d_dot, joint_names=part.joint_names)


def test_without_torque_and_gains_the_chain_and_the_gains_ratios_are_learned():
    # case 3: a PD servo whose gains nobody gives, joint_states without effort
    data = servoed()
    kp, kd = SERVO_KP, SERVO_KD
    settings = ChainSettings(refine_blocks=40, block_length=8, max_starts=20, seed=1,
                             joint_iterations=40)
    found = fit_chain([without_effort(data.slice(0, 1200))],
                      [without_effort(data.slice(1200, 1600))], settings, case='unknown')
    assert found is not None and found.report['case'] == 'unknown'
    assert axis_errors(found.chain, arm_chain())['aligned_deg_max'] < 1.0
    assert found.arm.consistent()
    assert np.max(found.fit.errors) < 0.01     # held-out closed-loop equation error
    for learned in (np.array(found.report['gains']['kp']), found.fit.law.kp):
        np.testing.assert_allclose(learned / learned.mean(), kp / kp.mean(), rtol=0.03)
    np.testing.assert_allclose(found.fit.law.kd / found.fit.law.kp, kd / kp, rtol=0.03)
    with pytest.raises(ValueError):
        fit_chain([data], case='pd')


def test_under_a_pid_servo_the_chain_and_the_three_gains_are_learned():
    # case 3 with an integral term: ∫e and each segment's start are unknowns of the rows
    data = servoed(ki_per_kp=0.5)
    kp = SERVO_KP
    # two training segments: the integral's value at the second one's start is unknown
    train = [without_effort(data.slice(0, 600)), without_effort(data.slice(650, 1200))]
    held = [without_effort(data.slice(1200, 1600))]
    settings = ChainSettings(refine_blocks=40, block_length=8, max_starts=20, seed=1,
                             joint_iterations=40)       # the integral's columns: the default
    found = fit_chain(train, held, settings, case='unknown')
    assert found is not None
    assert axis_errors(found.chain, arm_chain())['aligned_deg_max'] < 1.0
    assert found.arm.consistent()
    assert np.max(found.fit.errors) < 0.01     # held-out closed-loop equation error
    gains = found.report['gains']
    learned_kp, learned_ki = np.array(gains['kp']), np.array(gains['ki'])
    np.testing.assert_allclose(learned_kp / learned_kp.mean(), kp / kp.mean(), rtol=0.03)
    np.testing.assert_allclose(learned_ki / learned_kp, 0.5, rtol=0.05)
    np.testing.assert_allclose(found.fit.law.ki / found.fit.law.kp, 0.5, rtol=0.05)
    # the same data without the integral's columns leave the servo's torque unexplained
    pd_only = fit_chain(train, held, ChainSettings(refine_blocks=40, block_length=8,
                                                   max_starts=20, seed=1, joint_iterations=40,
                                                   integral=False), case='unknown')
    assert pd_only is None or np.max(pd_only.fit.errors) > 3 * np.max(found.fit.errors)


def test_an_axis_the_data_cannot_see_is_reported_undetermined():
    chain = arm_chain()
    truth = ChainStructure(chain)
    parameters = bodies(3, np.random.default_rng(21))
    parameters[20:30] = 0.0     # the last body carries nothing: its axis moves no mass
    data = dataset(truth, parameters, 8.0, 22)
    rows = block_rows([data], 30, 8, np.random.default_rng(23))
    score = ChainScore(rows, torque_weights([data]))
    coding = ChainCoding(3)
    x = coding.numbers(chain)
    report = determinacy(score, coding, x)
    assert report['free_directions'] >= 1 or report['axis_deg'][2] > 10.0
    assert max(report['axis_deg'][:2]) < 1.0 < report['axis_deg'][2]

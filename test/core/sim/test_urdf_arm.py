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

"""URDF arms: the dynamics against the planar arm, Pinocchio's reduction, bad URDFs."""

import numpy as np
import pytest

pinocchio = pytest.importorskip('pinocchio')

from rkgnn_ros.core.sim.plant import ArmParameters, PlanarArm  # noqa: E402
from rkgnn_ros.core.sim.servo import Servo  # noqa: E402
from rkgnn_ros.core.sim.simulate import simulate  # noqa: E402
from rkgnn_ros.core.sim.trajectories import SumOfSines  # noqa: E402
from rkgnn_ros.core.sim.urdf_arm import (example_robot_urdf, read_description,  # noqa: E402
                                         reduce_urdf, UrdfArm, UrdfError)
from urdf_helpers import planar_urdf  # noqa: E402

UR5 = 'example-robot-data:ur_description/urdf/ur5_robot.urdf'
PANDA = 'example-robot-data:panda_description/urdf/panda.urdf'
PANDA_6 = [f'panda_joint{i}' for i in range(1, 7)]


@pytest.fixture(scope='module')
def planar_pair():
    masses, lengths = [6.0, 4.0, 3.0], [0.2, 0.3, 0.1]
    planar = PlanarArm(ArmParameters(np.array(masses), np.array(lengths), viscous=[0.5, 0.3, 0.1],
                                     coulomb=[0.3, 0.2, 0.1]))
    urdf = UrdfArm(planar_urdf(masses, lengths), viscous=[0.5, 0.3, 0.1],
                   coulomb=[0.3, 0.2, 0.1])
    return planar, urdf


def test_the_planar_arm_written_as_a_urdf_has_the_planar_dynamics(planar_pair):
    planar, urdf = planar_pair
    rng = np.random.default_rng(0)
    q, v, a = (rng.uniform(-2.0, 2.0, (20, 3)) for _ in range(3))
    np.testing.assert_allclose(urdf.mass_matrix(q), planar.mass_matrix(q), atol=1e-12)
    np.testing.assert_allclose(urdf.gravity_terms(q), planar.gravity_terms(q), atol=1e-12)
    np.testing.assert_allclose(urdf.velocity_terms(q, v), planar.velocity_terms(q, v),
                               atol=1e-12)
    np.testing.assert_allclose(urdf.inverse_dynamics(q, v, a),
                               planar.inverse_dynamics(q, v, a), atol=1e-11)
    tau = planar.inverse_dynamics(q, v, a)
    np.testing.assert_allclose(urdf.forward_dynamics(q, v, tau), a, atol=1e-9)
    np.testing.assert_allclose(urdf.forward_dynamics(q[0], v[0], tau[0]), a[0], atol=1e-9)
    np.testing.assert_allclose(urdf.dynamics(np.hstack([q, v]), tau), planar.dynamics(
        np.hstack([q, v]), tau), atol=1e-9)


def test_closed_loop_eigenvalues_match_the_planar_arms(planar_pair):
    planar, urdf = planar_pair
    kp, kd = np.array([32.84, 42.05, 42.31]), np.array([42.44, 0.19, 4.86])
    theta, theta_dot = np.array([-1.2, 0.3, 0.2]), np.array([0.4, -0.2, 1.0])
    ours = np.sort_complex(urdf.closed_loop_eigenvalues(theta, theta_dot, kp, kd))
    planars = np.sort_complex(planar.closed_loop_eigenvalues(theta, theta_dot, kp, kd))
    # the planar arm's Jacobian is a central difference with relative step 1e-6
    np.testing.assert_allclose(ours, planars, rtol=1e-5, atol=1e-5)
    assert urdf.stable_step(kp, kd, theta, theta_dot) == pytest.approx(
        planar.stable_step(kp, kd, theta, theta_dot), rel=1e-5)


def test_regressor_reproduces_the_torque_of_a_real_arm():
    arm = UrdfArm(UR5, viscous=0.4, coulomb=0.2)
    rng = np.random.default_rng(1)
    q, v, a = (rng.uniform(-1.5, 1.5, (10, 6)) for _ in range(3))
    y = arm.regressor(q, v, a)
    assert y.shape == (10, 6, 72)
    np.testing.assert_allclose(y @ arm.parameter_vector(), arm.inverse_dynamics(q, v, a),
                               atol=1e-10)
    m = arm.mass_matrix(q)
    np.testing.assert_allclose(m, np.swapaxes(m, -1, -2), atol=0.0)
    assert np.linalg.eigvalsh(m).min() > 0.0


def test_locked_joints_equal_pinocchios_reduced_model():
    locked = {'panda_joint7': 0.8, 'panda_finger_joint1': 0.02, 'panda_finger_joint2': 0.01}
    arm = UrdfArm(PANDA, joints=PANDA_6, locked=locked)
    assert arm.joint_names == tuple(PANDA_6)
    assert arm.locked == locked
    full = pinocchio.buildModelFromUrdf(example_robot_urdf('panda_description/urdf/panda.urdf'))
    q_lock = pinocchio.neutral(full)
    for name, value in locked.items():
        q_lock[full.joints[full.getJointId(name)].idx_q] = value
    lock_ids = [full.getJointId(name) for name in locked]
    reduced = pinocchio.buildReducedModel(full, lock_ids, q_lock)
    data = reduced.createData()
    rng = np.random.default_rng(2)
    for q in rng.uniform(-1.0, 1.0, (5, 6)):
        expected = pinocchio.crba(reduced, data, q)
        expected = np.triu(expected) + np.triu(expected, 1).T
        np.testing.assert_allclose(arm.mass_matrix(q), expected, atol=1e-10)
        np.testing.assert_allclose(arm.gravity_terms(q),
                                   pinocchio.computeGeneralizedGravity(reduced, data, q),
                                   atol=1e-10)


def test_a_servo_with_gravity_compensation_holds_a_urdf_arm_at_rest():
    arm = UrdfArm(UR5)
    home = np.array([0.0, -1.2, 1.0, -1.4, -1.57, 0.0])
    kp = np.array([300.0, 300.0, 150.0, 40.0, 40.0, 10.0])
    kd = np.array([40.0, 40.0, 20.0, 4.0, 4.0, 0.6])
    rest = SumOfSines(home, np.zeros((6, 1)), np.ones((6, 1)), np.zeros((6, 1)))
    held = simulate(arm, Servo(kp, kd, gravity='measured', arm=arm), rest, 1.0)
    np.testing.assert_allclose(held.theta, np.broadcast_to(home, held.theta.shape), atol=1e-7)
    np.testing.assert_allclose(held.tau, arm.gravity_terms(held.theta), atol=1e-5)
    sagging = simulate(arm, Servo(kp, kd), rest, 1.0)
    # without compensation the PD needs an error Kp e = G to hold the arm
    assert np.max(np.abs(sagging.theta[-1] - home)) > 1e-2


def test_reduce_urdf_keeps_the_urdf_loadable_and_fixes_the_locked_joints():
    xml, _ = read_description(PANDA)
    reduced, joints, locked = reduce_urdf(xml, PANDA_6)
    assert joints == tuple(PANDA_6)
    assert set(locked) == {'panda_joint7', 'panda_finger_joint1', 'panda_finger_joint2'}
    model = pinocchio.buildModelFromXML(reduced)
    assert tuple(model.names[1:]) == tuple(PANDA_6)
    assert locked['panda_joint7'] == 0.0


@pytest.mark.parametrize('description, joints, message', [
    ('', None, 'robot_description is empty'),
    ('/no/such/arm.urdf', None, "cannot read '/no/such/arm.urdf'"),
    ('<robot name="x"><link name="a"></robot>', None, 'not valid XML'),
    ('<sdf version="1.6"/>', None, 'not a URDF'),
    (planar_urdf([1.0], [0.3]), ['elbow'], "no joint named 'elbow'"),
    (planar_urdf([1.0], [0.3], joint_type='continuous'), ['joint1'],
     "'joint1' is continuous (no position limits)"),
    (planar_urdf([1.0], [0.3], joint_type='prismatic'), ['joint1'], "'joint1' is prismatic"),
    (planar_urdf([1.0, 1.0], [0.3, 0.2], inertial=False), None, 'move no inertia'),
    (planar_urdf([1.0, 1.0], [0.3, 0.2]), ['joint2', 'joint1'], 'list them base to tip'),
    (UR5, ['elbow_joint', 'elbow_joint'], 'repeat a name'),
])
def test_bad_urdfs_are_refused_naming_the_problem(description, joints, message):
    with pytest.raises(UrdfError) as info:
        UrdfArm(description, joints=joints)
    assert message in str(info.value)


def test_a_revolute_joint_without_limits_is_refused():
    xml = planar_urdf([1.0], [0.3]).replace('<limit lower="-3" upper="3" ',
                                            '<limit ')
    with pytest.raises(UrdfError, match="'joint1' has no usable <limit lower upper>"):
        reduce_urdf(xml, ['joint1'])


def test_locking_a_joint_that_moves_or_does_not_exist_is_refused():
    with pytest.raises(UrdfError, match="cannot lock 'joint1'"):
        UrdfArm(planar_urdf([1.0, 1.0], [0.3, 0.2]), joints=['joint1', 'joint2'],
                locked={'joint1': 0.1})
    with pytest.raises(UrdfError, match='not finite'):
        UrdfArm(planar_urdf([1.0, 1.0], [0.3, 0.2]), joints=['joint1'],
                locked={'joint2': float('nan')})


def test_example_robot_urdf_names_a_missing_file():
    with pytest.raises(UrdfError, match='has no robots/none/arm.urdf'):
        example_robot_urdf('none/arm.urdf')

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

"""The rigid-body loop under a PID: its integral grows inside the rollout, as the servo's."""

import numpy as np
import pytest

pytest.importorskip('pinocchio')

from rkgnn_ros.core.fitting.controller_laws import ControllerLaw  # noqa: E402
from rkgnn_ros.core.fitting.rigid_fit import RigidArm  # noqa: E402
from rkgnn_ros.core.fitting.rigid_loop import RigidLoop  # noqa: E402
from rkgnn_ros.core.rigid.kernels import N_INERTIAL  # noqa: E402
from rkgnn_ros.core.rigid.structure import RigidStructure  # noqa: E402
from rkgnn_ros.core.sim.arm_simulator import ArmSimulator  # noqa: E402
from rkgnn_ros.core.sim.trajectories import SumOfSines  # noqa: E402
from rkgnn_ros.core.sim.urdf_arm import UrdfArm  # noqa: E402

UR5 = 'example-robot-data:ur_description/urdf/ur5_robot.urdf'
KP = np.array([400.0, 400.0, 200.0, 40.0, 40.0, 10.0])
KD = np.array([40.0, 40.0, 20.0, 3.0, 3.0, 0.3])
HOME = np.array([0.0, -1.57, 1.57, -1.57, -1.57, 0.0])


def pid_law(ki, integral_term):
    """Return the PID law τ = Kp e + Kd ė + I with I starting at ``integral_term`` (N m)."""
    n = KP.size
    return ControllerLaw(kp=KP, kd=KD, ki=ki, bias=np.zeros(n), integral_term=integral_term,
                         feedforward=np.zeros(n), theta_weights=np.zeros((n, 0)),
                         theta_input='measured', features=None, fit_ratio=np.zeros(n),
                         samples=0, tau_limit=np.full(n, np.inf), filter_sigma=0.02)


def test_a_pid_loop_rolls_out_as_the_servo_it_was_fitted_to():
    arm = UrdfArm(UR5)
    structure = RigidStructure(arm.urdf, arm.joint_names)
    params = structure.prior.copy()
    params[N_INERTIAL * structure.n_joints:] = 0.0      # the simulated arm has no joint terms
    ki = 0.5 * KP                                         # 1/s: the integral acts within 2 s
    reference = SumOfSines.random(6, np.random.default_rng(5), n_terms=2, amplitude=0.4,
                                  offsets=HOME)
    sim = ArmSimulator(arm, KP, KD, reference, 0.001, compiled=False, ki=ki)
    sim.advance(3.0)                                      # the integral has grown by now
    start = sim.x.copy()
    n = arm.n_joints
    t = np.arange(201) * 0.01
    truth = []
    for k, tk in enumerate(t):
        if k:
            sim.advance(3.0 + tk)
        truth.append(sim.x[:n].copy())
    truth = np.array(truth)
    theta_d, theta_d_dot = reference.evaluate(3.0 + t)
    loop = RigidLoop(RigidArm(structure, params), pid_law(ki, start[2 * n:]))
    states = loop.simulate(start[:2 * n], t, theta_d, theta_d_dot)
    error = np.max(np.abs(states[:, :n] - truth))
    assert error < 1e-4
    # the same law with its integral held along earlier passes drifts from the servo
    loop._integral_compiled = False
    held = np.max(np.abs(loop.simulate(start[:2 * n], t, theta_d, theta_d_dot)[:, :n] - truth))
    assert held > 10.0 * error

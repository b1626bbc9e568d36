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

"""A payload on the last link: the plant changes, the servo's gravity model does not."""

import numpy as np
import pytest
from rkgnn_ros.core.sim.arm_simulator import ArmSimulator
from rkgnn_ros.core.sim.payload import with_payload
from rkgnn_ros.core.sim.plant import PlanarArm
from rkgnn_ros.core.sim.trajectories import paper_reference
from rkgnn_ros.sim_node.parameters import build_config, ConfigurationError, PARAMETERS


def test_the_planar_payload_is_a_mass_at_the_last_tip():
    arm = PlanarArm.paper()
    heavier = with_payload(arm, 2.0)
    theta = np.array([[0.3, -0.2, 0.5]])
    # G of the last joint: (m3 + 2) g l3 cos(θ1 + θ2 + θ3)
    lever = 0.1 * np.cos(theta.sum())
    assert heavier.gravity_terms(theta)[0, 2] - arm.gravity_terms(theta)[0, 2] == \
        pytest.approx(2.0 * 9.81 * lever, rel=1e-9)
    assert arm.params.masses[-1] == 3.0                    # the nominal arm is untouched


def test_a_urdf_payload_adds_its_gravity_about_every_joint_before_it():
    pytest.importorskip('pinocchio')
    from rkgnn_ros.core.sim.urdf_arm import UrdfArm
    arm = UrdfArm('example-robot-data:ur_description/urdf/ur5_robot.urdf')
    heavier = with_payload(arm, 3.0, [0.0, 0.0, 0.05])
    q = arm.home[None]
    extra = heavier.gravity_terms(q) - arm.gravity_terms(q)
    assert abs(extra[0, 1]) > 5.0                          # 3 kg about the shoulder
    np.testing.assert_allclose(with_payload(arm, 0.0).gravity_terms(q), arm.gravity_terms(q))


def test_the_simulator_carries_the_payload_while_its_servo_compensates_the_nominal_arm():
    arm = PlanarArm.paper()
    sim = ArmSimulator(arm, [32.84, 42.05, 42.31], [42.44, 0.19, 4.86], paper_reference(3),
                       0.001, gravity_compensation='measured')
    sim.advance(1.0)
    sim.set_payload(2.0)
    assert sim.arm.params.masses[-1] == 5.0 and sim.servo.arm is arm
    sim.advance(2.0)
    theta, *_ = sim.sample()
    compare = ArmSimulator(arm, [32.84, 42.05, 42.31], [42.44, 0.19, 4.86],
                           paper_reference(3), 0.001, gravity_compensation='measured')
    compare.advance(2.0)
    # the payload pulls the arm off its path (the servo does not know of it)
    assert np.max(np.abs(theta - compare.sample()[0])) > 1e-3
    sim.set_payload(0.0)
    assert sim.arm is arm


def _values(**changes):
    values = {spec.name: spec.default for spec in PARAMETERS}
    values.update(changes)
    return values


def test_payload_parameters_are_checked():
    with pytest.raises(ConfigurationError, match='payload.com'):
        build_config(_values(**{'payload.mass': 1.0, 'payload.com': [0.0, 0.1]}))
    with pytest.raises(ConfigurationError, match='detach_at'):
        build_config(_values(**{'payload.mass': 1.0, 'payload.attach_at': 5.0,
                                'payload.detach_at': 2.0}))
    config, _ = build_config(_values(**{'payload.mass': 2.0, 'payload.attach_at': 60.0}))
    assert config.payload[0] == 2.0 and config.payload[2] == 60.0

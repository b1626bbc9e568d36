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
Compile the nodes' numba kernels into their on-disk cache, at set-up time.

numba compiles a kernel the first time it is called with new argument types and, with
``cache=True``, keeps the machine code beside the source (``__pycache__``, where the
symlinked install that ``ros2 run`` uses finds it too). The identifier's first search
otherwise pays that compilation after the first joint_states. This runs what the first
minutes of an identifier run: the online policy of :mod:`rkgnn_ros.core.fitting.online` on
a few seconds of the simulated paper arm, in the three cases (the equation-error start, the
rollouts, the refinement, the validation), with the default network and with the
trigonometric basis, and the prediction of the published models; every kernel then sits in
the cache, with those of :func:`rkgnn_ros.core.fitting.identify.precompile`, which the node
runs before it spins, and sim_arm's simulation kernels; and, on a UR5 of example-robot-data,
the rigid-body kernels an identifier with a robot description and sim_arm on a URDF arm use
(:func:`precompile_rigid`). ``make build`` runs it (``python tools/precompile.py``, the
checkout's package first on the path); a second run finds everything cached and takes
seconds. A set-up tool, not a part of the nodes: it drives the simulator of
:mod:`rkgnn_ros.core.sim`, which in the package only sim_arm's parts import.
"""

import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from rkgnn_ros.core.fitting.identify import precompile  # noqa: E402
from rkgnn_ros.core.fitting.online import (ModelUpdate, Observation,  # noqa: E402
                                           OnlineIdentification, OnlineSettings)
from rkgnn_ros.core.sim.arm_simulator import ArmSimulator  # noqa: E402
from rkgnn_ros.core.sim.plant import PDController, PlanarArm  # noqa: E402
from rkgnn_ros.core.sim.simulate import simulate  # noqa: E402
from rkgnn_ros.core.sim.trajectories import paper_reference  # noqa: E402
from rkgnn_ros.streams.buffer import StreamBuffer  # noqa: E402

JOINTS = ('j1', 'j2', 'j3')

#: The network settings compiled: the default and the trigonometric basis (its dispatch).
NETWORKS = ({}, {'basis': 'trig+rbf'})

#: The URDF arm whose rigid-body kernels are compiled (example-robot-data's UR5).
RIGID_ARM = 'example-robot-data:ur_description/urdf/ur5_robot.urdf'

#: Steps of the fake clock before giving up on a published model.
STEP_LIMIT = 400


def _buffer(data, case: str) -> StreamBuffer:
    """Return a buffer holding every stream of ``data``."""
    buffer = StreamBuffer(JOINTS, 0.01, 4.0, 0.1, need_tau=case == 'torque',
                          need_desired=case != 'torque')
    for k in range(data.t.size):
        buffer.add_state(1000.0 + data.t[k], data.theta[k], data.theta_dot[k], data.tau[k])
        buffer.add_command(1000.0 + data.t[k], data.theta_d[k], data.theta_d_dot[k])
    return buffer


def run_case(data, case: str, network: dict) -> int:
    """
    Drive the online policy on ``data`` until it publishes, then predict with the model.

    Returns
    -------
    int
        Generations run (RuntimeError if no model was published).

    """
    now = [100.0]
    pd = PDController.paper()
    gains = case == 'pd_gains'
    settings = OnlineSettings(case=case, min_window=2.0, validation_fraction=0.25,
                              model_publish_period=0.0, network=network,
                              kp=tuple(pd.kp.diagonal()) if gains else (),
                              kd=tuple(pd.kd.diagonal()) if gains else (),
                              optimizer_settings={'population_size': 6}, seed=0)
    policy = OnlineIdentification(lambda: now[0], warm_start_seconds=2.0, warm_start_nfev=3)
    buffer = _buffer(data, case)
    generations = 0
    for _ in range(STEP_LIMIT):
        now[0] += 0.1
        obs = Observation(settings, JOINTS, {'state': now[0], 'command': now[0]})
        if policy.data_due(obs):
            obs = obs._replace(data=buffer.capture())
        result = policy.step(obs)
        generations += int(result.ran)
        updates = [e for e in result.events if isinstance(e, ModelUpdate)]
        if updates and generations >= 2:
            update = updates[-1]
            update.model.predict(data.slice(0, 100))
            if update.loop is not None:
                update.loop.loop.model.predict(data.slice(0, 100))
            return generations
    raise RuntimeError(f'case {case}: no model published in {STEP_LIMIT} steps')


def precompile_sim_arm() -> None:
    """
    Compile sim_arm's simulation kernels: continuous and digital PD, PID with Ĝ.

    Left to the first ``ros2 run rkgnn_ros sim_arm`` after set-up, they took it about 4.6 s
    to start (measured in a fresh clone), while an identifier started with it was waiting.
    """
    arm, reference = PlanarArm.paper(), paper_reference(3)
    pd = PDController.paper()
    for rate, ki, gravity in ((None, 0.0, 'none'), (500.0, 0.0, 'none'),
                              (None, 20.0, 'measured')):
        sim = ArmSimulator(arm, np.diag(pd.kp), np.diag(pd.kd), reference, 0.0005,
                           control_rate=rate, ki=ki, gravity_compensation=gravity)
        sim.advance(0.01)
        sim.sample()


def precompile_rigid() -> int:
    """
    Compile the rigid-body kernels: a URDF arm simulated, fitted and rolled out per case.

    Returns the number of cases that published a closed loop (0 when example-robot-data,
    whose UR5 it runs, is not installed). Left to the first identifier run with a robot
    description, their compilation blocks its first fit and first prediction.
    """
    from rkgnn_ros.core.rigid.structure import RigidStructure
    from rkgnn_ros.core.rigid.urdf import UrdfError
    from rkgnn_ros.core.sim.servo import Servo
    from rkgnn_ros.core.sim.trajectories import SumOfSines
    from rkgnn_ros.core.sim.urdf_arm import UrdfArm
    try:
        arm = UrdfArm(RIGID_ARM, viscous=[1.0] * 6, coulomb=[0.5] * 6)
    except UrdfError as problem:
        print(f'precompile: rigid-body kernels left to their first use ({problem})',
              flush=True)
        return 0
    kp, kd = np.array([400.0, 400.0, 200.0, 40.0, 40.0, 10.0]), np.full(6, 10.0)
    home = np.array([0.0, -1.57, 1.57, -1.57, -1.57, 0.0])
    reference = SumOfSines.random(6, np.random.default_rng(0), n_terms=2, amplitude=0.3,
                                  offsets=home)
    data = simulate(arm, Servo(kp, kd), reference, 4.0, rate=100.0,
                    joint_names=arm.joint_names)
    structure = RigidStructure(arm.urdf, arm.joint_names)
    closed = 0
    for case in ('torque', 'pd_gains', 'unknown'):
        gains = {'kp': tuple(kp), 'kd': tuple(kd)} if case == 'pd_gains' else {}
        settings = OnlineSettings(case=case, min_window=2.0, validation_fraction=0.25,
                                  model_publish_period=0.0, **gains)
        buffer = StreamBuffer(tuple(arm.joint_names), 0.01, 4.0, 0.1,
                              need_tau=case == 'torque', need_desired=True)
        for k in range(data.t.size):
            buffer.add_state(1000.0 + data.t[k], data.theta[k], data.theta_dot[k], data.tau[k])
            buffer.add_command(1000.0 + data.t[k], data.theta_d[k], data.theta_d_dot[k])
        now = [100.0]
        policy = OnlineIdentification(lambda: now[0])
        for _ in range(4):
            now[0] += 1.0
            obs = Observation(settings, tuple(arm.joint_names),
                              {'state': now[0], 'command': now[0]}, structure=structure)
            result = policy.step(obs._replace(data=buffer.capture()))
            loops = [e.loop for e in result.events
                     if isinstance(e, ModelUpdate) and e.loop is not None]
            if loops:
                loops[-1].model.warm_up()
                x0 = np.concatenate([data.theta[0], data.theta_dot[0]])
                loops[-1].loop.simulate(x0, data.t[:50], data.theta_d[:50],
                                        data.theta_d_dot[:50])
                closed += 1
                break
    return closed


def main(argv=None) -> int:
    """Compile every kernel of a first identifier (and sim_arm) run; print how long."""
    start = time.monotonic()
    precompile()                                   # what the node compiles before spinning
    precompile_sim_arm()
    data = simulate(PlanarArm.paper(), PDController.paper(), paper_reference(3), 4.0,
                    rate=100.0, joint_names=JOINTS)
    for network in NETWORKS:
        for case in ('torque', 'pd_gains', 'unknown'):
            generations = run_case(data, case, network)
            print(f'precompile: case {case}, network {network or "default"}: '
                  f'{generations} generations', flush=True)
    closed = precompile_rigid()
    print(f'precompile: rigid body, {closed} of 3 cases closed', flush=True)
    print(f'precompile: kernels cached in {time.monotonic() - start:.0f} s', flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())

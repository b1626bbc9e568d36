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

"""Helpers shared by the tests of the model: scales, genome blocks, a small identified model."""

import numpy as np
from rkgnn_ros.core.model.model import RKGNNModel
from rkgnn_ros.core.model.scales import Scales
from rkgnn_ros.core.model.spec import NetworkSpec
from rkgnn_ros.core.sim.parameters import ArmParameters
from rkgnn_ros.core.sim.plant import PDController, PlanarArm
from rkgnn_ros.core.sim.simulate import simulate
from rkgnn_ros.core.sim.trajectories import paper_reference


def unit_scales(n, **overrides):
    """Scales of 1 everywhere (θ centred on 0): genome values are then physical values."""
    values = {name: np.ones(n) for name in ('theta_spread', 'velocity', 'acceleration',
                                            'torque', 'error', 'error_rate')}
    values['theta_center'] = np.zeros(n)
    values.update({k: np.asarray(v, dtype=float) for k, v in overrides.items()})
    return Scales(**values)


def block(spec, name):
    """Return the genome block called ``name``."""
    return next(b for b in spec.blocks() if b.name == name)


def set_block(spec, genome, name, values):
    """Write ``values`` (reshaped to the block's shape) into ``genome`` in place."""
    b = block(spec, name)
    genome[b.start:b.stop] = np.asarray(values, dtype=float).reshape(b.shape).ravel()


N = 3
SCALES = Scales(theta_center=[-1.5, 0.0, 0.0], theta_spread=[0.3, 0.3, 0.3],
                velocity=[1.0, 1.0, 1.0], acceleration=[5.0, 5.0, 5.0], torque=[3.0, 2.0, 1.0],
                error=[0.1, 0.1, 0.1], error_rate=[0.5, 0.5, 0.5])
KP = np.array([30.0, 20.0, 10.0])
KD = np.array([3.0, 2.0, 1.0])
REFERENCE = paper_reference(N)
NAMES = ('shoulder', 'elbow', 'wrist')

# a 2-link arm under PD control, for identification
ARM2 = ArmParameters(masses=[4.0, 3.0], lengths=[0.3, 0.2], viscous=[0.3, 0.1],
                     coulomb=[0.2, 0.1])
KP2 = np.array([40.0, 30.0])
KD2 = np.array([5.0, 3.0])


def make_model(case='pd_gains', inertia='cholesky', velocity='learned', seed=0, sigma=0.05,
               **kwargs):
    spec = NetworkSpec(N, case, inertia=inertia, velocity=velocity, bias=True,
                       torque_linear=True)
    genome = spec.initial_genome() + sigma * np.random.default_rng(seed).standard_normal(
        spec.genome_size)
    gains = {'kp': KP, 'kd': KD} if case == 'pd_gains' else {}
    kwargs.setdefault('substeps', 3)
    return RKGNNModel(spec, SCALES, genome, joint_names=NAMES, dt=0.01, **gains, **kwargs)


def torque_signal(t):
    return np.column_stack([np.sin(2 * np.pi * (0.7 + 0.3 * i) * t + i)
                            for i in range(N)]) * SCALES.torque


def simulate_model(model, t):
    qd, qd_dot = REFERENCE.evaluate(t)
    x0 = np.concatenate([qd[0], qd_dot[0]])
    if model.case == 'torque':
        return model.simulate(x0, t, tau=torque_signal(t))
    return model.simulate(x0, t, reference=REFERENCE)


def arm2_run():
    """Return 10 s at 100 Hz of the 2-link arm under PD control (1001 samples)."""
    return simulate(PlanarArm(ARM2), PDController(KP2, KD2), paper_reference(2), 10.0,
                    rate=100.0)

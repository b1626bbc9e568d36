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
Fixed-seed outputs of the numerical core, to hold a restructured core to the one before it.

:func:`compute` builds every output from public entry points only (costs and rollouts of
the compiled kernel and of the numpy reference, model rollouts and terms, equation-error
residuals, the least-squares warm start, the PD-tuning cost), so the same construction runs
on any version of the core. ``test/data/golden_core.json`` holds what it gave at commit
6d3b752 (before the core was restructured); ``python3 test/golden_core.py`` rewrites it.
"""

import json
import os
import sys

import numpy as np
from rkgnn_ros.core.fitting.fitness import FitnessProblem
from rkgnn_ros.core.fitting.refine import equation_residuals
from rkgnn_ros.core.fitting.warmstart import estimate_acceleration, least_squares_genome
from rkgnn_ros.core.model.model import RKGNNModel
from rkgnn_ros.core.model.spec import NetworkSpec
from rkgnn_ros.core.sim.plant import PDController, PlanarArm
from rkgnn_ros.core.sim.simulate import simulate
from rkgnn_ros.core.sim.trajectories import paper_reference
from rkgnn_ros.core.sim.tuning import TrackingProblem

PATH = os.path.join(os.path.dirname(os.path.abspath(__file__)), 'data', 'golden_core.json')
N = 3
KP = np.array([32.84, 42.05, 42.31])
KD = np.array([42.44, 0.19, 4.86])
ROLLOUT_ROWS = [1, 25, 49, 50, 51, 100]
MODEL_ROWS = [0, 50, 100]


def specs():
    """(name, spec): the paper's and our structures in every case, and two mixed ones."""
    out = []
    for case in ('torque', 'pd_gains', 'unknown'):
        out.append((f'paper_{case}', NetworkSpec.paper(N, case)))
        out.append((f'recommended_{case}', NetworkSpec.recommended(N, case)))
    out.append(('penalty_christoffel', NetworkSpec(N, 'torque', inertia='penalty',
                                                   velocity='christoffel', bias=True)))
    out.append(('cholesky_learned', NetworkSpec(N, 'unknown', inertia='cholesky',
                                                velocity='learned', torque_units=2,
                                                torque_linear=True)))
    return out


def data():
    """One second of the paper's arm under its PD at 100 Hz (LSODA, no noise)."""
    return simulate(PlanarArm.paper(), PDController.paper(), paper_reference(N), duration=1.0,
                    rate=100.0)


def genomes(spec):
    """Four genomes: the initial one, two perturbations of it and a random-centre one."""
    rng = np.random.default_rng(7)
    g0 = spec.initial_genome()
    eps = rng.standard_normal((2, spec.genome_size))
    g3 = spec.initial_genome(rng) + 0.02 * rng.standard_normal(spec.genome_size)
    return np.vstack([g0, g0 + 0.02 * eps[0], g0 + 0.1 * eps[1], g3])


def _torque(spec, d):
    """Return the torque of the equation error: measured, the known law, or None (case 3)."""
    if spec.case == 'torque':
        return d.tau
    if spec.case == 'pd_gains':
        return KP * (d.theta_d - d.theta) + KD * (d.theta_d_dot - d.theta_dot)
    return None


def compute():
    """Return every golden output as plain lists (JSON-ready)."""
    d = data()
    segments = [d.slice(0, 50), d.slice(50, d.n_samples)]
    out = {}
    for name, spec in specs():
        pop = genomes(spec)
        entry = {}
        for shooting in (0, 10):
            problem = FitnessProblem(spec, segments, kp=KP, kd=KD, substeps=4,
                                     shooting=shooting, torque_interpolation='linear')
            with np.errstate(all='ignore'):
                entry[f'cost_{shooting}'] = problem.cost(pop).tolist()
                entry[f'cost_numpy_{shooting}'] = problem.cost_numpy(pop).tolist()
                entry[f'rollouts_{shooting}'] = problem.rollouts(pop)[:, ROLLOUT_ROWS].tolist()
        scales = problem.scales
        model = RKGNNModel(spec, scales, pop[1], kp=KP, kd=KD, dt=0.01, substeps=4)
        entry['simulate'] = model.predict(d)[MODEL_ROWS].tolist()
        zero = np.zeros((3, N))
        theta = d.theta[[0, 40, 80]]
        terms = model.terms(theta, d.theta_dot[[0, 40, 80]], theta + 0.01, zero + 0.1,
                            tau=np.ones(N))
        entry['terms'] = {k: np.asarray(v).tolist() for k, v in terms.items()}
        acc = estimate_acceleration(d.theta_dot, d.dt)
        u = (np.zeros((d.n_samples, N)) if spec.case == 'torque'
             else np.hstack([d.theta_d, d.theta_d_dot]))
        for compiled in (True, False):
            r = equation_residuals(spec, scales, pop, (d.state, acc, u, _torque(spec, d)), KP,
                                   KD, compiled=compiled)
            entry[f'equation_{compiled}'] = r[:, ::7].tolist()
        if spec.inertia == 'penalty' and spec.velocity == 'learned':
            entry['least_squares'] = least_squares_genome(spec, [d], scales, kp=KP,
                                                          kd=KD).tolist()
        out[name] = entry
    tracking = TrackingProblem(PlanarArm.paper(), paper_reference(N), duration=0.3)
    gains = np.array([np.concatenate([KP, KD]), [30.0] * 3 + [5.0] * 3,
                      [80.0] * 3 + [40.0] * 3])
    out['tracking'] = {'cost': tracking.cost(gains).tolist(),
                       'cost_numpy': tracking.cost_numpy(gains).tolist()}
    return out


if __name__ == '__main__':
    os.makedirs(os.path.dirname(PATH), exist_ok=True)
    with open(PATH, 'w', encoding='utf-8') as f:
        json.dump(compute(), f)
    sys.exit(0)

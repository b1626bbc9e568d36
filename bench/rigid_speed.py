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
How long the rigid-body path takes at 7 joints: the closed form and a 2 s prediction.

On the Panda of ``config/sim_arm_panda.yaml`` (seven joints, its servo, friction and rotor
inertia), 20 s of 100 Hz data simulated offline: the wall time of each fit the identifier
runs at a refresh (case 1: the law on the gravity regressor, then the arm; case 2 and 3:
the closed loop in the form chosen, and the choice of forms), and of one 2 s prediction of
the fitted loop from a measured state (the RKG steps its stiffness asks for), each the
median of ``--repeats`` runs in this process, BLAS on one thread as in the identifier.
Writes ``bench/results/rigid_speed.json``; the goals (issue 29): the closed form <= 1 s,
a prediction <= 5 ms.
"""

import argparse
import datetime
import json
import os
import statistics
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from rkgnn_ros.core.fitting.case_one import fit_law  # noqa: E402
from rkgnn_ros.core.fitting.rigid_fit import fit_closed, fit_closed_forms  # noqa: E402
from rkgnn_ros.core.fitting.rigid_fit import fit_torque  # noqa: E402
from rkgnn_ros.core.fitting.rigid_law import GravityFeatures  # noqa: E402
from rkgnn_ros.core.fitting.rigid_loop import RigidLoop  # noqa: E402
from rkgnn_ros.core.fitting.validation import split_validation  # noqa: E402
from rkgnn_ros.core.rigid.structure import RigidStructure  # noqa: E402
from rkgnn_ros.core.sim.servo import Servo  # noqa: E402
from rkgnn_ros.core.sim.simulate import simulate  # noqa: E402
from rkgnn_ros.core.sim.trajectories import SumOfSines  # noqa: E402
from rkgnn_ros.core.sim.urdf_arm import UrdfArm  # noqa: E402
import scipy.linalg  # noqa: E402,F401 - loaded before the BLAS thread limit, which then reaches it
from threadpoolctl import threadpool_limits  # noqa: E402
import yaml  # noqa: E402


def _timed(function, repeats):
    times, value = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        value = function()
        times.append(time.perf_counter() - start)
    return statistics.median(times), value


def main(argv=None):
    """Time the fits and a prediction; return the exit code."""
    parser = argparse.ArgumentParser(description='rigid-body path speed at 7 joints')
    parser.add_argument('--repeats', type=int, default=5)
    parser.add_argument('--out', default=os.path.join(HERE, 'results', 'rigid_speed.json'))
    args = parser.parse_args(argv)
    threadpool_limits(1)
    with open(os.path.join(os.path.dirname(HERE), 'config', 'sim_arm_panda.yaml'),
              encoding='utf-8') as f:
        values = yaml.safe_load(f)['/**/sim_arm']['ros__parameters']
    arm = UrdfArm(values['robot_description'], values['urdf']['joints'],
                  viscous=values['viscous'], coulomb=values['coulomb'])
    arm.set_armature(values['urdf']['armature'])
    kp, kd = np.array(values['kp']), np.array(values['kd'])
    home = np.array(values['urdf']['home'])
    reference = SumOfSines.random(7, np.random.default_rng(1), n_terms=3, amplitude=0.4,
                                  offsets=home)
    data = simulate(arm, Servo(kp, kd), reference, 20.0, rate=100.0,
                    joint_names=arm.joint_names)
    train, validation, _ = split_validation([data], 0.2)
    structure = RigidStructure(arm.urdf, arm.joint_names)
    features = GravityFeatures(structure)
    fit_torque(structure, train, validation)               # compiled before timing
    timings = {}
    timings['law_s'], law = _timed(lambda: fit_law([data], features=features), args.repeats)
    timings['case1_arm_s'], fit = _timed(lambda: fit_torque(structure, train, validation),
                                         args.repeats)
    timings['case2_s'], _ = _timed(lambda: fit_closed(structure, train, validation, kp, kd,
                                                      features=features), args.repeats)
    timings['case3_s'], closed = _timed(lambda: fit_closed(structure, train, validation,
                                                           features=features), args.repeats)
    timings['case3_forms_s'], _ = _timed(lambda: fit_closed_forms(
        structure, train, validation, features=features), max(1, args.repeats // 2))
    timings['closed_form_s'] = timings['law_s'] + timings['case1_arm_s']
    loop = RigidLoop(fit.arm, law)
    start = 1000
    t = data.t[start:start + 201] if start + 201 <= data.n_samples else None
    if t is None:
        t = data.t[-201:]
        start = data.n_samples - 201
    x0 = np.concatenate([data.theta[start], data.theta_dot[start]])
    window = slice(start, start + 201)
    loop.simulate(x0, t, data.theta_d[window], data.theta_d_dot[window])
    timings['prediction_2s_ms'], states = _timed(
        lambda: loop.simulate(x0, t, data.theta_d[window], data.theta_d_dot[window]),
        20 * args.repeats)
    timings['prediction_2s_ms'] *= 1e3
    error = np.abs(states[:, :7] - data.theta[window]).max()
    result = {'date': datetime.date.today().isoformat(), 'load_average': os.getloadavg()[0],
              'arm': 'Panda, config/sim_arm_panda.yaml, 20 s at 100 Hz, PD',
              **{k: round(v, 5) for k, v in timings.items()},
              'prediction_substeps': int(loop._substeps_cache[2]),
              'prediction_max_error_rad': float(error),
              'case1_heldout_torque_error': fit.error, 'case3_heldout_error': closed.error,
              'goals': {'closed_form_s': 1.0, 'prediction_2s_ms': 5.0}}
    print(json.dumps(result, indent=1))
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, 'w', encoding='utf-8') as f:
        json.dump(result, f, indent=2)
    return 0


if __name__ == '__main__':
    sys.exit(main())

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
No robot description (issue 33, offline, case 1): the chain learned from joint data.

Simulated arms: example-robot-data's UR5 and Panda as sim_arm simulates them
(``config/sim_arm_ur5.yaml``, ``config/sim_arm_panda.yaml``: friction, the Panda's rotor
inertia, the PD gains), by :func:`rkgnn_ros.core.sim.simulate.simulate` under a
continuous PD :class:`~rkgnn_ros.core.sim.servo.Servo`, 100 Hz, exact sensors: 30 s along
``SumOfSines.random`` (seed 1, the config's amplitude, 3 sines of 0.1-0.8 Hz per joint,
about the config's home pose) fit; 10 s along other sines (seed 7, 0.8 of the amplitude,
about home + 0.2 rad on every joint) are held out.
:func:`~rkgnn_ros.core.fitting.chain_fit.fit_chain` gets the 30 s only: no URDF, no
kinematics.

Figures per arm:

- ``torque_nrmse_heldout``: as ``bench/urdf_arms.py``'s torque figure: the learned model's
  torque at every held-out sample (θ̇, θ̈ from θ by short derivative kernels), it and the
  measured torque through one Gaussian low-pass of 0.05 s (parallel filtering), RMSE / std
  per joint, the worst joint (``..._per_joint`` beside it); ``urdf_torque_nrmse_heldout``:
  the same for ``fit_torque`` given the true URDF, for reference;
- ``axis_error_deg_max``: the learned axes at θ = 0 against the URDF's, after the one
  rotation that maps the learned set best onto the true one (Kabsch): that covers a rigid
  motion of the arm and its mirror image (an exact symmetry of the dynamics, which acts on
  the axes, pseudo-vectors, as a rotation); ``axis_pairwise_deg_max``: the largest error of
  the angle between two axes over all pairs, no alignment at all;
- ``fit_s`` (wall) and ``fit_cpu_s`` (this process's CPU) of ``fit_chain``, BLAS on one
  thread, under ``nice`` on the shared machine.

Real Panda (``real_panda``): ``bench/real_panda.py``'s data, split and metric (first 70 %
fits, last 30 % held out, nMSE per joint with θ̈ and τ low-passed at 20 Hz), the chain
learned from the training part alone; ``nmse_mean`` beside the least squares with the true
kinematics (0.010 in that bench).

Writes ``bench/results/learned_chain.json`` (``--out``) and each learned arm beside it as
``learned_chain_<arm>.urdf``. Goals (issue 33): torque NRMSE <= 0.03, axes
within 5 degrees, fit <= 600 s; real Panda nMSE mean <= 0.03.
"""

import argparse
import dataclasses
import datetime
import json
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
for path in (ROOT, HERE):
    if path not in sys.path:
        sys.path.insert(0, path)

RESULTS = os.path.join(HERE, 'results', 'learned_chain.json')
ARMS = {'ur5': 'sim_arm_ur5.yaml', 'panda': 'sim_arm_panda.yaml'}
TRAIN_S, HELD_S, RATE = 30.0, 10.0, 100.0
TORQUE_SIGMA = 0.05
GOALS = {'torque_nrmse_heldout': 0.03, 'axis_error_deg_max': 5.0, 'fit_s': 600.0,
         'real_panda_nmse_mean': 0.03}


def _values(arm):
    import yaml
    with open(os.path.join(ROOT, 'config', ARMS[arm]), encoding='utf-8') as f:
        return yaml.safe_load(f)['/**/sim_arm']['ros__parameters']


def simulated(arm):
    """Return (UrdfArm, training Dataset, held-out Dataset) of an arm (module docstring)."""
    from rkgnn_ros.core.sim.servo import Servo
    from rkgnn_ros.core.sim.simulate import simulate
    from rkgnn_ros.core.sim.trajectories import SumOfSines
    from rkgnn_ros.core.sim.urdf_arm import UrdfArm
    values = _values(arm)
    sim = UrdfArm(values['robot_description'], values['urdf']['joints'],
                  viscous=values['viscous'], coulomb=values['coulomb'])
    if 'armature' in values['urdf']:
        sim.set_armature(values['urdf']['armature'])
    home = np.array(values['urdf']['home'], dtype=float)
    amplitude = float(values.get('reference', {}).get('amplitude', 0.5))
    servo = Servo(np.array(values['kp']), np.array(values['kd']))
    n = home.size
    train = simulate(sim, servo, SumOfSines.random(n, np.random.default_rng(1), n_terms=3,
                                                   amplitude=amplitude, offsets=home),
                     TRAIN_S, rate=RATE, joint_names=sim.joint_names)
    held = simulate(sim, servo, SumOfSines.random(n, np.random.default_rng(7), n_terms=3,
                                                  amplitude=0.8 * amplitude,
                                                  offsets=home + 0.2),
                    HELD_S, rate=RATE, joint_names=sim.joint_names)
    return sim, train, held


def torque_nrmse(arm, held):
    """Return the torque error per joint on held-out data (module docstring)."""
    from rkgnn_ros.core.fitting.rigid_fit import _prepare, torque_errors
    rows, _, _ = _prepare(arm.structure, [held], [], TORQUE_SIGMA, False)
    return torque_errors(arm, rows)


def run_arm(name, settings, log, path=RESULTS):
    """Return the figures of one simulated arm."""
    from rkgnn_ros.core.fitting.chain_fit import fit_chain
    from rkgnn_ros.core.fitting.rigid_fit import fit_torque
    from rkgnn_ros.core.rigid.chain import axis_errors, chain_of
    from rkgnn_ros.core.rigid.structure import RigidStructure
    sim, train, held = simulated(name)
    truth = RigidStructure(sim.urdf, sim.joint_names)
    wall, cpu = time.perf_counter(), time.process_time()
    found = fit_chain([train], settings=settings, log=log)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    if found is None:
        return {'error': 'fit_chain returned None'}
    errors = torque_nrmse(found.arm, held)
    axes = axis_errors(found.chain, chain_of(truth))
    reference = fit_torque(truth, [train], [])
    out = {'torque_nrmse_heldout': float(np.max(errors)),
           'torque_nrmse_heldout_per_joint': errors.tolist(),
           'axis_error_deg_max': axes['aligned_deg_max'],
           'axis_error_deg': axes['aligned_deg'],
           'axis_pairwise_deg_max': axes['pairwise_deg_max'],
           'gravity_tilt_error_deg': axes['gravity_deg'], 'mirror_image': axes['mirrored'],
           'fit_s': wall, 'fit_cpu_s': cpu, 'consistent': found.arm.consistent(),
           'urdf_torque_nrmse_heldout': float(np.max(torque_nrmse(reference.arm, held))),
           'report': found.report}
    _write_urdf(name, found, path)
    return out


def _write_urdf(name, found, out):
    """Write the learned arm's URDF beside the results: ``<out without .json>_<arm>.urdf``."""
    path = f'{os.path.splitext(out)[0]}_{name}.urdf'
    with open(path, 'w', encoding='utf-8') as f:
        f.write(found.urdf(f'bench/learned_chain.py, {name}, '
                           f'{datetime.date.today().isoformat()}'))


def run_real_panda(settings, log, data, path=RESULTS):
    """Return the real Panda figures (module docstring)."""
    import real_panda
    from rkgnn_ros.core.fitting.chain_fit import fit_chain
    from rkgnn_ros.core.rigid.chain import axis_errors, chain_of
    from rkgnn_ros.core.rigid.structure import RigidStructure
    t, theta, theta_dot, tau = real_panda.load(data)
    grid, (theta, theta_dot, tau) = real_panda.resample(t, theta, theta_dot, tau)
    train, held = real_panda.parts(grid, theta, theta_dot, tau)
    wall, cpu = time.perf_counter(), time.process_time()
    found = fit_chain([train.dataset()], settings=settings, log=log)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    if found is None:
        return {'error': 'fit_chain returned None'}
    nmse = held.nmse(found.arm.inverse_dynamics(held.theta, held.theta_dot, held.theta_ddot))
    axes = axis_errors(found.chain, chain_of(RigidStructure(*_urdf_panda())))
    _write_urdf('real_panda', found, path)
    return {'nmse_mean': float(np.mean(nmse)), 'nmse_per_joint': nmse.tolist(),
            'axis_error_deg_max': axes['aligned_deg_max'], 'axis_error_deg': axes['aligned_deg'],
            'axis_pairwise_deg_max': axes['pairwise_deg_max'],
            'fit_s': wall, 'fit_cpu_s': cpu, 'consistent': found.arm.consistent(),
            'report': found.report}


def _urdf_panda():
    import real_panda
    from rkgnn_ros.core.sim.urdf_arm import UrdfArm
    arm = UrdfArm(real_panda.URDF)
    return arm.urdf, arm.joint_names


def main(argv=None) -> int:
    """Run the bench and write bench/results/learned_chain.json."""
    from rkgnn_ros.core.fitting.chain_fit import ChainSettings
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0].strip())
    parser.add_argument('--arms', default='ur5,panda,real_panda')
    parser.add_argument('--seed', type=int, default=0, help="of fit_chain's starts and rows")
    parser.add_argument('--data', default=os.path.join(ROOT, '..', 'shared', 'data',
                                                       'panda_gaz2019'))
    parser.add_argument('--out', default=RESULTS)
    parser.add_argument('--merge', action='store_true', help='keep entries not rerun')
    parser.add_argument('--set', action='append', default=[],
                        help='a ChainSettings field, e.g. --set refine_blocks=120')
    args = parser.parse_args(argv)
    import real_panda
    blas = real_panda.single_threaded_blas()
    results = {}
    if args.merge and os.path.exists(args.out):
        with open(args.out, encoding='utf-8') as f:
            results = json.load(f)
    fields = {f.name: f.type for f in dataclasses.fields(ChainSettings)}
    changes = {}
    for item in args.set:
        key, _, value = item.partition('=')
        kind = fields[key]
        changes[key] = (value == 'true' if kind is bool
                        else kind(value) if kind in (int, float) else float(value))
    settings = ChainSettings(seed=args.seed, **changes)

    def log(text):
        print('  ' + text, flush=True)

    for name in [a for a in args.arms.split(',') if a]:
        print(f'== {name}', flush=True)
        if name == 'real_panda':
            results[name] = run_real_panda(settings, log, args.data, args.out)
        else:
            results[name] = run_arm(name, settings, log, args.out)
        print(json.dumps({k: (np.round(v, 4).tolist() if isinstance(v, list) else v)
                          for k, v in results[name].items() if k != 'report'}), flush=True)
    results['goals'] = dict(GOALS)
    results['meta'] = {'date': datetime.date.today().isoformat(), 'cpus': os.cpu_count(),
                       'blas': blas, 'seed': args.seed, 'settings': repr(settings),
                       'load_average': os.getloadavg(),
                       'metric': 'module docstring of bench/learned_chain.py'}
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, 'w', encoding='utf-8') as f:
        json.dump(results, f, indent=2)
    return 0


if __name__ == '__main__':
    sys.exit(main())

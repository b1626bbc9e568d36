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

Online (``--online``, issue 33's online figure): the installed ``sim_arm`` on the UR5 and
the Panda (their configs, PD servo, exact sensors, effort published) and the installed
``identifier`` on its defaults but WITHOUT a robot description (its ``robot_description``
topic remapped to one nobody publishes), as processes on a private ROS_DOMAIN_ID, for
``--online-duration`` s (180) of the arm's stamps (``bench/urdf_arms.py``'s ``run_cell``).
Its chain learner (``rkgnn_ros/core/fitting/chain_online.py``) fits the chain in the
background and hands it to the rigid-body policy. ``online_ratio_120s`` per arm: the
published predictions' 2 s-ahead error (RMSE / θ range, mean over joints) over the
predictions started in the 5 s bin ending at 120 s, divided by following the reference's
over the same ones (``bench/online_servos.py``'s ``score``); beside it under ``online``:
both errors, the curve of every 5 s bin, what was published, the identifier's log lines of
the chain learner and the machine's load. ``--merge`` keeps every other entry of the file.

Case 3 (``--case-three``): the same simulated arms' 30 s without effort and no gains given
(``fit_chain(case='unknown')``: the gains are learned with the chain, up to one common
factor); under ``case_three`` per arm: ``axis_error_deg_max`` as above,
``equation_error_heldout`` (the closed loop's equation error on the 10 s held out, RMSE /
std of the servo's torque, the worst joint), ``kp_ratio_error_max`` (the learned Kp over
its mean against the true Kp over theirs, the worst relative error),
``kd_over_kp_error_max`` and ``fit_s`` (the integral's columns in the rows, as by default:
``--set integral=false`` leaves them out). ``--servo pid``: the same under a PID servo (Ki =
0.5 Kp /s), under ``case_three_pid``, with ``ki_over_kp_error_max`` too. With ``--online``
too: the online figure in case 3 (sensors ``no_effort``: no effort
published, no gains given), under ``online_case_three_ratio_120s`` and
``online_case_three`` per arm; with ``--servo`` other than 'pd' the keys end in
``_<servo>`` (``online_case_three_pid``, ...). Case 2 (``--online --case-two``): the
same without effort, the identifier given the servo's PD gains (the sim config's ``kp``,
``kd``), under ``online_case_two_ratio_120s`` and ``online_case_two`` per arm.

Writes ``bench/results/learned_chain.json`` (``--out``) and each learned arm beside it as
``learned_chain_<arm>.urdf``. Goals (issue 33): torque NRMSE <= 0.03, axes
within 5 degrees, fit <= 600 s; real Panda nMSE mean <= 0.03; online ratio at 120 s
<= 1/3.
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
#: Ki / Kp (1/s) of ``--servo pid`` (as bench/urdf_arms.py's pid servo)
PID_KI_PER_KP = 0.5
#: case 3's servos (``--servo``)
SERVOS = ('pd', 'pid')
GOALS = {'torque_nrmse_heldout': 0.03, 'axis_error_deg_max': 5.0, 'fit_s': 600.0,
         'real_panda_nmse_mean': 0.03, 'online_ratio_120s': 1.0 / 3.0}
ONLINE_AT = 120.0
#: the identifier hears no robot description: its topic goes where nobody publishes
NO_DESCRIPTION = ['-r', 'robot_description:=learned_chain_bench_no_description']
#: words of the identifier's log lines that tell the chain learner's story
CHAIN_WORDS = ('chain', 'rigid-body model', 'rigid body of')


def _values(arm):
    import yaml
    with open(os.path.join(ROOT, 'config', ARMS[arm]), encoding='utf-8') as f:
        return yaml.safe_load(f)['/**/sim_arm']['ros__parameters']


def simulated(arm, servo_form='pd'):
    """
    Return (UrdfArm, training Dataset, held-out Dataset) of an arm (module docstring).

    ``servo_form`` 'pid': the config's PD gains and Ki = :data:`PID_KI_PER_KP` Kp.
    """
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
    kp = np.array(values['kp'], dtype=float)
    ki = PID_KI_PER_KP * kp if servo_form == 'pid' else 0.0
    servo = Servo(kp, np.array(values['kd']), ki=ki)
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


def run_case_three(name, settings, log, servo_form='pd'):
    """Return the case-3 figures of one simulated arm under a servo of :data:`SERVOS`."""
    from rkgnn_ros.core.data import Dataset
    from rkgnn_ros.core.fitting.chain_fit import fit_chain
    from rkgnn_ros.core.rigid.chain import axis_errors, chain_of
    from rkgnn_ros.core.rigid.structure import RigidStructure
    sim, train, held = simulated(name, servo_form)

    def without_effort(data):
        return Dataset(data.t, data.theta, data.theta_dot, theta_d=data.theta_d,
                       theta_d_dot=data.theta_d_dot, joint_names=data.joint_names)
    truth = RigidStructure(sim.urdf, sim.joint_names)
    wall = time.perf_counter()
    found = fit_chain([without_effort(train)], [without_effort(held)], settings, log=log,
                      case='unknown')
    wall = time.perf_counter() - wall
    if found is None:
        return {'error': 'fit_chain returned None'}
    values = _values(name)
    kp, kd = np.array(values['kp'], dtype=float), np.array(values['kd'], dtype=float)
    law = found.fit.law
    ratio = (law.kp / law.kp.mean()) / (kp / kp.mean()) - 1.0
    damping = (law.kd / law.kp) / (kd / kp) - 1.0
    extra = {}
    if servo_form == 'pid':
        integral = law.ki / law.kp / PID_KI_PER_KP - 1.0
        extra = {'ki_over_kp_error_max': float(np.max(np.abs(integral))),
                 'ki_over_kp_error': integral.tolist()}
    return {'axis_error_deg_max': axis_errors(found.chain, chain_of(truth))['aligned_deg_max'],
            'equation_error_heldout': float(np.max(found.fit.errors)),
            'equation_error_heldout_per_joint': found.fit.errors.tolist(),
            'kp_ratio_error_max': float(np.max(np.abs(ratio))),
            'kp_ratio_error': ratio.tolist(),
            'kd_over_kp_error_max': float(np.max(np.abs(damping))),
            'form': law.describe(), 'fit_s': wall, 'consistent': found.arm.consistent(),
            'servo': servo_form, **extra, 'load_average': os.getloadavg(),
            'report': found.report}


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


def run_online(name, duration, domain, at=ONLINE_AT, sensors='exact', servo='pd',
               gains=False):
    """
    Return the online figures of one arm (module docstring; 'no_effort': case 3).

    ``gains``: the identifier is given the servo's PD gains (case 2 with 'no_effort').
    """
    import urdf_arms
    log_dir = os.path.join(ROOT, 'log', 'bench')
    prefix = f'learned_chain_online_{name}_{sensors}_{servo}_' + ('gains_' if gains else '')
    given = list(NO_DESCRIPTION)
    if gains:
        values = _values(name)
        given += ['-p', f"kp:={list(map(float, values['kp']))}",
                  '-p', f"kd:={list(map(float, values['kd']))}"]
    began = time.monotonic()
    cell = urdf_arms.run_cell(name, servo, sensors, duration, 2.0, domain, log_dir,
                              identifier_args=given, prefix=prefix, torque=False)
    cell['wall_s'] = time.monotonic() - began
    lines = []
    path = os.path.join(log_dir, prefix + 'identifier.log')
    if os.path.exists(path):
        with open(path, encoding='utf-8', errors='replace') as f:
            lines = [line.strip()[:400] for line in f
                     if any(word in line for word in CHAIN_WORDS)]
    cell['chain_log'] = lines[:40]
    if 'error' in cell:
        return {'online_ratio_120s': None, 'online': cell}
    curve = cell['curve']
    row = next((k for k, end in enumerate(curve['t_end']) if abs(end - at) < 1e-9), None)
    prediction = follow = None
    if row is not None:
        prediction, follow = curve['prediction'][row], curve['follow_reference'][row]
    ratio = prediction / follow if prediction is not None and follow else None
    cell.update(prediction_nrmse_120s=prediction, follow_reference_nrmse_120s=follow)
    return {'online_ratio_120s': ratio, 'online': cell}


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
    parser.add_argument('--case-three', action='store_true',
                        help='case 3 instead: the simulated arms without effort or gains')
    parser.add_argument('--case-two', action='store_true',
                        help="with --online: no effort, the servo's PD gains given")
    parser.add_argument('--servo', choices=SERVOS, default='pd',
                        help="case 3's servo: 'pid' has Ki = 0.5 Kp; its figures go under "
                        "'case_three_pid'")
    parser.add_argument('--online', action='store_true',
                        help='the online figure instead: sim_arm and the identifier without '
                        'a robot description (the arms of --arms other than real_panda)')
    parser.add_argument('--online-duration', type=float, default=180.0)
    parser.add_argument('--domain', type=int, default=None,
                        help='ROS_DOMAIN_ID of the online runs (default from the pid)')
    args = parser.parse_args(argv)
    if args.online:
        return main_online(args)
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
    key_three = 'case_three' if args.servo == 'pd' else f'case_three_{args.servo}'

    def log(text):
        print('  ' + text, flush=True)

    for name in [a for a in args.arms.split(',') if a]:
        print(f'== {name}', flush=True)
        if args.case_three:
            if name in ARMS:
                found = run_case_three(name, settings, log, args.servo)
                results.setdefault(key_three, {})[name] = found
                print(json.dumps({k: v for k, v in found.items() if k != 'report'}),
                      flush=True)
            continue
        if name == 'real_panda':
            results[name] = run_real_panda(settings, log, args.data, args.out)
        else:
            results[name] = run_arm(name, settings, log, args.out)
        print(json.dumps({k: (np.round(v, 4).tolist() if isinstance(v, list) else v)
                          for k, v in results[name].items() if k != 'report'}), flush=True)
    meta = {'date': datetime.date.today().isoformat(), 'cpus': os.cpu_count(),
            'blas': blas, 'seed': args.seed, 'settings': repr(settings),
            'load_average': os.getloadavg(),
            'metric': 'module docstring of bench/learned_chain.py'}
    if args.case_three:
        results.setdefault(key_three, {})['meta'] = meta
    else:
        results['goals'], results['meta'] = dict(GOALS), meta
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, 'w', encoding='utf-8') as f:
        json.dump(results, f, indent=2)
    return 0


def main_online(args) -> int:
    """Run the online figure of each arm and merge it into ``--out`` (module docstring)."""
    results = {}
    if os.path.exists(args.out):
        with open(args.out, encoding='utf-8') as f:
            results = json.load(f)
    names = [a for a in args.arms.split(',') if a in ARMS]
    key = ('online_case_two' if args.case_two else 'online_case_three') + (
        '' if args.servo == 'pd' else f'_{args.servo}')
    closed = args.case_three or args.case_two    # no effort published
    for i, name in enumerate(names):
        domain = (20 + (os.getpid() + 37 * i) % 200 if args.domain is None
                  else args.domain + i)
        print(f'== {name} online, no robot description: {args.online_duration:.0f} s on '
              f'ROS_DOMAIN_ID={domain}', flush=True)
        figures = run_online(name, args.online_duration, domain,
                             sensors='no_effort' if closed else 'exact',
                             servo=args.servo, gains=args.case_two)
        if closed:   # case 3 (no effort, no gains) or 2 (the gains given): their own keys
            figures = {f'{key}_ratio_120s': figures['online_ratio_120s'],
                       key: figures['online']}
        elif args.servo != 'pd':
            figures = {f'online_{args.servo}_ratio_120s': figures['online_ratio_120s'],
                       f'online_{args.servo}': figures['online']}
        entry = results.setdefault(name, {})
        entry.update(figures)
        cell = figures[next(k for k in figures if not k.endswith('_ratio_120s'))]
        print(json.dumps({'ratio_120s': figures[next(iter(figures))],
                          **{k: cell.get(k) for k in (
                              'prediction_nrmse_120s', 'follow_reference_nrmse_120s',
                              'first_model_prediction_s', 'published_sources',
                              'load_average', 'wall_s', 'error')}}), flush=True)
        for line in cell.get('chain_log', []):
            print('  ' + line, flush=True)
    results['goals'] = dict(results.get('goals', {}), **GOALS)
    results.setdefault('meta', {})[key if closed else 'online'] = {
        'date': datetime.date.today().isoformat(), 'cpus': os.cpu_count(),
        'duration_s': args.online_duration, 'at_s': ONLINE_AT, 'servo': args.servo,
        'sensors': 'no_effort' if closed else 'exact', 'gains_given': args.case_two,
        'load_average_end': os.getloadavg(),
        'metric': 'module docstring of bench/learned_chain.py (online)'}
    with open(args.out, 'w', encoding='utf-8') as f:
        json.dump(results, f, indent=2)
    return 0


if __name__ == '__main__':
    sys.exit(main())

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
Wall-time budgets of the offline entry points on a real 7-joint arm, alone and loaded.

The recording: the real Franka Emika Panda excitation trajectory of Gaz et al. (RA-L 2019),
read by path from ``--data`` (default ``../shared/data/panda_gaz2019`` beside the
repository, its README says what it holds; it is never copied into this repository):
20.9 s of θ, θ̇ and the measured joint torque of 7 joints at about 1 kHz (case 1, torque
known). Without that folder the
benchmark says so and writes nothing.

Per entry point, budget (``--budgets``, 10 s and 60 s) and load, in a fresh process each:

- ``fit_best``: the recording resampled to 100 Hz (linear interpolation) as one
  ``Dataset``; ``wall_s`` is the call ``fit_best(data, 'torque', time_budget=budget)``;
- ``identify_bag``: the raw samples written as ``joint_states`` (effort, no commands) into
  a rosbag2 (MCAP) in a temporary folder with the project's ``RecordingWriter``;
  ``wall_s`` is the process ``python -m rkgnn_ros.identify_bag <bag> --budget <budget>
  --params-file config/identifier.yaml`` from start to exit (its budget counts from the
  process's start), with its exit code and the report's verdict.

``alone``: nothing else started by the benchmark (the machine's load is recorded);
``loaded``: a busy loop on each core (``os.cpu_count()`` processes spinning in Python),
started before the cell and stopped after it. ``worst_overrun_ratio`` is the largest
``wall_s / budget_s`` over the cells run (goal: at most 1.1).

Writes ``bench/results/budgets.json`` (``--out``). About 8 minutes for the 8 cells.
"""

import argparse
import datetime
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)

DATA = os.environ.get('RKGNN_PANDA_DATA', os.path.join(
    os.path.dirname(os.path.dirname(os.path.abspath(__file__))), '..', 'shared', 'data',
    'panda_gaz2019'))
JOINTS = tuple(f'panda_joint{j + 1}' for j in range(7))
RATE = 100.0            # Hz of the Dataset fit_best is given
T0 = 1_700_000_000.0    # s, where the recording's stamps start
FILES = ('time', 'positions', 'velocity', 'torques')


def recording(folder: str):
    """Return (t, θ, θ̇, τ) of the Panda recording: (N,), (N, 7) x 3."""
    arrays = [np.loadtxt(os.path.join(folder, f'exciting_traj_{name}.txt')) for name in FILES]
    t, rest = arrays[0], [a.reshape(-1, len(JOINTS)) for a in arrays[1:]]
    if any(a.shape[0] != t.size for a in rest):
        raise ValueError(f'{folder}: the files do not hold the same number of samples')
    return (t, *rest)


def as_dataset(folder: str):
    """Return the recording resampled to :data:`RATE` as one case-1 ``Dataset``."""
    from rkgnn_ros.core.data import Dataset
    t, theta, theta_dot, tau = recording(folder)
    grid = np.arange(0.0, t[-1] - t[0] + 1e-9, 1.0 / RATE)

    def resampled(values):
        return np.stack([np.interp(grid, t - t[0], values[:, j])
                         for j in range(values.shape[1])], axis=1)
    return Dataset(grid, resampled(theta), resampled(theta_dot), tau=resampled(tau),
                   joint_names=JOINTS)


def write_bag(folder: str, path: str) -> int:
    """Write the raw samples as joint_states into a new rosbag2 at ``path``; return count."""
    from rclpy.serialization import serialize_message
    from rkgnn_ros.wire.conversions import make_joint_state, seconds_to_stamp
    from rkgnn_ros.recordings.reader import RecordingWriter
    t, theta, theta_dot, tau = recording(folder)
    with RecordingWriter(path, 'mcap') as bag:
        for k in range(t.size):
            stamp = T0 + t[k] - t[0]
            state = make_joint_state(seconds_to_stamp(stamp), list(JOINTS), theta[k],
                                     theta_dot[k], tau[k])
            bag.write('/joint_states', 'sensor_msgs/msg/JointState',
                      int(round(stamp * 1e9)) + 200_000, serialize_message(state))
    return int(t.size)


def fit_best_cell(folder: str, budget: float) -> dict:
    """Run fit_best once on the resampled recording (in this process); return its figures."""
    from rkgnn_ros.core.fitting.identify import fit_best
    data = as_dataset(folder)
    t0 = time.perf_counter()
    result = fit_best(data, 'torque', time_budget=budget)
    wall = time.perf_counter() - t0
    info = result.model.info
    phases = [h['phase'] for h in result.history]
    return {'wall_s': round(wall, 2), 'budget_s': budget,
            'selected': info.get('selected'), 'cost': _number(info.get('cost')),
            'validation_nrmse': _number(info.get('validation_nrmse')),
            'warning': info.get('warning', ''), 'generations': int(result.generations),
            'stages': {phase: phases.count(phase) for phase in dict.fromkeys(phases)},
            'interrupted': [h['phase'] for h in result.history if h.get('interrupted')]}


def identify_bag_cell(bag: str, budget: float, env) -> dict:
    """Run identify_bag as a process on ``bag``; return its wall time, exit and verdict."""
    out = tempfile.mkdtemp(prefix='budgets_out_')
    try:
        t0 = time.perf_counter()
        done = subprocess.run(
            [sys.executable, '-m', 'rkgnn_ros.identify_bag', bag, '--budget', f'{budget:g}',
             '--params-file', os.path.join(ROOT, 'config', 'identifier.yaml'), '--out', out,
             '--quiet'], env=env, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        cell = {'wall_s': round(wall, 2), 'budget_s': budget, 'exit': done.returncode,
                'stderr': done.stderr.strip().splitlines()[-1:] if done.stderr else []}
        try:
            with open(os.path.join(out, 'report.json'), encoding='utf-8') as f:
                report = json.load(f)
            cell.update(heldout_nrmse=_number(report['heldout']['nrmse']),
                        baselines=report['heldout'].get('baselines', {}),
                        verdict=report.get('verdict', {}).get('text', ''),
                        generations=report['fit']['generations'],
                        fit_budget_s=round(report['fit']['budget_s'], 2),
                        figures=len(report.get('figures', [])))
        except (OSError, ValueError, KeyError) as error:
            cell['report'] = f'unreadable: {error}'
        return cell
    finally:
        shutil.rmtree(out, ignore_errors=True)


def _number(value):
    return None if value is None else float(value)


class BusyLoops:
    """One spinning Python process per core while the block runs (started and ended here)."""

    def __init__(self, count: int):
        self.count = count
        self.processes = []

    def __enter__(self):
        for _ in range(self.count):
            self.processes.append(subprocess.Popen([sys.executable, '-c', 'while True: pass']))
        time.sleep(1.0)   # let them take the cores before the cell starts
        return self

    def __exit__(self, *exc):
        for process in self.processes:
            process.kill()
        for process in self.processes:
            process.wait()
        self.processes = []


def run_cell(entry: str, budget: float, folder: str, bag: str, env) -> dict:
    """Run one cell in a fresh process (fit_best) or as identify_bag's own process."""
    if entry == 'identify_bag':
        return identify_bag_cell(bag, budget, env)
    done = subprocess.run([sys.executable, os.path.abspath(__file__), '--cell', entry,
                           '--budget-s', f'{budget:g}', '--data', folder],
                          env=env, capture_output=True, text=True)
    if done.returncode != 0:
        return {'wall_s': None, 'budget_s': budget, 'error': done.stderr.strip()[-500:]}
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    """Run the cells; write the JSON; return 0 (skipped: the recording is absent)."""
    p = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    p.add_argument('--data', default=DATA, help='folder of the Panda recording')
    p.add_argument('--budgets', type=float, nargs='+', default=[10.0, 60.0])
    p.add_argument('--entries', nargs='+', default=['fit_best', 'identify_bag'],
                   choices=['fit_best', 'identify_bag'])
    p.add_argument('--loads', nargs='+', default=['alone', 'loaded'],
                   choices=['alone', 'loaded'])
    p.add_argument('--out', default=os.path.join(HERE, 'results', 'budgets.json'))
    p.add_argument('--cell', help=argparse.SUPPRESS)        # one fit_best cell, in-process
    p.add_argument('--budget-s', type=float, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.cell:
        print(json.dumps(fit_best_cell(args.data, args.budget_s)), flush=True)
        return 0
    missing = [name for name in FILES
               if not os.path.isfile(os.path.join(args.data, f'exciting_traj_{name}.txt'))]
    if missing:
        print(f'budgets: skipped: the Panda recording is not in {args.data} (no '
              f'exciting_traj_{missing[0]}.txt; --data or RKGNN_PANDA_DATA names it)',
              flush=True)
        return 0
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [ROOT] + [p for p in [os.environ.get('PYTHONPATH')] if p]))
    work = tempfile.mkdtemp(prefix='budgets_')
    results = {}
    try:
        bag = os.path.join(work, 'panda')
        messages = write_bag(args.data, bag) if 'identify_bag' in args.entries else 0
        for load in args.loads:
            for entry in args.entries:
                for budget in args.budgets:
                    before = os.getloadavg()
                    if load == 'loaded':
                        with BusyLoops(os.cpu_count() or 1):
                            cell = run_cell(entry, budget, args.data, bag, env)
                    else:
                        cell = run_cell(entry, budget, args.data, bag, env)
                    cell['load_before'] = [round(x, 2) for x in before]
                    if cell.get('wall_s') is not None:
                        cell['ratio'] = round(cell['wall_s'] / budget, 3)
                    results.setdefault(entry, {}).setdefault(f'{budget:g}s', {})[load] = cell
                    print(f'{entry:12s} budget {budget:5g} s {load:7s}: wall '
                          f'{cell.get("wall_s")} s (ratio {cell.get("ratio")}); '
                          + ', '.join(f'{k} {cell[k]}' for k in
                                      ('exit', 'selected', 'verdict', 'warning') if k in cell),
                          flush=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    ratios = [cell['ratio'] for budgets in results.values() for loads in budgets.values()
              for cell in loads.values() if 'ratio' in cell]
    out = {'date': datetime.date.today().isoformat(), 'cpus': os.cpu_count(),
           'data': {'folder': args.data, 'joints': len(JOINTS), 'fit_best_rate_hz': RATE,
                    'bag_messages': messages},
           'goal': 'worst_overrun_ratio <= 1.1',
           'worst_overrun_ratio': max(ratios) if ratios else None,
           'cells': results}
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, 'w', encoding='utf-8') as f:
        json.dump(out, f, indent=1)
    print(f'worst_overrun_ratio {out["worst_overrun_ratio"]}; wrote {args.out}', flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())

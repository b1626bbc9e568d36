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
Fitness evaluation speed: per-individual Python loop, batched numpy, compiled kernel.

Run from the package root::

    PYTHONPATH=. .venv/bin/python bench/fitness_speed.py

The problem is the paper's (case 1, 3 joints, ``NetworkSpec.paper(3, 'torque')``, 99
genome elements): 1000 samples at 100 Hz of the paper arm under the paper's PD, 4 RKG
substeps per sample, a population of 100 genomes drawn around the initial genome.

That population diverges on single-shooting rollouts (every one of them within about
0.6 s: the initial genome has no gravity term, and the measured torque holds the arm
against gravity), and the compiled kernel stops a rollout at its divergence while the
numpy reference runs on to the end, so timing them there would not compare like with
like. The benchmark therefore uses multiple shooting (a restart from the measured state
every :data:`SHOOTING` samples), which keeps every cost finite and does not change the
work per individual: still 999 x 4 RKG steps of 4 N_f evaluations. The single-shooting
divergence is measured and reported beside the timings.

Timings: the loop (``cost_loop``) on a subset of :data:`LOOP_SUBSET` individuals, scaled
to the population; numpy (``cost_numpy``) and the kernel (``cost``, after one warm-up
call) on the whole population, median of several repeats. Results go to
``bench/results/fitness_speed.json``.
"""

import datetime
import json
import os
import platform
import subprocess
import sys
import time

import numba
import numpy as np
from rkgnn_ros.core.fitting.fitness import FitnessProblem
from rkgnn_ros.core.model.spec import NetworkSpec
from rkgnn_ros.core.sim.plant import PDController, PlanarArm
from rkgnn_ros.core.sim.simulate import simulate
from rkgnn_ros.core.sim.trajectories import paper_reference

POPULATION = 100
SEED = 0
SIGMA = 0.05
SUBSTEPS = 4
SHOOTING = 5
LOOP_SUBSET = 5
FAST_REPEATS = 9
NUMPY_REPEATS = 3
LOOP_REPEATS = 1
RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), 'results',
                       'fitness_speed.json')


def timed(fn, repeats):
    """Return the wall times (s) of ``repeats`` calls of ``fn`` and the last result."""
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return times, out


def max_rel_diff(a, b):
    """Return max |a - b| / |b| over the entries finite in both (inf if the inf sets differ)."""
    a, b = np.asarray(a), np.asarray(b)
    if not np.array_equal(np.isfinite(a), np.isfinite(b)):
        return float('inf')
    fin = np.isfinite(a)
    if not fin.any():
        return 0.0
    return float(np.max(np.abs(a[fin] - b[fin]) / np.abs(b[fin])))


def git_state():
    """Return the commit and whether rkgnn_ros/core differs from it (None outside git)."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    try:
        commit = subprocess.run(['git', 'rev-parse', 'HEAD'], cwd=root, check=True,
                                capture_output=True, text=True).stdout.strip()
        dirty = subprocess.run(['git', 'status', '--porcelain', '--', 'rkgnn_ros/core'],
                               cwd=root, check=True, capture_output=True, text=True).stdout
        return {'commit': commit, 'core_modified': bool(dirty.strip())}
    except (OSError, subprocess.CalledProcessError):
        return {'commit': None, 'core_modified': None}


def main():
    load_before = os.getloadavg()
    data = simulate(PlanarArm.paper(), PDController.paper(), paper_reference(3), 9.99,
                    rate=100)
    spec = NetworkSpec.paper(3, 'torque')
    rng = np.random.default_rng(SEED)
    population = spec.initial_genome() + SIGMA * rng.standard_normal(
        (POPULATION, spec.genome_size))  # (P, 99)
    problem = FitnessProblem(spec, data, substeps=SUBSTEPS, shooting=SHOOTING)
    single = FitnessProblem(spec, data, substeps=SUBSTEPS, shooting=0)
    evaluations = (data.n_samples - 1) * SUBSTEPS * 4  # N_f calls per individual

    print(f'problem: case 1, n = 3, genome {spec.genome_size}, {data.n_samples} samples '
          f'at {1.0 / data.dt:.0f} Hz, substeps {SUBSTEPS}, shooting every {SHOOTING} '
          f'samples, P = {POPULATION} ({evaluations} N_f evaluations per individual)')
    print(f'machine: {os.cpu_count()} CPUs, numba threads {numba.get_num_threads()}, '
          f'load average {load_before[0]:.2f} / {load_before[1]:.2f} / {load_before[2]:.2f}')

    # single shooting with this population: why the benchmark uses multiple shooting
    single_costs = single.cost(population)
    rows = single.rollouts(population)  # (P, N, 6), NaN from the divergence on
    diverged_at = np.where(np.isnan(rows).any(axis=2).any(axis=1),
                           np.argmax(np.isnan(rows).any(axis=2), axis=1), data.n_samples)
    n_single_finite = int(np.isfinite(single_costs).sum())
    print(f'single shooting: {n_single_finite}/{POPULATION} finite costs, rollouts diverge '
          f'at t = {data.dt * diverged_at.min():.2f} .. {data.dt * diverged_at.max():.2f} s')

    # fast path: one warm-up call (compilation or loading from the disk cache), then repeats
    t0 = time.perf_counter()
    problem.cost(population)
    warmup_s = time.perf_counter() - t0
    fast_times, fast_costs = timed(lambda: problem.cost(population), FAST_REPEATS)
    n_finite = int(np.isfinite(fast_costs).sum())
    print(f'finite costs: {n_finite}/{POPULATION}')

    numpy_times, numpy_costs = timed(lambda: problem.cost_numpy(population), NUMPY_REPEATS)
    subset = population[:LOOP_SUBSET]
    loop_times, loop_costs = timed(lambda: problem.cost_loop(subset), LOOP_REPEATS)
    load_after = os.getloadavg()

    fast_s = float(np.median(fast_times))
    numpy_s = float(np.median(numpy_times))
    loop_subset_s = float(np.median(loop_times))
    loop_s = loop_subset_s * POPULATION / LOOP_SUBSET
    diff_fast_numpy = max_rel_diff(fast_costs, numpy_costs)
    diff_loop_numpy = max_rel_diff(loop_costs, numpy_costs[:LOOP_SUBSET])
    diff_fast_loop = max_rel_diff(fast_costs[:LOOP_SUBSET], loop_costs)

    def line(name, seconds, note=''):
        rate = POPULATION / seconds
        print(f'  {name:<34s} {seconds * 1e3:10.1f} ms {rate:12.1f} evals/s '
              f'{rate * evaluations:14.3e} N_f/s {note}')

    print(f'time for the population of {POPULATION}:')
    line('loop (cost_loop)', loop_s,
         f'(measured on {LOOP_SUBSET} individuals: {loop_subset_s * 1e3:.1f} ms, '
         f'scaled x{POPULATION // LOOP_SUBSET})')
    line('numpy (cost_numpy)', numpy_s, f'(median of {NUMPY_REPEATS})')
    line('numba kernel (cost)', fast_s,
         f'(median of {FAST_REPEATS}, after a {warmup_s:.2f} s warm-up)')
    speedup_vs_loop = loop_s / fast_s
    speedup_vs_numpy = numpy_s / fast_s
    print(f'speed-up of the kernel: {speedup_vs_loop:.0f}x the loop (goal >= 150), '
          f'{speedup_vs_numpy:.1f}x numpy (goal >= 5); numpy is '
          f'{loop_s / numpy_s:.1f}x the loop')
    print(f'agreement (max relative difference of finite costs): kernel-numpy '
          f'{diff_fast_numpy:.2e}, loop-numpy {diff_loop_numpy:.2e}, kernel-loop '
          f'{diff_fast_loop:.2e}')
    print(f'load average after: {load_after[0]:.2f} / {load_after[1]:.2f} / '
          f'{load_after[2]:.2f}')

    result = {
        'speedup_vs_loop': speedup_vs_loop,
        'speedup_vs_numpy': speedup_vs_numpy,
        'speedup_numpy_vs_loop': loop_s / numpy_s,
        'evaluations_per_second': {'loop': POPULATION / loop_s, 'numpy': POPULATION / numpy_s,
                                   'kernel': POPULATION / fast_s},
        'timings_s': {
            'kernel_repeats': fast_times, 'kernel_median': fast_s,
            'kernel_warmup': warmup_s,
            'numpy_repeats': numpy_times, 'numpy_median': numpy_s,
            'loop_subset_repeats': loop_times, 'loop_subset_median': loop_subset_s,
            'loop_subset_size': LOOP_SUBSET, 'loop_scaled_to_population': loop_s,
        },
        'max_relative_difference': {'kernel_numpy': diff_fast_numpy,
                                    'loop_numpy': diff_loop_numpy,
                                    'kernel_loop': diff_fast_loop},
        'problem': {
            'case': 'torque', 'network': spec.to_dict(), 'genome_size': spec.genome_size,
            'samples': data.n_samples, 'rate_hz': 1.0 / data.dt, 'substeps': SUBSTEPS,
            'shooting': SHOOTING, 'population': POPULATION, 'seed': SEED, 'sigma': SIGMA,
            'nf_evaluations_per_individual': evaluations, 'finite_costs': n_finite,
            'single_shooting_finite_costs': n_single_finite,
            'single_shooting_divergence_s': [float(data.dt * diverged_at.min()),
                                             float(data.dt * diverged_at.max())],
        },
        'machine': {
            'cpu_count': os.cpu_count(), 'numba_threads': numba.get_num_threads(),
            'numba_threading_layer': _threading_layer(),
            'platform': platform.platform(), 'processor': platform.processor(),
            'python': sys.version.split()[0], 'numpy': np.__version__,
            'numba': numba.__version__,
            'load_average_before': list(load_before), 'load_average_after': list(load_after),
        },
        'code': git_state(),
        'date': datetime.datetime.now(datetime.timezone.utc).isoformat(timespec='seconds'),
    }
    os.makedirs(os.path.dirname(RESULTS), exist_ok=True)
    with open(RESULTS, 'w', encoding='utf-8') as f:
        json.dump(result, f, indent=2)
        f.write('\n')
    print(f'wrote {os.path.relpath(RESULTS)}')
    return 0


def _threading_layer():
    try:
        return numba.threading_layer()
    except ValueError:  # no parallel function has run yet
        return None


if __name__ == '__main__':
    sys.exit(main())

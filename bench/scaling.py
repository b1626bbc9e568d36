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
How the cost of one generation grows with joints, window length and population size.

Times one batched fitness evaluation of a whole population (the compiled kernel, after a
warm-up, median of repeats) on simulated data of an n-link planar arm under PD control,
varying one factor at a time around the default (3 joints, 1000 samples, population 100,
3 RBF units, 4 substeps, case 2). Fits the log-log growth exponent of each factor.

Expected, and what the fit checks: the work is one rollout per individual, each step
evaluating N_f: the RBF outputs (units x n² M entries, n³ B and C terms for the paper's
learned V), a Cholesky solve (n³/3) and the Christoffel terms (n³ per unit). So time is
linear in the window and the population (exponent 1; below 1 while the parallel kernel's
fixed overhead still matters) and between quadratic and cubic in n.

``linear_fit``: the closed-form fit that starts the global network
(:class:`~rkgnn_ros.core.fitting.linear.LinearDynamics` on the tied planar trigonometric
basis, torque measured, its ridge and θ̈ window chosen on held-out samples, M certified
positive on the joint range where the certificate is attempted: up to 4 joints) on 20 s of
100 Hz data, per joint count (median of ``--repeats``; goals 0.5 s at 3 joints, 3 s at 6).
Writes ``bench/results/scaling.json``.
"""

import argparse
import datetime
import json
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from rkgnn_ros.core.fitting.fitness import FitnessProblem  # noqa: E402
from rkgnn_ros.core.fitting.linear import LinearDynamics  # noqa: E402
from rkgnn_ros.core.model.spec import NetworkSpec  # noqa: E402
from rkgnn_ros.core.model.trig import TrigBasis  # noqa: E402
from rkgnn_ros.core.sim.parameters import ArmParameters  # noqa: E402
from rkgnn_ros.core.sim.plant import PDController, PlanarArm  # noqa: E402
from rkgnn_ros.core.sim.simulate import simulate  # noqa: E402
from rkgnn_ros.core.sim.trajectories import paper_reference  # noqa: E402


def arm(n):
    """Return an n-link arm like the paper's (masses and lengths shrinking outwards)."""
    masses = np.linspace(6.0, 2.0, n)
    lengths = np.linspace(0.3, 0.1, n)
    params = ArmParameters(masses=masses, lengths=lengths, viscous=np.full(n, 0.3),
                           coulomb=np.full(n, 0.1))
    return PlanarArm(params), PDController(np.full(n, 40.0), np.full(n, 5.0))


def time_generation(n, samples, population, repeats, seed=0):
    """Return the median seconds of one population's fitness on the given sizes."""
    plant, pd = arm(n)
    data = simulate(plant, pd, paper_reference(n), (samples - 1) / 100.0, rate=100.0)
    spec = NetworkSpec.recommended(n, 'pd_gains')
    problem = FitnessProblem(spec, [data], kp=np.full(n, 40.0), kd=np.full(n, 5.0),
                             substeps=4, shooting=5)
    rng = np.random.default_rng(seed)
    genomes = spec.initial_genome() + 0.05 * rng.standard_normal((population,
                                                                  spec.genome_size))
    problem.cost(genomes)  # compile / warm up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        problem.cost(genomes)
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def time_linear_fit(n, repeats, seconds=20.0):
    """Return the median seconds of the closed-form fit on ``seconds`` of 100 Hz data."""
    plant, pd = arm(n)
    data = simulate(plant, pd, paper_reference(n), seconds, rate=100.0)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        LinearDynamics(TrigBasis(n, planar=True, tied=True)).fit([data], 'torque')
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def exponent(xs, ys):
    """Return the least-squares slope of log y over log x."""
    return float(np.polyfit(np.log(xs), np.log(ys), 1)[0])


def main(argv=None):
    """Measure the three sweeps; write scaling.json."""
    parser = argparse.ArgumentParser(description='generation cost vs problem size')
    parser.add_argument('--repeats', type=int, default=5)
    parser.add_argument('--out', default=os.path.join(HERE, 'results', 'scaling.json'))
    args = parser.parse_args(argv)
    load = os.getloadavg()
    sweeps = {
        'joints': ([2, 3, 4, 6], lambda v: time_generation(v, 1000, 100, args.repeats)),
        'window_samples': ([250, 500, 1000, 2000],
                           lambda v: time_generation(3, v, 100, args.repeats)),
        'population': ([25, 50, 100, 200, 400],
                       lambda v: time_generation(3, 1000, v, args.repeats)),
    }
    result = {'date': datetime.date.today().isoformat(), 'cpus': os.cpu_count(),
              'load_start': load, 'defaults': {'joints': 3, 'window_samples': 1000,
                                               'population': 100, 'theta_units': 3,
                                               'substeps': 4, 'case': 'pd_gains'}}
    for name, (values, measure) in sweeps.items():
        seconds = [measure(v) for v in values]
        slope = exponent(values, seconds)
        result[name] = {'values': values, 'seconds_per_generation': seconds,
                        'growth_exponent': slope}
        shown = '  '.join(f'{v}: {1e3 * s:.1f} ms' for v, s in zip(values, seconds))
        print(f'{name:15s} {shown}  -> exponent {slope:.2f}', flush=True)
    joints = [2, 3, 4, 6]
    seconds = [time_linear_fit(n, args.repeats) for n in joints]
    result['linear_fit'] = {'joints': joints, 'data_s': 20.0, 'rate_hz': 100.0,
                            'seconds': seconds}
    shown = '  '.join(f'{n}: {s:.3f} s' for n, s in zip(joints, seconds))
    print(f'linear fit, 20 s at 100 Hz   {shown}', flush=True)
    result['load_end'] = os.getloadavg()
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, 'w', encoding='utf-8') as f:
        json.dump(result, f, indent=2)
    return 0


if __name__ == '__main__':
    sys.exit(main())

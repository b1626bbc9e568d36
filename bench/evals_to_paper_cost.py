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
Evaluations each optimizer needs to reach the training cost the paper's EA ends with.

Per case: the paper's EA on the paper's structure (population 100, 200 generations, as in
``tools/paper.py``) gives its final best cost J* on the fitting run. Then, on the same
problem (same structure, data and cost), each of our optimizers runs until its best cost
is <= J* or the cap (2x the EA's 20 000 evaluations) is reached: CMA-ES (pycma) from the
default genome, and CMA-ES started from the equation-error fit (our pipeline's first
stage; its residual evaluations are counted too). Writes
``bench/results/evals_to_paper_cost.json``; ``null`` means not reached within the cap.
The EA's run is :func:`_shared.paper_ea`, which ``bench/peers.py`` reuses in the same
``make bench`` (``paper_ea_s`` is the time of the run that computed it).
"""

import argparse
import datetime
import json
import math
import os
import sys
import time

# bench/_shared.py (it puts the checkout on sys.path)
from _shared import paper_ea, structure_evolution
import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from rkgnn_ros.core.fitting.refine import refine_equation_error  # noqa: E402
from rkgnn_ros.core.sim.plant import PDController, PlanarArm  # noqa: E402
from rkgnn_ros.core.sim.simulate import simulate  # noqa: E402
from rkgnn_ros.core.sim.trajectories import paper_reference  # noqa: E402


def run_until(evo, target, cap, used=0):
    """Step until best cost <= target or ``cap`` evaluations; return evaluations or None."""
    while used < cap:
        stats = evo.step()
        used += int(stats['population'])
        if stats['best_cost'] <= target:
            return used
    return None


def main(argv=None):
    """Measure per case; write the JSON."""
    parser = argparse.ArgumentParser(description='evaluations to reach the paper EA cost')
    parser.add_argument('--cases', default='1,2,3')
    parser.add_argument('--generations', type=int, default=200)
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--out', default=os.path.join(HERE, 'results',
                                                      'evals_to_paper_cost.json'))
    args = parser.parse_args(argv)
    pd = PDController.paper()
    data = simulate(PlanarArm.paper(), pd, paper_reference(3), 10.0, rate=100.0)
    result = {'date': datetime.date.today().isoformat(), 'cpus': os.cpu_count(),
              'load_start': os.getloadavg(), 'generations': args.generations}
    for case in args.cases.split(','):
        kp, kd = (np.diag(pd.kp), np.diag(pd.kd)) if case == '2' else (None, None)
        paper, record = paper_ea(case, data, kp, kd, args.generations, args.seed)
        target = float(paper.optimizer.best_cost)
        budget = 100 * args.generations
        cap = 2 * budget
        entry = {'paper_ea_final_cost': target if math.isfinite(target) else None,
                 'paper_ea_evaluations': budget,
                 'paper_ea_s': record['seconds']}
        if math.isfinite(target):
            t0 = time.perf_counter()
            cma = structure_evolution(case, data, kp, kd, 'cmaes', {}, args.seed)
            entry['cmaes'] = run_until(cma, target, cap)
            entry['cmaes_s'] = round(time.perf_counter() - t0, 1)
            t0 = time.perf_counter()
            warm = structure_evolution(case, data, kp, kd, 'cmaes', {'sigma': 0.05},
                                       args.seed)
            nfev = 500
            genome, _ = refine_equation_error(warm.spec, [data], warm.scales,
                                              warm.optimizer.best_x, kp, kd, max_nfev=nfev)
            cost = float(warm.problem.cost(genome[None])[0])
            warm.optimizer.seed_best(genome, cost)
            warm.optimizer.restart(genome, 0.05)
            entry['equation_error_then_cmaes'] = (nfev if cost <= target
                                                  else run_until(warm, target, cap, nfev))
            entry['equation_error_then_cmaes_s'] = round(time.perf_counter() - t0, 1)
        entry['cap'] = cap
        result[case] = entry
        print(f'case {case}: {entry}', flush=True)
    result['load_end'] = os.getloadavg()
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, 'w', encoding='utf-8') as f:
        json.dump(result, f, indent=2)
    return 0


if __name__ == '__main__':
    sys.exit(main())

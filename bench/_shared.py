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
What two benchmarks of one ``make bench`` compute alike, computed once (not a benchmark).

``bench/peers.py`` and ``bench/evals_to_paper_cost.py`` both run the paper's EA on the
paper's structure over the same 10 s fitting run (population 100, the same generations,
seed and cost): the same final genome and cost to the last digit, about 100 s a case.
:func:`paper_ea` runs it once and keeps the result in ``build/bench_cache/`` under a key
made of all it depends on: the case, generations, seed, the fitting run's bytes, the
gains, the versions of Python, numpy and numba, and the bytes of every ``rkgnn_ros``
source file. A change to any of them runs the EA again. ``RKGNN_BENCH_CACHE=off``
turns the cache off; ``RKGNN_BENCH_CACHE=DIR`` moves it.
"""

import glob
import hashlib
import json
import math
import os
import pickle
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

from rkgnn_ros.core.fitting.identify import Evolution  # noqa: E402
from rkgnn_ros.core.model.spec import NetworkSpec  # noqa: E402

CASES = {'1': 'torque', '2': 'pd_gains', '3': 'unknown'}


def cache_dir():
    """Return the cache directory, or None when ``RKGNN_BENCH_CACHE=off``."""
    where = os.environ.get('RKGNN_BENCH_CACHE', '')
    if where.lower() == 'off':
        return None
    return where or os.path.join(ROOT, 'build', 'bench_cache')


def _code_digest():
    """SHA-256 of the rkgnn_ros sources and the numeric libraries' versions."""
    import numba
    h = hashlib.sha256()
    h.update(f'{sys.version}|{np.__version__}|{numba.__version__}'.encode())
    for path in sorted(glob.glob(os.path.join(ROOT, 'rkgnn_ros', '**', '*.py'),
                                 recursive=True)):
        h.update(os.path.relpath(path, ROOT).encode())
        with open(path, 'rb') as f:
            h.update(f.read())
    return h.hexdigest()


def _array_digest(*arrays):
    h = hashlib.sha256()
    for a in arrays:
        if a is None:
            h.update(b'None')
            continue
        a = np.ascontiguousarray(a)
        h.update(f'{a.dtype}{a.shape}'.encode())
        h.update(a.tobytes())
    return h.hexdigest()


def structure_evolution(case, data, kp, kd, optimizer, settings, seed):
    """Return a search of ``optimizer`` on the paper's structure, cost and torque hold."""
    spec = NetworkSpec.paper(data.n_joints, CASES[case])
    return Evolution(spec, data, optimizer, settings, seed, kp, kd,
                     torque_interpolation='hold')


def paper_evolution(case, data, kp, kd, seed):
    """Return the paper's EA on the paper's structure, started as ``make paper`` starts it."""
    return structure_evolution(case, data, kp, kd, 'paper', {'population_size': 100}, seed)


def paper_ea(case, data, kp, kd, generations, seed):
    """
    Run (or reuse) the paper's EA for ``generations``; return (Evolution, record).

    The Evolution holds the final best genome and cost (``optimizer.best_x``,
    ``best_cost``; its ``best_model`` is the fitted model). ``record``: ``start_cost``,
    ``final_cost``, ``evaluations``, ``seconds`` (the EA's own wall time when it ran) and
    ``reused`` (True when it came from the cache).
    """
    evo = paper_evolution(case, data, kp, kd, seed)
    where = cache_dir()
    path = None
    if where is not None:
        key = json.dumps({'what': 'paper_ea', 'case': case, 'generations': int(generations),
                          'seed': int(seed), 'population': 100,
                          'data': _array_digest(data.t, data.state, data.tau,
                                                data.theta_d, data.theta_d_dot),
                          'gains': _array_digest(kp, kd), 'code': _code_digest()},
                         sort_keys=True)
        path = os.path.join(where, 'paper_ea-' + hashlib.sha256(key.encode()).hexdigest()[:24]
                            + '.pkl')
        try:
            with open(path, 'rb') as f:
                record = pickle.load(f)
            evo.optimizer.seed_best(record['genome'], record['final_cost'])
            return evo, dict(record, genome=None, reused=True)
        except (OSError, EOFError, pickle.UnpicklingError, KeyError, ValueError, TypeError):
            pass  # not there (or unreadable): run it
    t0 = time.perf_counter()
    start_cost = float(evo.problem.cost(evo.optimizer.x0[None])[0])
    for _ in range(generations):
        evo.step()
    record = {'start_cost': start_cost if math.isfinite(start_cost) else math.inf,
              'final_cost': float(evo.optimizer.best_cost),
              'evaluations': int(evo.optimizer.evaluations),
              'seconds': round(time.perf_counter() - t0, 1),
              'genome': np.array(evo.optimizer.best_x)}
    if path is not None:
        os.makedirs(where, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=where, suffix='.tmp')
        with os.fdopen(fd, 'wb') as f:
            pickle.dump(record, f)
        os.replace(tmp, path)
    return evo, dict(record, genome=None, reused=False)

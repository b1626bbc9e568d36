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
Run every benchmark in bench/ (``make bench``); each writes its JSON to bench/results/.

Benchmarks measure speed as ratios within one run and accuracy on fixed seeds; none is a
test. Pass names to run a subset: ``python bench/run_all.py fitness_speed``. A run of them
all writes ``bench/results/bench_times.json`` (seconds per script, and in all).
"""

import datetime
import glob
import json
import os
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
LONG = {'soak', 'killtest'}  # 30 min and ~5 min: run by name only


def main(argv=None):
    """Run the selected benchmarks in turn; return non-zero if any failed."""
    argv = sys.argv[1:] if argv is None else argv
    scripts = sorted(p for p in glob.glob(os.path.join(HERE, '*.py'))  # _*.py: shared code
                     if os.path.basename(p) not in ('run_all.py', 'summary.py')
                     and not os.path.basename(p).startswith('_'))
    name = lambda p: os.path.splitext(os.path.basename(p))[0]  # noqa: E731
    if argv:
        scripts = [p for p in scripts if name(p) in argv]
    else:  # the long fault runs only when named (make soak, make killtest)
        scripts = [p for p in scripts if name(p) not in LONG]
    failed = []
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [os.path.dirname(HERE)] + [p for p in [os.environ.get('PYTHONPATH')] if p]))
    start = time.perf_counter()
    times = {}
    for path in scripts:
        name = os.path.basename(path)
        print(f'== {name}', flush=True)
        t0 = time.perf_counter()
        code = subprocess.call([sys.executable, path], env=env)
        times[name] = {'seconds': round(time.perf_counter() - t0, 1), 'exit': code}
        print(f'== {name}: exit {code} after {time.perf_counter() - t0:.0f} s', flush=True)
        if code != 0:
            failed.append(name)
    if not argv:  # the whole of make bench: how long it took, script by script
        with open(os.path.join(HERE, 'results', 'bench_times.json'), 'w',
                  encoding='utf-8') as f:
            json.dump({'date': datetime.date.today().isoformat(), 'cpus': os.cpu_count(),
                       'load_end': os.getloadavg(),
                       'total_s': round(time.perf_counter() - start, 1), 'scripts': times},
                      f, indent=2)
    subprocess.call([sys.executable, os.path.join(HERE, 'summary.py')], env=env,
                    stdout=subprocess.DEVNULL)  # bench/results/README.md from the JSON
    if failed:
        print(f'failed: {failed}', flush=True)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())

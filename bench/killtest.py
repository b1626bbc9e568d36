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
Fault run: SIGKILL the identifier at random moments while it saves its model, 50 times.

Starts the installed ``sim_arm`` once (100 Hz) and, for each round, the installed
``identifier`` with ``model_file`` in a temporary folder. The first round waits for a
model of its own search; later rounds start from the file the previous round left (loaded
and published at start). A client calls ``~/save_model`` back to back and the identifier
is killed with SIGKILL after a random delay (uniform 0.2-1.5 s into the saves). Then the
file must load (``RKGNNModel.load``) and be either the model the round started from or one
the identifier published on ``~/model`` in that round (saves write the published model).

Writes ``bench/results/killtest.json``: ``kills``, ``loadable``, ``old_or_new``, the
saves acknowledged before each kill, and ``leftover_temp_files`` (temp files of killed
saves; the identifier removes them when it next starts). Run with ``make killtest``.
"""

import argparse
import datetime
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import time

from monitor import config, executable, NodeProcesses  # bench/monitor.py
import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from rkgnn_ros.core.model.model import RKGNNModel  # noqa: E402


def main(argv=None):
    """Run the kill rounds; return 0 when every file loaded as the old or a new model."""
    parser = argparse.ArgumentParser(description='SIGKILL the identifier during saves')
    parser.add_argument('--kills', type=int, default=50)
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--domain', type=int, default=None)
    parser.add_argument('--out', default=os.path.join(HERE, 'results', 'killtest.json'))
    args = parser.parse_args(argv)

    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from std_msgs.msg import String
    from std_srvs.srv import Trigger

    rng = random.Random(args.seed)
    domain = args.domain if args.domain is not None else 20 + os.getpid() % 200
    log_dir = os.path.join(os.path.dirname(HERE), 'log', 'bench')
    folder = tempfile.mkdtemp(prefix='rkgnn_killtest_')
    path = os.path.join(folder, 'model.yaml')
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED='1')
    sim = NodeProcesses([('sim_arm', [])], domain, log_dir, prefix='killtest_')
    rounds = []
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain)
    node = rclpy.create_node('killtest_client', context=ctx)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    published = []
    qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
    node.create_subscription(String, 'identifier/model', lambda m: published.append(m.data),
                             qos)
    save = node.create_client(Trigger, 'identifier/save_model')
    try:
        for k in range(args.kills):
            old = RKGNNModel.load(path).genome if os.path.exists(path) else None
            published.clear()
            log = open(os.path.join(log_dir, 'killtest_identifier.log'), 'w', encoding='utf-8')
            proc = subprocess.Popen(
                [executable('identifier'), '--ros-args', '--params-file',
                 config('identifier.yaml'), '-p', f'model_file:={path}', '-p',
                 'min_window:=1.0', '-p', 'model_publish_period:=0.0', '-p',
                 'es.population_size:=8'], env=env, stdout=log, stderr=subprocess.STDOUT)
            try:
                end = time.monotonic() + 90.0
                while not published and time.monotonic() < end:  # a model to save
                    executor.spin_once(timeout_sec=0.05)
                    sim.check()
                if not published:
                    raise RuntimeError(f'round {k}: no model within 90 s')
                assert save.wait_for_service(timeout_sec=10.0)
                delay = rng.uniform(0.2, 1.5)
                kill_at = time.monotonic() + delay
                acknowledged = 0
                future = save.call_async(Trigger.Request())
                while time.monotonic() < kill_at:
                    executor.spin_once(timeout_sec=0.001)
                    if future.done():
                        acknowledged += bool(future.result().success)
                        future = save.call_async(Trigger.Request())
                proc.send_signal(signal.SIGKILL)
                proc.wait(10)
            finally:
                if proc.poll() is None:
                    proc.kill()
                    proc.wait()
                log.close()
            for _ in range(20):  # models still in flight
                executor.spin_once(timeout_sec=0.01)
            try:
                genome = RKGNNModel.load(path).genome
                loadable = True
            except (OSError, ValueError) as exc:
                genome, loadable = None, False
                print(f'round {k}: NOT loadable: {exc}', flush=True)
            new = [RKGNNModel.from_yaml(text).genome for text in published]
            is_old = genome is not None and old is not None and np.array_equal(genome, old)
            is_new = genome is not None and any(np.array_equal(genome, g) for g in new)
            temps = [n for n in os.listdir(folder) if n.endswith('.tmp')]
            rounds.append({'round': k, 'delay_s': round(delay, 3), 'saves': acknowledged,
                           'loadable': loadable, 'old': bool(is_old), 'new': bool(is_new),
                           'temp_files': len(temps)})
            print(f'round {k + 1}/{args.kills}: killed after {delay:.2f} s and {acknowledged} '
                  f"saves: {'loadable' if loadable else 'NOT LOADABLE'}, "
                  f"{'new' if is_new else 'old' if is_old else 'NEITHER'} model, "
                  f'{len(temps)} temp file(s)', flush=True)
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
        sim.stop()
    result = {
        'date': datetime.date.today().isoformat(), 'cpus': os.cpu_count(), 'seed': args.seed,
        'kills': len(rounds), 'loadable': sum(r['loadable'] for r in rounds),
        'old_or_new': sum(r['old'] or r['new'] for r in rounds),
        'saves_acknowledged': sum(r['saves'] for r in rounds),
        'leftover_temp_files': rounds[-1]['temp_files'] if rounds else None,
        'max_temp_files_seen': max((r['temp_files'] for r in rounds), default=None),
        'rounds': rounds,
        'note': 'temp files of killed saves are removed by the identifier when it next '
                'starts (remove_stale_temp_files), so at most one is ever left',
    }
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, 'w', encoding='utf-8') as f:
        json.dump(result, f, indent=2)
    print(json.dumps({k: result[k] for k in ('kills', 'loadable', 'old_or_new',
                                             'saves_acknowledged', 'leftover_temp_files',
                                             'max_temp_files_seen')}, indent=2), flush=True)
    return 0 if result['loadable'] == result['old_or_new'] == result['kills'] else 1


if __name__ == '__main__':
    sys.exit(main())

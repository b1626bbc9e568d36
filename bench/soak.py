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
Soak run: sim_arm + identifier for 30 minutes at 100 Hz, with run-time changes.

Starts the installed ``sim_arm`` and ``identifier`` (the executables ``ros2 run`` starts)
on a private ROS domain. Every 2-8 s (random, seeded) a client sets one ES parameter
through ``~/set_parameters`` -- what ``ros2 param set`` calls -- most of them valid, about
one in six invalid (which must be rejected); every ~2 minutes it calls ``~/reset``. Every
10 s it samples the identifier process's resident memory and thread count
(``/proc/<pid>/status``), the generation and drop counters from ``/diagnostics`` and the
``joint_states`` rate it receives.

Writes ``bench/results/soak.json``: ``rss_growth_fraction`` (resident memory at the end
over minute 5, minus one), ``thread_count_start`` (minute 5) and ``thread_count_end``,
``drops`` (messages the identifier dropped, all reasons) with the per-reason breakdown,
the time series, and the parameter changes applied and rejected. Not a test: run with
``make soak`` or ``python bench/soak.py --minutes 30``.
"""

import argparse
import datetime
import json
import os
import random
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from monitor import NodeProcesses  # noqa: E402


def proc_status(pid):
    """Return (resident memory in MiB, thread count) of a process."""
    rss = threads = None
    with open(f'/proc/{pid}/status', encoding='ascii') as f:
        for line in f:
            if line.startswith('VmRSS:'):
                rss = int(line.split()[1]) / 1024.0
            elif line.startswith('Threads:'):
                threads = int(line.split()[1])
    return rss, threads


def random_change(rng):
    """Return (name, value, should_succeed) for one ros2-param-set-style change."""
    if rng.random() < 1.0 / 6.0:
        return rng.choice([('es.sigma', -0.5, False), ('es.crossover_rate', 1.5, False),
                           ('es.population_size', -3, False), ('es.mutation_rate', 2.0, False),
                           ('es.algorithm', 'simplex', False), ('window', 0.2, False)])
    name = rng.choice(['es.population_size', 'es.sigma', 'es.crossover_rate',
                       'es.mutation_rate', 'es.tournament_size', 'es.algorithm'])
    value = {'es.population_size': lambda: rng.randint(8, 40),
             'es.sigma': lambda: round(rng.uniform(0.05, 1.0), 3),
             'es.crossover_rate': lambda: round(rng.uniform(0.0, 1.0), 3),
             'es.mutation_rate': lambda: round(rng.uniform(0.2, 1.0), 3),
             'es.tournament_size': lambda: rng.randint(2, 6),
             'es.algorithm': lambda: rng.choice(['cmaes', 'sep-cmaes', 'paper'])}[name]()
    return name, value, True


def main(argv=None):
    """Run the soak; return the exit code (non-zero if a node died)."""
    parser = argparse.ArgumentParser(description='30-minute soak of sim_arm + identifier')
    parser.add_argument('--minutes', type=float, default=30.0)
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--domain', type=int, default=None)
    parser.add_argument('--out', default=os.path.join(HERE, 'results', 'soak.json'))
    args = parser.parse_args(argv)

    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from rclpy.qos import qos_profile_sensor_data
    from diagnostic_msgs.msg import DiagnosticArray
    from rcl_interfaces.srv import SetParameters
    from sensor_msgs.msg import JointState
    from std_srvs.srv import Trigger

    rng = random.Random(args.seed)
    domain = args.domain if args.domain is not None else 20 + os.getpid() % 200
    log_dir = os.path.join(os.path.dirname(HERE), 'log', 'bench')
    duration = 60.0 * args.minutes
    nodes = NodeProcesses([('sim_arm', []), ('identifier', [])], domain, log_dir,
                          prefix='soak_')
    pid = nodes.procs[1].pid
    diag = {}
    received = [0]
    samples, changes, resets = [], [], []
    failure = None
    try:
        ctx = rclpy.Context()
        rclpy.init(context=ctx, domain_id=domain)
        node = rclpy.create_node('soak_client', context=ctx)

        def on_diag(msg):
            for status in msg.status:
                if status.name == 'identifier':
                    diag.clear()
                    diag.update({kv.key: kv.value for kv in status.values})

        node.create_subscription(DiagnosticArray, '/diagnostics', on_diag, 10)
        node.create_subscription(JointState, 'joint_states',
                                 lambda m: received.__setitem__(0, received[0] + 1),
                                 qos_profile_sensor_data)
        set_client = node.create_client(SetParameters, 'identifier/set_parameters')
        reset_client = node.create_client(Trigger, 'identifier/reset')
        executor = SingleThreadedExecutor(context=ctx)
        executor.add_node(node)

        def call(client, request, timeout=5.0):
            future = client.call_async(request)
            end = time.monotonic() + timeout
            while not future.done() and time.monotonic() < end:
                executor.spin_once(timeout_sec=0.05)
            return future.result() if future.done() else None

        t0 = time.monotonic()
        next_change = t0 + rng.uniform(2.0, 8.0)
        next_reset = t0 + rng.uniform(100.0, 140.0)
        next_sample = t0 + 10.0
        last_received, last_sample_t = 0, t0
        while time.monotonic() - t0 < duration:
            executor.spin_once(timeout_sec=0.1)
            nodes.check()
            now = time.monotonic()
            if now >= next_change:
                next_change = now + rng.uniform(2.0, 8.0)
                name, value, valid = random_change(rng)
                request = SetParameters.Request(
                    parameters=[Parameter(name, value=value).to_parameter_msg()])
                response = call(set_client, request)
                ok = response is not None and response.results[0].successful
                changes.append({'t': round(now - t0, 1), 'name': name, 'value': value,
                                'valid': valid, 'accepted': ok,
                                'reason': '' if response is None or ok
                                else response.results[0].reason})
            if now >= next_reset:
                next_reset = now + rng.uniform(100.0, 140.0)
                response = call(reset_client, Trigger.Request())
                resets.append({'t': round(now - t0, 1),
                               'success': bool(response is not None and response.success)})
            if now >= next_sample:
                next_sample += 10.0
                rss, threads = proc_status(pid)
                rate = (received[0] - last_received) / (now - last_sample_t)
                last_received, last_sample_t = received[0], now
                drops = {k[len('drops.'):]: int(float(v)) for k, v in diag.items()
                         if k.startswith('drops.')}
                sample = {'t': round(now - t0, 1), 'rss_mib': round(rss, 2),
                          'threads': threads, 'generation': diag.get('generation'),
                          'generations_per_s': diag.get('generations_per_s'),
                          'state': diag.get('state'), 'drops': sum(drops.values()),
                          'joint_states_hz': round(rate, 1), 'load': os.getloadavg()[0]}
                samples.append(sample)
                print(f"[{sample['t']:7.1f} s] rss {sample['rss_mib']:.1f} MiB, "
                      f"{threads} threads, generation {sample['generation']} "
                      f"({sample['generations_per_s']}/s), drops {sample['drops']}, "
                      f'joint_states {rate:.0f} Hz, {len(changes)} changes, '
                      f'{len(resets)} resets', flush=True)
        final_drops = {k[len('drops.'):]: int(float(v)) for k, v in diag.items()
                       if k.startswith('drops.')}
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
    except RuntimeError as exc:  # a node died
        failure = str(exc)
        final_drops = {}
    finally:
        codes = nodes.stop()
    after5 = [s for s in samples if s['t'] >= min(300.0, duration / 3)]
    first = after5[0] if after5 else (samples[0] if samples else None)
    last = samples[-1] if samples else None
    result = {
        'date': datetime.date.today().isoformat(), 'cpus': os.cpu_count(),
        'minutes': args.minutes, 'seed': args.seed, 'publish_rate_hz': 100.0,
        'rss_growth_fraction': (last['rss_mib'] / first['rss_mib'] - 1.0
                                if first and last else None),
        'rss_mib_minute5': first['rss_mib'] if first else None,
        'rss_mib_end': last['rss_mib'] if last else None,
        'thread_count_start': first['threads'] if first else None,
        'thread_count_end': last['threads'] if last else None,
        'drops': int(sum(final_drops.values())), 'drops_by_reason': final_drops,
        'parameter_changes': len(changes),
        'valid_changes_accepted': sum(c['accepted'] for c in changes if c['valid']),
        'valid_changes_rejected': [c for c in changes if c['valid'] and not c['accepted']],
        'invalid_changes_rejected': sum(not c['accepted'] for c in changes if not c['valid']),
        'invalid_changes_accepted': [c for c in changes if not c['valid'] and c['accepted']],
        'resets': resets, 'exit_codes': codes, 'failure': failure,
        'samples': samples,
        'note': 'rss_growth_fraction = RSS at the end / RSS at minute 5 - 1 (identifier '
                'process); thread_count_start is taken at minute 5, after start-up',
    }
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, 'w', encoding='utf-8') as f:
        json.dump(result, f, indent=2)
    summary = {k: result[k] for k in ('rss_growth_fraction', 'thread_count_start',
                                      'thread_count_end', 'drops', 'parameter_changes',
                                      'valid_changes_accepted', 'invalid_changes_rejected',
                                      'exit_codes', 'failure')}
    print(json.dumps(summary, indent=2), flush=True)
    return 1 if failure or any(codes) else 0


if __name__ == '__main__':
    sys.exit(main())

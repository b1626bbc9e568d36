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
Hostile input to the installed nodes, as processes: every break of issues 15 and 31.

Starts the ``identifier`` executable (what ``ros2 run`` starts) on a private ROS domain
and feeds it each break an adversarial pass found: model files that are a FIFO,
``/dev/zero``, an alias bomb, 10^9 substeps, NaN info or 1e308 weights (a process each:
it must start, answer a service and say why it refused the file); then, on one node with
a good model, a save over a device node, float extremes and a parameter named '', one
stamp outlier a second interleaved with good data, malformed raw CDR, over-budget
messages, and 100,000-point reference trajectories at 2 Hz for ``--flood-minutes``. Then
the third probe's breaks (issue 31, :mod:`hostile_probe`): FIFOs, a 1 GB URDF, a junk
recording, bad folders and numbers for identify_bag; URDFs with NaN or inf inertials;
a recording whose joints never move; a forward topic of another type; finite garbage
joint_states with the feed-forward on (``--garbage-seconds``); feed-forwards beyond
sim_arm's default limit, of 10,000 points, and malformed CDR of encapsulation 7 to both
nodes; and 1 kHz streams with random drops and bursts for ``--drop-burst-minutes``.
``--only`` picks groups of breaks (``earlier`` is issue 15's).

Writes ``bench/results/hostile.json``: ``breaks_tested`` (how many breaks were fed),
``breaks_survived`` (those whose documented outcome held), ``tracebacks`` (lines with
'Traceback' in every identifier's log), ``max_rss_mb`` (the largest resident memory of
any identifier process, sampled), ``reference_flood_rss_growth_fraction`` (resident
memory at the end of the flood over its value after the first minute, minus one), and
one entry per break, and ``drop_burst_tracebacks`` (the drop/burst identifier's log). Not a
test: ``python bench/hostile.py`` (about 20 minutes).
"""

import argparse
import datetime
import json
import math
import os
import stat
import sys
import tempfile
import threading
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from monitor import NodeProcesses  # noqa: E402

JOINTS = ('j1', 'j2', 'j3')
PATIENCE = 90.0


def rss_mb(pid):
    """Return the resident memory (MiB) of a process, None if it is gone."""
    try:
        with open(f'/proc/{pid}/status', encoding='ascii') as f:
            for line in f:
                if line.startswith('VmRSS:'):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def wait_for(predicate, timeout, interval=0.1):
    """Poll ``predicate`` until truthy or ``timeout`` s pass; return its last value."""
    end = time.monotonic() + timeout
    while True:
        value = predicate()
        if value or time.monotonic() > end:
            return value
        time.sleep(interval)


class Identifier:
    """One identifier process, its log, and a client node spinning in a thread."""

    def __init__(self, tag, domain, log_dir, extra=()):
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rcl_interfaces.srv import SetParameters
        from rclpy.executors import SingleThreadedExecutor
        from std_srvs.srv import SetBool, Trigger
        self.nodes = NodeProcesses([('identifier', ['-p', f'joints:={list(JOINTS)}'] +
                                     list(extra))], domain, log_dir, prefix=f'hostile_{tag}_')
        self.pid = self.nodes.procs[0].pid
        self.log_path = self.nodes.logs[0].name
        self.max_rss = 0.0
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain)
        self.client = rclpy.create_node(f'hostile_{tag}_client', context=self.context)
        self.lock = threading.Lock()
        self.diag = {}
        self.client.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 10)
        self.set_client = self.client.create_client(SetParameters, 'identifier/set_parameters')
        self.save_client = self.client.create_client(Trigger, 'identifier/save_model')
        self.pause_client = self.client.create_client(SetBool, 'identifier/pause')
        self.SetBool = SetBool
        self.Trigger = Trigger
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.client)
        self.spinner = threading.Thread(target=self.executor.spin, daemon=True)
        self.spinner.start()

    def _on_diag(self, msg):
        for status in msg.status:
            if status.name == 'identifier':
                with self.lock:
                    self.diag = {kv.key: kv.value for kv in status.values}

    def sample_rss(self):
        value = rss_mb(self.pid)
        if value is not None:
            self.max_rss = max(self.max_rss, value)
        return value

    def log(self):
        with open(self.log_path, encoding='utf-8', errors='replace') as f:
            return f.read()

    def call(self, client, request, timeout=PATIENCE):
        if not client.wait_for_service(timeout_sec=timeout):
            return None
        future = client.call_async(request)
        wait_for(future.done, timeout, 0.02)
        return future.result() if future.done() else None

    def set_one(self, name, value):
        from rcl_interfaces.srv import SetParameters
        from rclpy.parameter import Parameter
        request = SetParameters.Request(parameters=[Parameter(name, value=value)
                                                    .to_parameter_msg()])
        response = self.call(self.set_client, request)
        return None if response is None else response.results[0]

    def drops(self, reason):
        with self.lock:
            return int(self.diag.get(f'drops.{reason}', 0))

    def answers(self):
        response = self.call(self.pause_client, self.SetBool.Request(data=False))
        return bool(response is not None and response.success)

    def close(self):
        import rclpy
        self.sample_rss()
        self.executor.shutdown(timeout_sec=2.0)
        self.client.destroy_node()
        rclpy.try_shutdown(context=self.context)
        codes = self.nodes.stop()
        return codes[0], self.log().count('Traceback')


def make_model():
    """Return a 3-joint case-1 model matching config/identifier.yaml's network."""
    from rkgnn_ros.core.fitting.identify import Evolution
    from rkgnn_ros.core.model.network import NetworkSpec
    from rkgnn_ros.core.sim.plant import PDController, PlanarArm
    from rkgnn_ros.core.sim.simulate import simulate
    from rkgnn_ros.core.sim.trajectories import paper_reference
    data = simulate(PlanarArm.paper(), PDController.paper(), paper_reference(3), 6.0,
                    rate=100.0, joint_names=JOINTS)
    model = Evolution(NetworkSpec.recommended(3, 'torque'), [data], seed=0).best_model(JOINTS)
    model.info['cost'] = 1.0
    return model, data


def bad_model_files(model, folder):
    """Return ``{break: path}`` of the model files an adversary leaves."""
    import yaml

    def text(**changes):
        d = model.to_dict()
        for key, value in changes.items():
            *path, last = key.split('__')
            node = d
            for part in path:
                node = node[part]
            node[last] = value
        return yaml.safe_dump(d, sort_keys=False)
    genome = model.genome.tolist()
    genome[::3] = [1e308] * len(genome[::3])
    lines = ['a0: &a0 ["bomb", "bomb", "bomb", "bomb", "bomb", "bomb", "bomb", "bomb"]']
    lines += [f'a{k}: &a{k} [' + ', '.join([f'*a{k - 1}'] * 9) + ']' for k in range(1, 9)]
    files = {'alias_bomb': '\n'.join(lines) + '\n',
             'substeps_1e9': text(integration__substeps=10 ** 9),
             'nan_info': text(info__generation=math.nan, info__cost=math.inf),
             'weights_1e308': text(genome=genome)}
    paths = {}
    for name, content in files.items():
        paths[name] = os.path.join(folder, f'{name}.yaml')
        with open(paths[name], 'w', encoding='utf-8') as f:
            f.write(content)
    paths['fifo'] = os.path.join(folder, 'fifo')
    os.mkfifo(paths['fifo'])
    paths['dev_zero'] = '/dev/zero'
    return paths


def refused_file_break(name, path, domain, log_dir):
    """Start a node on a bad model file: it must start, answer, log the refusal."""
    node = Identifier(name, domain, log_dir, ['-p', f'model_file:={path}'])
    try:
        refused = wait_for(lambda: 'cannot use model_file' in node.log(), PATIENCE)
        answers = node.answers()
        node.sample_rss()
        line = next((row for row in node.log().splitlines() if 'cannot use model_file' in row),
                    '')
    finally:
        code, tracebacks = node.close()
    return {'break': f'model file: {name}', 'survived': bool(refused and answers and
                                                             code == 0 and not tracebacks),
            'exit_code': code, 'tracebacks': tracebacks, 'max_rss_mb': round(node.max_rss, 1),
            'log': line[line.find('cannot use'):][:300]}


def live_breaks(model_path, data, domain, log_dir, folder, flood_minutes):
    """Feed the breaks that need a running node with a good model; return the results."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.serialization import serialize_message
    from rkgnn_ros.wire.conversions import make_joint_state
    from sensor_msgs.msg import JointState
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint
    node = Identifier('live', domain, log_dir, ['-p', f'model_file:={model_path}'])
    results = []
    try:
        assert wait_for(node.answers, PATIENCE), 'the identifier does not answer'
        # a save over a device node (root) or a FIFO: refused, nothing replaced
        target = os.path.join(folder, 'device')
        try:
            os.mknod(target, 0o666 | stat.S_IFCHR, os.makedev(1, 3))
        except PermissionError:
            os.mkfifo(target)
        mode = os.stat(target).st_mode
        node.set_one('model_file', target)
        response = node.call(node.save_client, node.Trigger.Request())
        results.append({'break': 'save over a special file', 'survived': bool(
            response is not None and not response.success and os.stat(target).st_mode == mode),
            'reply': None if response is None else response.message})
        node.set_one('model_file', model_path)
        # float extremes and a nameless parameter: refused at set time
        replies = {f'{name}={value!r}': node.set_one(name, value) for name, value in (
            ('prediction.rate', 1e-300), ('prediction.rate', 1e-9), ('es.sigma', 5e-324),
            ('', 1))}
        results.append({'break': "float extremes and a parameter named ''",
                        'survived': all(r is not None and not r.successful
                                        for r in replies.values()),
                        'reasons': {k: None if r is None else r.reason
                                    for k, r in replies.items()}})
        states = node.client.create_publisher(JointState, 'joint_states', 100)
        commands = node.client.create_publisher(JointState, 'joint_commands', 100)
        wait_for(lambda: states.get_subscription_count() >= 1, PATIENCE)
        # one stamp outlier a second, interleaved with good data at 100 Hz for 15 s
        buffered = []
        t_base = time.time()
        for k in range(1500):
            i = k % data.n_samples
            stamp = t_base + 0.01 * k
            states.publish(make_joint_state(stamp, JOINTS, data.theta[i], data.theta_dot[i],
                                            data.tau[i]))
            commands.publish(make_joint_state(stamp, JOINTS, data.theta_d[i],
                                              data.theta_d_dot[i]))
            if k % 100 == 50:
                rogue = stamp + 3 * 3600.0 if k % 200 == 50 else stamp - 3 * 3600.0
                states.publish(make_joint_state(rogue, JOINTS, data.theta[i],
                                                data.theta_dot[i], data.tau[i]))
            if k % 100 == 99:
                with node.lock:
                    buffered.append(int(node.diag.get('samples_buffered', 0)))
            time.sleep(max(0.0, stamp + 0.01 - time.time()))
        time.sleep(2.0)
        results.append({'break': 'one stamp outlier a second with good data', 'survived': bool(
            node.drops('stamp_outlier') >= 10 and node.drops('clock_jump') == 0
            and buffered[-1] > buffered[len(buffered) // 3] > 0),
            'samples_buffered_each_second': buffered,
            'stamp_outlier': node.drops('stamp_outlier'),
            'clock_jump': node.drops('clock_jump')})
        # malformed raw CDR: counted, and Fast CDR prints nothing
        good = serialize_message(make_joint_state(t_base, JOINTS, data.theta[0],
                                                  data.theta_dot[0], data.tau[0]))
        before = node.drops('malformed')
        for _ in range(100):
            states.publish(good[:20] + b'\xff\xff\xff\x7f' + good[24:])
            time.sleep(0.005)
        wait_for(lambda: node.drops('malformed') > before, 10.0)
        results.append({'break': 'malformed raw CDR', 'survived': bool(
            node.drops('malformed') > before and 'sequence size' not in node.log()),
            'malformed': node.drops('malformed') - before,
            'stderr_lines': node.log().count('sequence size')})
        # over-budget messages: 300 joints, a 10 kB name, a 10,001-point reference
        before = node.drops('over_budget')
        names = list(JOINTS) + [f'x{k}' for k in range(300)]
        states.publish(make_joint_state(t_base, names, [0.0] * len(names),
                                        [0.0] * len(names), [0.0] * len(names)))
        names = list(JOINTS) + ['n' * 10_000]
        states.publish(make_joint_state(t_base, names, [0.0] * 4, [0.0] * 4, [0.0] * 4))
        reference = node.client.create_publisher(JointTrajectory, 'reference_trajectory',
                                                 QoSProfile(depth=1, reliability=(
                                                     ReliabilityPolicy.BEST_EFFORT)))
        wait_for(lambda: reference.get_subscription_count() >= 1, PATIENCE)

        def trajectory(points):
            msg = JointTrajectory(joint_names=list(JOINTS))
            msg.header.stamp.sec = int(t_base)
            for k in range(points):
                point = JointTrajectoryPoint(positions=[0.1, 0.2, 0.3],
                                             velocities=[0.0, 0.0, 0.0])
                point.time_from_start.sec, centis = divmod(k, 100)
                point.time_from_start.nanosec = centis * 10_000_000
                msg.points.append(point)
            return serialize_message(msg)
        reference.publish(trajectory(10_001))
        wait_for(lambda: node.drops('over_budget') >= before + 2, 10.0)
        results.append({'break': 'over-budget messages', 'survived': bool(
            node.drops('over_budget') >= before + 2), 'over_budget':
            node.drops('over_budget') - before})
        # 100,000-point references at 2 Hz
        huge = trajectory(100_000)
        samples = []
        start = time.monotonic()
        k = 0
        while time.monotonic() - start < 60.0 * flood_minutes:
            reference.publish(huge)
            k += 1
            if k % 20 == 0:  # every 10 s
                samples.append((round(time.monotonic() - start, 1), node.sample_rss()))
                print(f'  flood {samples[-1][0]:6.1f} s: identifier RSS {samples[-1][1]:.1f} '
                      'MiB', flush=True)
            time.sleep(max(0.0, start + 0.5 * k - time.monotonic()))
        minute = next((rss for t, rss in samples if t >= 60.0), samples[0][1])
        growth = samples[-1][1] / minute - 1.0
        results.append({'break': f'100,000-point references at 2 Hz for {flood_minutes} min',
                        'survived': bool(growth <= 0.10 and node.answers()),
                        'rss_after_first_minute_mb': round(minute, 1),
                        'rss_end_mb': round(samples[-1][1], 1),
                        'rss_growth_fraction': round(growth, 4), 'messages': k,
                        'rss_samples': samples})
    finally:
        code, tracebacks = node.close()
    for result in results:
        result['exit_code'] = code
    return results, tracebacks, node.max_rss


GROUPS = ('earlier', 'files', 'urdf', 'still', 'forward', 'garbage', 'sim_arm', 'dropburst')


def probe_breaks(groups, domain, log_dir, folder, data, args):
    """Run the third probe's breaks (bench/hostile_probe.py); return (results, drop/burst)."""
    import hostile_probe as probe
    results, drop_burst = [], None
    for group, run in (
            ('files', lambda: probe.file_breaks(domain, folder)),
            ('urdf', lambda: probe.urdf_breaks(domain, folder)),
            ('still', lambda: probe.still_joints_break(domain, folder)),
            ('forward', lambda: probe.forward_topic_breaks(domain)),
            ('garbage', lambda: probe.garbage_break(Identifier, domain, log_dir, data,
                                                    args.garbage_seconds)),
            ('sim_arm', lambda: probe.sim_arm_breaks(domain, log_dir))):
        if group in groups:
            print(f'== {group}', flush=True)
            for result in run():
                print(f"   {result['break']}: survived {result['survived']}", flush=True)
                results.append(result)
    if 'dropburst' in groups:
        print(f'== 1 kHz drops and bursts for {args.drop_burst_minutes:g} min', flush=True)
        drop_burst = probe.drop_burst_stream(Identifier, domain, log_dir, data,
                                             args.drop_burst_minutes)
        print(f"   survived {drop_burst['survived']}, tracebacks {drop_burst['tracebacks']}",
              flush=True)
        results.append(drop_burst)
    return results, drop_burst


def main(argv=None):
    """Feed every break; write bench/results/hostile.json; non-zero if one did not hold."""
    parser = argparse.ArgumentParser(description='hostile input to the identifier')
    parser.add_argument('--flood-minutes', type=float, default=5.0)
    parser.add_argument('--garbage-seconds', type=float, default=60.0,
                        help='finite garbage joint_states with the feed-forward on')
    parser.add_argument('--drop-burst-minutes', type=float, default=5.0,
                        help='1 kHz streams with random drops and bursts')
    parser.add_argument('--only', default=','.join(GROUPS),
                        help=f'comma-separated groups of breaks, of {",".join(GROUPS)}')
    parser.add_argument('--domain', type=int, default=None)
    parser.add_argument('--out', default=os.path.join(HERE, 'results', 'hostile.json'))
    args = parser.parse_args(argv)
    groups = set(args.only.split(','))
    unknown = groups - set(GROUPS)
    if unknown:
        parser.error(f'unknown groups {sorted(unknown)}')
    import rclpy  # noqa: F401 - fail early without ROS
    domain = args.domain if args.domain is not None else 20 + os.getpid() % 200
    log_dir = os.path.join(os.path.dirname(HERE), 'log', 'bench')
    model, data = make_model()
    results, tracebacks, max_rss, flood = [], 0, 0.0, None
    with tempfile.TemporaryDirectory(prefix='hostile_') as folder:
        if 'earlier' in groups:
            from rkgnn_ros.identification.model_file import save_model_file
            model_path = os.path.join(folder, 'model.yaml')
            assert save_model_file(model_path, model)[0]
            for name, path in bad_model_files(model, folder).items():
                print(f'== model file: {name}', flush=True)
                result = refused_file_break(name, path, domain, log_dir)
                print(f"   survived: {result['survived']}; {result['log']}", flush=True)
                results.append(result)
                tracebacks += result['tracebacks']
                max_rss = max(max_rss, result['max_rss_mb'])
            print('== a running node: save, parameters, stamps, CDR, budgets, flood',
                  flush=True)
            live, live_tracebacks, live_rss = live_breaks(model_path, data, domain, log_dir,
                                                          folder, args.flood_minutes)
            results += live
            tracebacks += live_tracebacks
            max_rss = max(max_rss, live_rss)
            flood = next(r for r in live if r['break'].startswith('100,000'))
        probed, drop_burst = probe_breaks(groups, domain, log_dir, folder, data, args)
    results += probed
    tracebacks += sum(r['tracebacks'] for r in probed)
    summary = {
        'date': datetime.date.today().isoformat(), 'cpus': os.cpu_count(),
        'load_average': round(os.getloadavg()[0], 1), 'groups': sorted(groups),
        'breaks_tested': len(results),
        'breaks_survived': sum(bool(r['survived']) for r in results),
        'tracebacks': tracebacks,
        'drop_burst_tracebacks': None if drop_burst is None else drop_burst['tracebacks'],
        'drop_burst_minutes': args.drop_burst_minutes if drop_burst else None,
        'max_rss_mb': round(max_rss, 1),
        'reference_flood_rss_growth_fraction': flood and flood['rss_growth_fraction'],
        'flood_minutes': args.flood_minutes if flood else None,
        'note': 'tracebacks: lines with Traceback in the output of every process fed a break '
                '(identifier, sim_arm, identify_bag); max_rss_mb: the largest resident memory '
                'sampled of any identifier process of the earlier rounds; the flood fraction '
                'is RSS at its end over RSS after its first minute, minus one; '
                'drop_burst_tracebacks: in the identifier fed 1 kHz streams with random '
                'drops and bursts',
        'breaks': results,
    }
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, 'w', encoding='utf-8') as f:
        json.dump(summary, f, indent=2, default=float)
    print(json.dumps({k: summary[k] for k in ('breaks_tested', 'breaks_survived', 'tracebacks',
                                              'drop_burst_tracebacks', 'max_rss_mb',
                                              'reference_flood_rss_growth_fraction')},
                     indent=2), flush=True)
    return 0 if summary['breaks_survived'] == len(results) and not tracebacks else 1


if __name__ == '__main__':
    sys.exit(main())

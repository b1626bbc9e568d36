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
Hostile input, round 3 (issue 31): the nine breaks of the third probe, and drop/burst streams.

Each function feeds one group of breaks to the installed executables as processes and
returns one result per break: ``break``, ``survived`` (its documented refusal held: a
clear message, no traceback, no hang, bounded memory) and ``tracebacks`` (lines with
'Traceback' in the processes' output), with the figures it measured. ``hostile.py`` runs
them after the earlier rounds' breaks and writes them into ``bench/results/hostile.json``.

Memory is compared, not judged absolutely: a process refusing a 300 MB junk file against
the same process refusing a 1 kB one (each one's peak RSS, from ``wait4`` in a small
launcher: a child forked from the benchmark itself would report the benchmark's RSS).
"""

import math
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
JOINTS = ('j1', 'j2', 'j3')
SIM_JOINTS = ('joint1', 'joint2', 'joint3')
PATIENCE = 90.0
HANG_S = 30.0     # a refusal that takes longer than this counts as a hang


#: Starts a command and reports its peak resident memory: forked from this small process,
#: the command's peak is its own (a child forked from the benchmark inherits its RSS).
_LAUNCHER = """
import os, sys
pid = os.fork()
if pid == 0:
    os.execv(sys.argv[1], sys.argv[1:])
_, status, usage = os.wait4(pid, 0)
sys.stdout.write(f'\\nmaxrss_kb={usage.ru_maxrss}\\n')
sys.exit(os.waitstatus_to_exitcode(status))
"""


def run(name, args, domain, timeout=HANG_S):
    """Run an installed executable to its end; return code, output, seconds, peak RSS."""
    from monitor import executable
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED='1')
    with tempfile.TemporaryFile('w+', encoding='utf-8') as out:
        start = time.monotonic()
        proc = subprocess.Popen([sys.executable, '-S', '-c', _LAUNCHER,
                                 executable(name)] + list(args), env=env, stdout=out,
                                stderr=subprocess.STDOUT, start_new_session=True)
        try:
            proc.wait(timeout=timeout)
            hung = False
        except subprocess.TimeoutExpired:
            hung = True
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        out.seek(0)
        text = out.read()
    peak = [line for line in text.splitlines() if line.startswith('maxrss_kb=')]
    return {'code': None if hung else proc.returncode, 'hung': hung,
            'seconds': round(time.monotonic() - start, 2),
            'max_rss_mb': round(int(peak[-1].split('=')[1]) / 1024.0, 1) if peak else None,
            'output': text}


def refused(label, outcome, words, code=1, extra=None):
    """Return the result of a break that must end with ``code`` and say ``words``."""
    text = outcome['output']
    tracebacks = text.count('Traceback')
    said = all(word in text for word in words)
    result = {'break': label, 'survived': bool(outcome['code'] == code and said and
                                               not tracebacks and not outcome['hung']),
              'exit_code': outcome['code'], 'hung': outcome['hung'],
              'seconds': outcome['seconds'], 'tracebacks': tracebacks,
              'said': next((line.strip()[-300:] for line in text.splitlines()
                            if words and words[0] in line), '')}
    result.update(extra or {})
    return result


# --------------------------------------------------------------------------- files and args

def file_breaks(domain, folder):
    """Feed breaks 5 and 6: FIFOs, a 1 GB URDF, a junk recording, bad folders, numbers."""
    results = []
    fifo = os.path.join(folder, 'fifo.mcap')
    os.mkfifo(fifo)
    results.append(refused('identify_bag: a FIFO as the recording',
                           run('identify_bag', [fifo, '--quiet'], domain),
                           ['a FIFO, not a regular file']))
    params = os.path.join(folder, 'params_fifo.yaml')
    os.mkfifo(params)
    results.append(refused('identify_bag: a FIFO as --params-file',
                           run('identify_bag', [fifo, '--params-file', params, '--quiet'],
                               domain), ['a FIFO, not a regular file']))
    urdf_fifo = os.path.join(folder, 'arm_fifo.urdf')
    os.mkfifo(urdf_fifo)
    results.append(refused('sim_arm: a FIFO robot_description',
                           run('sim_arm', ['--ros-args', '-p',
                                           f'robot_description:={urdf_fifo}'], domain),
                           ['a FIFO, not a regular file']))
    small, huge = os.path.join(folder, 'small.urdf'), os.path.join(folder, 'huge.urdf')
    with open(small, 'wb') as f:
        f.write(b'x' * 1024)
    with open(huge, 'wb') as f:
        f.truncate(1024 ** 3)  # sparse: 1 GB that costs no disk
    base = run('sim_arm', ['--ros-args', '-p', f'robot_description:={small}'], domain)
    big = run('sim_arm', ['--ros-args', '-p', f'robot_description:={huge}'], domain)
    growth = big['max_rss_mb'] - base['max_rss_mb']
    result = refused('sim_arm: a 1 GB robot_description', big, ['more than the limit'],
                     extra={'max_rss_mb': big['max_rss_mb'],
                            'rss_over_a_1_kB_file_mb': round(growth, 1)})
    result['survived'] = bool(result['survived'] and growth < 64.0)
    results.append(result)
    junk_small, junk_big = os.path.join(folder, 'junk_s.mcap'), os.path.join(folder,
                                                                             'junk_b.mcap')
    for path, size in ((junk_small, 1024), (junk_big, 300 * 1024 ** 2)):
        with open(path, 'wb') as f:
            f.write(b'\x89MCAP0\r\n' + os.urandom(1024))
            f.truncate(size)
    base = run('identify_bag', [junk_small, '--quiet'], domain)
    big = run('identify_bag', [junk_big, '--quiet'], domain)
    growth = big['max_rss_mb'] - base['max_rss_mb']
    result = refused('identify_bag: a 300 MB junk recording', big, ['cannot open'],
                     extra={'max_rss_mb': big['max_rss_mb'],
                            'rss_over_a_1_kB_file_mb': round(growth, 1)})
    result['survived'] = bool(result['survived'] and growth < 64.0)
    results.append(result)
    empty = os.path.join(folder, 'no_metadata')
    os.makedirs(empty)
    results.append(refused('identify_bag: a folder without metadata.yaml',
                           run('identify_bag', [empty, '--quiet'], domain),
                           ['without metadata.yaml']))
    for args in (['--heldout', '1e308'], ['--budget', 'nan', '--heldout', 'nan']):
        results.append(refused(f'identify_bag {" ".join(args)}',
                               run('identify_bag', [empty] + args, domain),
                               [f'argument {args[0]}'], code=2))
    return results


def planar_urdf(masses, lengths):
    """Return a URDF of a planar arm with point masses at its link tips (masses as text)."""
    links, joints, parent = ['<link name="base"/>'], [], 'base'
    for i, (mass, length) in enumerate(zip(masses, lengths)):
        name = f'link{i + 1}'
        links.append(f'<link name="{name}"><inertial><origin xyz="{length} 0 0"/><mass '
                     f'value="{mass}"/><inertia ixx="0" ixy="0" ixz="0" iyy="0" iyz="0" '
                     'izz="0"/></inertial></link>')
        origin = '0 0 0' if i == 0 else f'{lengths[i - 1]} 0 0'
        joints.append(f'<joint name="joint{i + 1}" type="revolute"><parent link="{parent}"/>'
                      f'<child link="{name}"/><origin xyz="{origin}"/><axis xyz="0 -1 0"/>'
                      '<limit lower="-3" upper="3" effort="100" velocity="5"/></joint>')
        parent = name
    return '<robot name="planar">' + ''.join(links + joints) + '</robot>'


def urdf_breaks(domain, folder):
    """Feed break 7: URDFs with NaN or inf mass, NaN inertia: sim_arm refuses to start."""
    results = []
    for label, xml in (
            ('NaN mass', planar_urdf([2.0, 'nan', 0.5], [0.3, 0.2, 0.1])),
            ('inf mass', planar_urdf([2.0, 1.0, 'inf'], [0.3, 0.2, 0.1])),
            ('NaN inertia', planar_urdf([2.0, 1.0, 0.5], [0.3, 0.2, 0.1]).replace(
                'ixx="0"', 'ixx="nan"', 1))):
        path = os.path.join(folder, f'{label.replace(" ", "_")}.urdf')
        with open(path, 'w', encoding='utf-8') as f:
            f.write(xml)
        outcome = run('sim_arm', ['--ros-args', '-p', f'robot_description:={path}'], domain)
        result = refused(f'sim_arm: a URDF with {label}', outcome, ["link '"])
        result['urdfdom_lines'] = outcome['output'].count('Error:')
        result['survived'] = bool(result['survived'] and not result['urdfdom_lines'])
        results.append(result)
    return results


def still_joints_break(domain, folder):
    """Feed break 8: a recording where 7 of 10 joints never move: identify_bag refuses it."""
    from rclpy.serialization import serialize_message
    from rkgnn_ros.wire.conversions import make_joint_state, seconds_to_stamp
    from rkgnn_ros.core.sim.plant import PDController, PlanarArm
    from rkgnn_ros.core.sim.simulate import simulate
    from rkgnn_ros.core.sim.trajectories import paper_reference
    from rkgnn_ros.recordings.reader import RecordingWriter
    data = simulate(PlanarArm.paper(), PDController.paper(), paper_reference(3), 20.0,
                    rate=100.0)
    names = [f'joint{i + 1}' for i in range(10)]
    still = np.full(7, 0.3)
    bag = os.path.join(folder, 'still')
    with RecordingWriter(bag) as writer:
        for k, t in enumerate(data.t):
            stamp = seconds_to_stamp(1.7e9 + t)
            state = make_joint_state(stamp, names, np.r_[data.theta[k], still],
                                     np.r_[data.theta_dot[k], 0 * still],
                                     np.r_[data.tau[k], 0 * still])
            writer.write('/joint_states', 'sensor_msgs/msg/JointState',
                         int((1.7e9 + t) * 1e9), serialize_message(state))
    outcome = run('identify_bag', [bag, '--quiet', '--max-generations', '3',
                                   '--out', os.path.join(folder, 'still_out')], domain,
                  timeout=PATIENCE)
    return [refused('identify_bag: 7 of 10 joints never move', outcome,
                    ['7 of 10 joints never move'])]


def forward_topic_breaks(domain):
    """Feed break 4: feedforward.forward_topic naming a topic of another type."""
    return [refused(f'identifier: feedforward.forward_topic {topic}',
                    run('identifier', ['--ros-args', '-p', f'joints:={list(JOINTS)}', '-p',
                                       f'feedforward.forward_topic:={topic}'], domain,
                        timeout=PATIENCE), ['refusing to start', 'feedforward.forward_topic'])
            for topic in ('/diagnostics', '/joint_states')]


# --------------------------------------------------------------------------- running nodes

def _encapsulation_7(raw):
    """Return ``raw`` with encapsulation XCDR2 (byte 1 = 7) and a count beyond the end."""
    return raw[:1] + b'\x07' + raw[2:20] + b'\xff\xff\xff\x7f' + raw[24:]


def garbage_break(identifier_cls, domain, log_dir, data, seconds):
    """Feed break 1 (and 3 to the identifier): finite garbage, the feed-forward on; CDR 7."""
    from rclpy.serialization import serialize_message
    from rkgnn_ros.wire.conversions import make_joint_state
    from sensor_msgs.msg import JointState
    node = identifier_cls('garbage', domain, log_dir, [
        '-p', 'case:=torque', '-p', 'feedforward.enabled:=true',
        '-p', 'feedforward.max_effort:=[50.0]'])
    rng = np.random.default_rng(0)
    results = []
    try:
        states = node.client.create_publisher(JointState, 'joint_states', 100)
        from hostile import wait_for
        wait_for(lambda: states.get_subscription_count() >= 1, PATIENCE)
        rss, sent, k = [], 0, 0
        t_base = time.time()
        start = time.monotonic()
        while time.monotonic() - start < seconds:
            i = k % data.n_samples
            stamp = t_base + 0.01 * k + 0.5 * (k // data.n_samples)  # replays after a gap
            if k % 50 == 25:  # 2 a second, on a good sample's stamp, sent first
                values = [rng.uniform(-1, 1, 3) * 10.0 ** rng.uniform(-2, 6, 3)
                          for _ in range(3)]
                states.publish(make_joint_state(stamp, JOINTS, *values))
                sent += 1
            states.publish(make_joint_state(stamp, JOINTS, data.theta[i], data.theta_dot[i],
                                            data.tau[i]))
            if k % 100 == 0:
                rss.append(node.sample_rss())
            k += 1
            time.sleep(max(0.0, start + 0.01 * k - time.monotonic()))
        time.sleep(2.0)
        implausible = sum(node.drops(f'implausible_{what}')
                          for what in ('jump', 'velocity', 'effort'))
        with node.lock:
            cost = float(node.diag.get('best_cost', 'nan'))
        settled = rss[min(10, len(rss) - 1)]
        growth = max(rss) - settled
        results.append({'break': 'identifier: finite garbage joint_states, feed-forward on',
                        'survived': bool(implausible >= 0.9 * sent and growth < 100.0
                                         and math.isfinite(cost) and cost < 1.0
                                         and node.answers()),
                        'garbage_sent': sent, 'implausible_drops': implausible,
                        'best_cost': cost, 'rss_after_10_s_mb': round(settled, 1),
                        'rss_growth_mb': round(growth, 1), 'seconds': seconds})
        good = serialize_message(make_joint_state(t_base, JOINTS, data.theta[0],
                                                  data.theta_dot[0], data.tau[0]))
        before = node.drops('malformed')
        for _ in range(100):
            states.publish(_encapsulation_7(good))
            time.sleep(0.005)
        wait_for(lambda: node.drops('malformed') >= before + 90, 10.0)
        results.append({'break': 'identifier: malformed CDR, encapsulation byte 1 = 7',
                        'survived': bool(node.drops('malformed') >= before + 90
                                         and 'sequence size' not in node.log()),
                        'malformed': node.drops('malformed') - before,
                        'stderr_lines': node.log().count('sequence size')})
    finally:
        code, tracebacks = node.close()
    return _one_process(results, code, tracebacks)


def _trajectory(stamp, efforts, dt=0.01):
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint
    msg = JointTrajectory(joint_names=list(SIM_JOINTS))
    msg.header.stamp.sec, msg.header.stamp.nanosec = int(stamp), int(stamp % 1 * 1e9)
    for k, effort in enumerate(efforts):
        point = JointTrajectoryPoint(positions=[0.0] * 3, velocities=[0.0] * 3,
                                     accelerations=[0.0] * 3, effort=[float(e) for e in effort])
        point.time_from_start.sec, ns = divmod(int(round(k * dt * 1e9)), 1_000_000_000)
        point.time_from_start.nanosec = ns
        msg.points.append(point)
    return msg


def sim_arm_breaks(domain, log_dir):
    """Feed breaks 2, 3 and 9 to sim_arm: beyond its default limit, CDR 7, 10,000 points."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.serialization import serialize_message
    from monitor import NodeProcesses
    from sensor_msgs.msg import JointState
    from trajectory_msgs.msg import JointTrajectory
    from hostile import wait_for
    nodes = NodeProcesses([('sim_arm', [])], domain, log_dir, prefix='hostile_probe_')
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain)
    client = rclpy.create_node('hostile_probe_sim_client', context=context)
    lock, arrivals = threading.Lock(), []

    def on_state(msg):
        with lock:
            arrivals.append((time.monotonic(), msg.header.stamp.sec
                             + msg.header.stamp.nanosec * 1e-9, np.abs(msg.effort).copy()))
    client.create_subscription(JointState, 'joint_states', on_state,
                               QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))
    send = client.create_publisher(JointTrajectory, '/sim_arm/feedforward', 10)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(client)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    log = nodes.logs[0].name

    def text():
        with open(log, encoding='utf-8', errors='replace') as f:
            return f.read()
    results = []
    try:
        wait_for(lambda: len(arrivals) > 100, PATIENCE)
        line = next((row for row in text().splitlines() if 'drive limits' in row), '')
        limits = [float(v) for v in line.split('drive limits ')[1].split(' N m')[0]
                  .split(', ')] if line else []
        for effort in (100.0, 1e4, 1e300):
            with lock:
                now = arrivals[-1][1]
            send.publish(_trajectory(now, [(effort,) * 3] * 200))
            time.sleep(1.0)
        with lock:
            count, peak = len(arrivals), np.max([a[2] for a in arrivals], axis=0)
        wait_for(lambda: len(arrivals) > count + 100, 10.0)
        results.append({'break': 'sim_arm: feed-forwards of 100, 1e4, 1e300 N m, default limit',
                        'survived': bool(limits and 'over_limit' in text() and
                                         np.all(peak <= np.array(limits) * 1.01) and
                                         len(arrivals) > count + 100),
                        'limits_n_m': limits, 'largest_effort_published': peak.tolist()})
        good = serialize_message(_trajectory(0.0, [(0.0,) * 3] * 3))
        for _ in range(100):
            send.publish(_encapsulation_7(good))
            time.sleep(0.005)
        time.sleep(1.0)
        results.append({'break': 'sim_arm: malformed CDR, encapsulation byte 1 = 7',
                        'survived': bool('encapsulation 0x0007' in text()
                                         and 'sequence size' not in text()),
                        'stderr_lines': text().count('sequence size')})
        before = text().count('fell behind')
        with lock:
            now, first = arrivals[-1][1], len(arrivals)
        # serialized once here, so that the benchmark's own Python does not delay the
        # messages; sim_arm's stamps are uniform unless it falls behind and skips ahead
        raw = serialize_message(_trajectory(now, [(0.1, 0.05, 0.01)] * 10_000, dt=0.001))
        for _ in range(10):  # 10,000-point feed-forwards at 10 Hz
            send.publish(raw)
            time.sleep(0.1)
        time.sleep(2.0)
        with lock:
            stamps = np.array([a[1] for a in arrivals[first:]])
        gap = float(np.diff(stamps).max()) if stamps.size > 1 else math.inf
        results.append({'break': 'sim_arm: 10,000-point feed-forwards at 10 Hz',
                        'survived': bool(gap < 0.05 and text().count('fell behind') == before),
                        'largest_stamp_step_s': round(gap, 4), 'messages': 10,
                        'bytes_each': len(raw)})
    finally:
        executor.shutdown(timeout_sec=2.0)
        client.destroy_node()
        rclpy.try_shutdown(context=context)
        code = nodes.stop()[0]
    return _one_process(results, code, text().count('Traceback'))


def _one_process(results, code, tracebacks):
    """Give results fed to one process its exit code; its tracebacks counted once."""
    for index, result in enumerate(results):
        result['exit_code'], result['process_tracebacks'] = code, tracebacks
        result['tracebacks'] = tracebacks if index == 0 else 0
        result['survived'] = bool(result['survived'] and code == 0 and not tracebacks)
    return results


class StateBytes:
    """JointState CDR bytes from one serialized template: the stamp and values written in."""

    def __init__(self, names):
        from rclpy.serialization import serialize_message
        from rkgnn_ros.wire.conversions import make_joint_state
        n = len(names)
        marks = [np.arange(n) + 1000.25 + 100 * field for field in range(3)]
        raw = serialize_message(make_joint_state(0.0, names, *marks))
        self.template = bytearray(raw)
        self.at = [raw.find(mark.astype('<f8').tobytes()) for mark in marks]
        assert min(self.at) > 0, 'the template does not hold its values'
        self.n = n

    def __call__(self, stamp, theta, theta_dot, tau) -> bytes:
        out = bytearray(self.template)
        sec = int(stamp)
        out[4:12] = np.array([sec, int((stamp - sec) * 1e9)], dtype='<u4').tobytes()
        for at, values in zip(self.at, (theta, theta_dot, tau)):
            out[at:at + 8 * self.n] = np.asarray(values, dtype='<f8').tobytes()
        return bytes(out)


def _played(j: int, n: int):
    """
    Return the sample index and the sign of θ̇ of step ``j`` of ``n`` samples played to and fro.

    Forward, then backward with the velocities negated: the stream stays continuous where
    a loop back to the first sample would jump (a jump the plausibility filter drops).
    """
    m = j % (2 * (n - 1))
    return (m, 1.0) if m < n - 1 else (2 * (n - 1) - m, -1.0)


def drop_burst_stream(identifier_cls, domain, log_dir, data, minutes, seed=0):
    """Joint states and commands at 1 kHz with random drops and bursts; count tracebacks."""
    from sensor_msgs.msg import JointState
    from hostile import wait_for
    node = identifier_cls('dropburst', domain, log_dir, ['-p', 'max_rate_hz:=2000.0'])
    rng = np.random.default_rng(seed)
    state_bytes = StateBytes(JOINTS)
    nan = np.full(len(JOINTS), np.nan)
    sent = 0
    try:
        states = node.client.create_publisher(JointState, 'joint_states', 1000)
        commands = node.client.create_publisher(JointState, 'joint_commands', 1000)
        wait_for(lambda: states.get_subscription_count() >= 1, PATIENCE)
        t_base, start, k = time.time(), time.monotonic(), 0
        while time.monotonic() - start < 60.0 * minutes:
            if rng.random() < 0.0005:     # a drop: up to 0.3 s of nothing (8 % in all)
                k += int(rng.integers(1, 300))
            burst = int(rng.integers(2, 50)) if rng.random() < 0.002 else 1
            for _ in range(burst):        # a burst: samples sent back to back, early
                i, sign = _played(k // 10, data.n_samples)
                after, _ = _played(k // 10 + 1, data.n_samples)
                stamp = t_base + 0.001 * k
                frac = (k % 10) / 10.0
                theta = data.theta[i] + frac * (data.theta[after] - data.theta[i])
                states.publish(state_bytes(stamp, theta, sign * data.theta_dot[i],
                                           data.tau[i]))
                commands.publish(state_bytes(stamp, data.theta_d[i],
                                             sign * data.theta_d_dot[i], nan))
                sent += 1
                k += 1
            time.sleep(max(0.0, start + 0.001 * k - time.monotonic()))
        seconds = time.monotonic() - start
        time.sleep(2.0)
        implausible = sum(node.drops(f'implausible_{what}')
                          for what in ('jump', 'velocity', 'effort'))
        answers = node.answers()
    finally:
        code, tracebacks = node.close()
    return {'break': f'1 kHz streams with random drops and bursts for {minutes:g} min',
            'survived': bool(answers and code == 0 and not tracebacks and not implausible),
            'exit_code': code, 'tracebacks': tracebacks, 'states_sent': sent,
            'rate_hz': round(sent / seconds, 1), 'stamped_rate_hz': round(k / seconds, 1),
            'implausible_drops': implausible,
            'max_rss_mb': round(node.max_rss, 1)}

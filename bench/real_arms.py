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
Real arms: a 6-joint URDF arm online, a recording identified offline, namespaced arms.

``--part urdf``: the installed ``sim_arm`` simulates a UR5 (``config/sim_arm_ur5.yaml``:
example-robot-data's URDF, six joints, PD without gravity compensation) at 100 Hz and the
installed ``identifier`` identifies it, case 1 and case 3, for ``--duration`` s each. Every
prediction's θ 2 s ahead is scored against the motion that followed, and so is following
the reference (θd 2 s ahead, from ``joint_commands``) on the same targets; each figure is
the RMSE over predictions started in the 5 s bin ending at 60 s, divided by the θ range,
mean over joints. ``urdf_6dof`` → case → ``prediction_nrmse_60s``,
``follow_reference_nrmse`` (goal: the first at most a third of the second).

``--part bag``: the installed ``sim_arm`` (the paper's arm) and ``identifier`` (case 1,
default parameters) run for ``--record`` s while a recorder writes ``joint_states``,
``joint_commands``, ``reference_trajectory`` and ``identifier/model`` into an MCAP
recording (rosbags). The installed ``identify_bag`` then identifies it with
``config/identifier.yaml``, the last 10 s held out. ``bag`` → ``fit_s`` (the whole
identify_bag run, wall time), ``heldout_nrmse_10s`` (its model predicting the held-out 10 s
from their first state, as the node predicts), ``online_heldout_nrmse_10s`` (the online
identifier's last model recorded before the held-out part, scored the same way).

``--part namespaces``: three installed sim_arm + identifier pairs under ``/arm1`` ..
``/arm3`` in one ROS domain for ``--duration`` s, each arm with joint names of its own (and
other masses). ``namespaces`` → ``arms``, ``models`` (identifiers whose model names their
own arm's joints), ``cross_talk`` (models naming another arm's joints, ``missing_joint``
drops the identifiers counted, and joint_states samples of another arm seen on an arm's
topic), with each process's CPU (% of one core over the run, from /proc) and the
identifiers' receipt-to-publish prediction latency (their /diagnostics).

``--part peer``: the least-squares peer on the same UR5, offline: 40 s simulated under the
same servo (the paper's sines about the home pose) fit the arm's parameters by least
squares on Pinocchio's joint-torque regressor (θ̈ by central differences of θ̇); the fitted
arm then predicts, in closed loop with the servo's known gains, 2 s ahead from every
0.25 s of a held-out 20 s run (other sines), scored like the online figure against
following the reference. ``urdf_6dof_peer`` → ``prediction_nrmse``,
``follow_reference_nrmse``, ``true_model_nrmse``.

Each part updates its own key of ``bench/results/real_arms.json`` and keeps the others.
"""

import argparse
import datetime
import json
import os
import sys
import threading
import time

from monitor import identifier_arguments, Monitor, NodeProcesses  # bench/monitor.py
import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from rkgnn_ros.core.selfcheck import ahead_errors  # noqa: E402

RESULTS = os.path.join(HERE, 'results', 'real_arms.json')
UR5_CONFIG = 'sim_arm_ur5.yaml'
BIN_S = 5.0


class CommandMonitor(Monitor):
    """A :class:`Monitor` that also records ``joint_commands`` (θd at the state stamps)."""

    def __init__(self, context, horizon):
        super().__init__(context, horizon)
        from rclpy.qos import qos_profile_sensor_data
        from sensor_msgs.msg import JointState
        self.command_lock = threading.Lock()
        self.command_t, self.command_theta = [], []
        self.node.create_subscription(JointState, 'joint_commands', self._on_command,
                                      qos_profile_sensor_data)

    def _on_command(self, msg):
        if len(msg.position) == 0:
            return
        with self.command_lock:
            self.command_t.append(self._stamp(msg.header))
            self.command_theta.append(np.array(msg.position, dtype=float))

    def commands(self):
        """Return the recorded (t, θd), sorted by stamp."""
        with self.command_lock:
            t, theta = np.array(self.command_t), np.array(self.command_theta)
        order = np.argsort(t)
        return t[order], theta[order]


def binned(t0, errors, start, theta_range, end):
    """Return the range-normalised RMSE of the errors started in the bin ending at ``end``."""
    sel = (t0 - start > end - BIN_S) & (t0 - start <= end)
    if not np.any(sel):
        return None
    rmse = np.sqrt(np.mean(np.square(errors[sel]), axis=0))
    return float(np.mean(rmse / theta_range))


def follow_reference_errors(t0s, horizon, meas_t, meas_theta, cmd_t, cmd_theta):
    """Return (t0, θd(t0 + h) - θ(t0 + h)) for the prediction starts ``t0s``."""
    out_t, out_e = [], []
    for t0 in t0s:
        target = t0 + horizon
        if not (meas_t[0] <= target <= meas_t[-1] and cmd_t[0] <= target <= cmd_t[-1]):
            continue
        theta = [np.interp(target, meas_t, meas_theta[:, j]) for j in range(meas_theta.shape[1])]
        theta_d = [np.interp(target, cmd_t, cmd_theta[:, j]) for j in range(cmd_theta.shape[1])]
        out_t.append(t0)
        out_e.append(np.array(theta_d) - np.array(theta))
    return np.asarray(out_t), np.asarray(out_e)


def run_urdf_case(case, duration, horizon, domain, log_dir, extra=()):
    """Run sim_arm (UR5) + identifier (``extra``: its parameters) for one case."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from monitor import config
    sim_args = ['--params-file', config(UR5_CONFIG)]
    nodes = NodeProcesses([('sim_arm', sim_args),
                           ('identifier', identifier_arguments(case, horizon, extra))],
                          domain, log_dir, prefix=f'real_arms_case{case}_')
    try:
        ctx = rclpy.Context()
        rclpy.init(context=ctx, domain_id=domain)
        monitor = CommandMonitor(ctx, horizon)
        executor = SingleThreadedExecutor(context=ctx)
        executor.add_node(monitor.node)
        t_start = time.monotonic()
        while time.monotonic() - t_start < duration:
            executor.spin_once(timeout_sec=0.1)
            nodes.check()
        snap = monitor.snapshot()
        cmd_t, cmd_theta = monitor.commands()
        executor.shutdown()
        monitor.node.destroy_node()
        rclpy.try_shutdown(context=ctx)
    finally:
        codes = nodes.stop()
    meas_t, meas_theta, t0s, offs, thetas, evolution, _ = snap
    order = np.argsort(meas_t)
    meas_t, meas_theta = meas_t[order], meas_theta[order]
    start = meas_t[0]
    theta_range = np.ptp(meas_theta, axis=0)
    pt0, err = ahead_errors(t0s, offs, thetas, meas_t, meas_theta, horizon)
    ft0, ferr = follow_reference_errors(pt0, horizon, meas_t, meas_theta, cmd_t, cmd_theta)
    curve = []
    for end in np.arange(BIN_S, duration + 1e-9, BIN_S):
        model = binned(pt0, err, start, theta_range, end)
        follow = binned(ft0, ferr, start, theta_range, end)
        if model is not None:
            curve.append([float(end), model, follow])
    at60 = next(((m, f) for t, m, f in curve if abs(t - 60.0) < 1e-9), (None, None))
    return {'prediction_nrmse_60s': at60[0], 'follow_reference_nrmse': at60[1],
            'ratio_60s': (None if None in at60 or not at60[1] else at60[0] / at60[1]),
            'curve_t_model_follow': curve, 'states': int(meas_t.size),
            'predictions': len(t0s), 'scored': int(pt0.size),
            'generations': int(evolution[-1][0]) if len(evolution) else 0,
            'exit_codes': codes}


def part_urdf(args, log_dir):
    """Run the 6-joint URDF arm online, cases 1 and 3; return the figures."""
    out = {'meta': {'date': datetime.date.today().isoformat(), 'arm': 'UR5 (example-robot-'
                    'data ur5_robot.urdf), 6 moving joints, PD without gravity compensation, '
                    'config/sim_arm_ur5.yaml', 'rate_hz': 100.0,
                    'duration_s': args.duration, 'horizon_s': args.horizon,
                    'metric': '2 s-ahead θ RMSE over predictions started in the 5 s bin '
                              'ending at t, divided by the θ range, mean over joints; '
                              'follow_reference: θd instead of the prediction, same targets',
                    'identifier_params': list(args.identifier_param)}}
    for i, case in enumerate(args.cases.split(',')):
        domain = args.domain + i
        print(f'== urdf_6dof case {case}: {args.duration:.0f} s on ROS_DOMAIN_ID={domain}',
              flush=True)
        extra = [a for p in args.identifier_param for a in ('-p', p)]
        result = run_urdf_case(case, args.duration, args.horizon, domain, log_dir, extra)
        for t, model, follow in result['curve_t_model_follow']:
            print(f'  t = {t:4.0f} s  model {model:8.2%}  follow reference '
                  f'{follow if follow is None else f"{follow:8.2%}"}', flush=True)
        print(f'  case {case}: at 60 s model {result["prediction_nrmse_60s"]}, follow '
              f'{result["follow_reference_nrmse"]}, ratio {result["ratio_60s"]}', flush=True)
        out[case] = result
    return out


class Recorder:
    """Records topics as serialized messages (what ros2 bag record stores)."""

    TOPICS = (('joint_states', 'sensor_msgs/msg/JointState'),
              ('joint_commands', 'sensor_msgs/msg/JointState'),
              ('reference_trajectory', 'trajectory_msgs/msg/JointTrajectory'),
              ('identifier/model', 'std_msgs/msg/String'))

    def __init__(self, context):
        from rclpy.node import Node
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import JointState
        from std_msgs.msg import String
        from trajectory_msgs.msg import JointTrajectory
        classes = {'sensor_msgs/msg/JointState': JointState, 'std_msgs/msg/String': String,
                   'trajectory_msgs/msg/JointTrajectory': JointTrajectory}
        self.node = Node('real_arms_recorder', context=context)
        self.lock = threading.Lock()
        self.messages = []
        for topic, kind in self.TOPICS:
            latched = topic in ('identifier/model', 'reference_trajectory')
            qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                             durability=(DurabilityPolicy.TRANSIENT_LOCAL if latched
                                         else DurabilityPolicy.VOLATILE))
            self.node.create_subscription(
                classes[kind], topic, lambda raw, t=topic, k=kind: self._add(t, k, raw), qos,
                raw=True)

    def _add(self, topic, kind, raw):
        with self.lock:
            self.messages.append(('/' + topic, kind, time.time_ns(), bytes(raw)))

    def write(self, path):
        """Write what was recorded as an MCAP recording at ``path``."""
        from rkgnn_ros.recordings.reader import RecordingWriter
        with self.lock:
            messages = sorted(self.messages, key=lambda m: m[2])
        with RecordingWriter(path, 'mcap') as bag:
            for topic, kind, log_ns, raw in messages:
                bag.write(topic, kind, log_ns, raw)
        return len(messages)


def part_bag(args, log_dir):
    """Record sim_arm + identifier, identify the recording with identify_bag; return figures."""
    import shutil
    import subprocess
    import tempfile
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from monitor import config, executable
    domain = args.domain
    folder = tempfile.mkdtemp(prefix='real_arms_bag_')
    bag = os.path.join(folder, 'sim_arm_60s')
    print(f'== bag: recording {args.record:.0f} s of sim_arm + identifier (case 1) on '
          f'ROS_DOMAIN_ID={domain}', flush=True)
    nodes = NodeProcesses([('sim_arm', []), ('identifier', identifier_arguments(1))],
                          domain, log_dir, prefix='real_arms_bag_')
    try:
        ctx = rclpy.Context()
        rclpy.init(context=ctx, domain_id=domain)
        recorder = Recorder(ctx)
        executor = SingleThreadedExecutor(context=ctx)
        executor.add_node(recorder.node)
        t_start = None  # the recording's time starts with the first joint_states
        while t_start is None or time.monotonic() - t_start < args.record:
            executor.spin_once(timeout_sec=0.1)
            nodes.check()
            if t_start is None and any(m[0] == '/joint_states' for m in recorder.messages):
                t_start = time.monotonic()
        executor.shutdown()
        count = recorder.write(bag)
        recorder.node.destroy_node()
        rclpy.try_shutdown(context=ctx)
    finally:
        codes = nodes.stop()
    print(f'  wrote {count} messages to {bag}', flush=True)
    out = os.path.join(folder, 'identified')
    command = [executable('identify_bag'), bag, '--params-file', config('identifier.yaml'),
               '--heldout', '10', '--budget', str(args.budget), '--out', out]
    print('  ' + ' '.join(command), flush=True)
    t0 = time.monotonic()
    done = subprocess.run(command, text=True)
    fit_s = time.monotonic() - t0
    if done.returncode != 0:
        raise RuntimeError(f'identify_bag exited {done.returncode}')
    with open(os.path.join(out, 'report.json'), encoding='utf-8') as f:
        report = json.load(f)
    result = {'fit_s': fit_s, 'heldout_nrmse_10s': report['heldout']['nrmse'],
              'online_heldout_nrmse_10s': report['heldout']['online_nrmse'],
              'ratio': (report['heldout']['nrmse'] / report['heldout']['online_nrmse']
                        if report['heldout']['online_nrmse'] else None),
              'recorded_s': args.record, 'messages': count, 'budget_s': args.budget,
              'generations': report['fit']['generations'], 'how': report['heldout']['how'],
              'training_s': report['data']['training']['seconds'],
              'drops': report['data']['drops'], 'exit_codes': codes,
              'meta': {'date': datetime.date.today().isoformat(),
                       'arm': 'paper 3-link planar arm, sim_arm defaults, 100 Hz',
                       'identifier': 'case 1, config/identifier.yaml',
                       'metric': 'θ-NRMSE (RMSE / std of θ, mean over joints) of the '
                                 'prediction of the last 10 s from their first state'}}
    print(f'  fit_s {fit_s:.1f}, held-out θ-NRMSE {result["heldout_nrmse_10s"]:.4g}, the '
          f'online model {result["online_heldout_nrmse_10s"]}', flush=True)
    shutil.rmtree(folder, ignore_errors=True)
    return result


def _cpu_seconds(pid):
    """Return the CPU time (user + system, s) of a process so far, None if it is gone."""
    try:
        with open(f'/proc/{pid}/stat', encoding='utf-8') as f:
            fields = f.read().rsplit(')', 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')
    except (OSError, IndexError, ValueError):
        return None


def part_namespaces(args, log_dir):
    """Run three namespaced arm pairs in one domain; return the figures."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from diagnostic_msgs.msg import DiagnosticArray
    from sensor_msgs.msg import JointState
    from std_msgs.msg import String
    from rkgnn_ros.core.fitting.identify import RKGNNModel
    arms = ('arm1', 'arm2', 'arm3')
    names = {arm: [f'{arm}_joint{i}' for i in (1, 2, 3)] for arm in arms}
    domain = args.domain
    print(f'== namespaces: {len(arms)} arm pairs for {args.duration:.0f} s on '
          f'ROS_DOMAIN_ID={domain}', flush=True)
    groups = []
    for k, arm in enumerate(arms):
        masses = [6.0 - k, 4.0, 3.0 + 0.5 * k]
        ns = ['-r', f'__ns:=/{arm}']
        groups.append(NodeProcesses(
            [('sim_arm', ns + ['-p', f'joint_names:={names[arm]}', '-p', f'masses:={masses}']),
             ('identifier', ns)], domain, log_dir, prefix=f'real_arms_{arm}_'))
    lock = threading.Lock()
    models, diagnostics, foreign = {}, {}, dict.fromkeys(arms, 0)
    states = dict.fromkeys(arms, 0)

    def on_state(arm, msg):
        with lock:
            states[arm] += 1
            if list(msg.name) != names[arm]:
                foreign[arm] += 1

    def on_diagnostics(msg):
        for status in msg.status:
            with lock:
                diagnostics[status.hardware_id] = {kv.key: kv.value for kv in status.values}

    try:
        ctx = rclpy.Context()
        rclpy.init(context=ctx, domain_id=domain)
        node = Node('real_arms_namespaces', context=ctx)
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        for arm in arms:
            node.create_subscription(String, f'/{arm}/identifier/model',
                                     lambda m, a=arm: models.__setitem__(a, m.data), latched)
            node.create_subscription(JointState, f'/{arm}/joint_states',
                                     lambda m, a=arm: on_state(a, m), 100)
        node.create_subscription(DiagnosticArray, '/diagnostics', on_diagnostics, 10)
        executor = SingleThreadedExecutor(context=ctx)
        executor.add_node(node)
        pids = {f'/{arm}/{name}': proc.pid for arm, group in zip(arms, groups)
                for name, proc in zip(group.names, group.procs)}
        cpu0 = {key: _cpu_seconds(pid) for key, pid in pids.items()}
        t_start = time.monotonic()
        while time.monotonic() - t_start < args.duration:
            executor.spin_once(timeout_sec=0.1)
            for group in groups:
                group.check()
        elapsed = time.monotonic() - t_start
        cpu = {key: round(100.0 * (_cpu_seconds(pid) - cpu0[key]) / elapsed, 1)
               for key, pid in pids.items()}
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
    finally:
        codes = [group.stop() for group in groups]
    own, cross = 0, 0
    for arm in arms:
        if arm in models:
            joints = list(RKGNNModel.from_yaml(models[arm]).joint_names)
            own += joints == names[arm]
            cross += joints != names[arm]
    missing = {key: int(values.get('drops.missing_joint', 0))
               for key, values in diagnostics.items()}
    latency = {key: {'p50_ms': float(values.get('prediction_latency_p50_ms', 'nan')),
                     'p99_ms': float(values.get('prediction_latency_p99_ms', 'nan'))}
               for key, values in diagnostics.items()}
    cross_talk = cross + sum(missing.values()) + sum(foreign.values())
    result = {'arms': len(arms), 'models': own, 'cross_talk': cross_talk,
              'foreign_models': cross, 'missing_joint_drops': missing,
              'foreign_states': foreign, 'states_seen': states, 'cpu_percent': cpu,
              'prediction_latency': latency, 'duration_s': args.duration,
              'exit_codes': codes,
              'meta': {'date': datetime.date.today().isoformat(),
                       'setup': 'installed sim_arm (planar arm, masses per arm) + identifier '
                                '(case 1, defaults) under /arm1../arm3, one ROS domain',
                       'cpu': '% of one core over the run, user + system, /proc; the '
                              'machine has 2 cores shared with other jobs',
                       'latency': "identifiers' /diagnostics at the end: receipt of the "
                                  'newest state to the publish of its prediction (10 Hz '
                                  'timer, so up to one state period of waiting is in it)'}}
    print(f'  models {own}/{len(arms)}, cross talk {cross_talk}, CPU {cpu}', flush=True)
    print(f'  latency {latency}', flush=True)
    return result


def _ur5_setup():
    """Return the UR5 of config/sim_arm_ur5.yaml: (arm, kp, kd, home)."""
    import yaml
    from rkgnn_ros.core.sim.urdf_arm import UrdfArm
    path = os.path.join(os.path.dirname(HERE), 'config', UR5_CONFIG)
    with open(path, encoding='utf-8') as f:
        values = yaml.safe_load(f)['/**/sim_arm']['ros__parameters']
    arm = UrdfArm(values['robot_description'], joints=values['urdf']['joints'],
                  gravity=values['gravity'], viscous=values['viscous'],
                  coulomb=values['coulomb'])
    return (arm, np.array(values['kp']), np.array(values['kd']),
            np.array(values['urdf']['home']))


class _FittedArm:
    """The arm of least-squares parameters ``p``: θ̈ = M⁻¹ (τ - h) from the regressor."""

    def __init__(self, arm, p):
        self.arm, self.p = arm, p

    def accel(self, theta, theta_dot, tau):
        n = theta.size
        zero = np.zeros(n)
        h = self.arm.regressor(theta, theta_dot, zero) @ self.p
        g = self.arm.regressor(theta, zero, zero) @ self.p
        m = np.stack([self.arm.regressor(theta, zero, e) @ self.p - g for e in np.eye(n)], 1)
        return np.linalg.solve(m, tau - h)


def _closed_loop_rollout(accel, kp, kd, reference, t0, x0, horizon, h=0.002):
    """Return θ at t0 + horizon of the PD loop from x0 (RK4 with step h)."""
    n = x0.size // 2

    def f(t, x):
        theta_d, theta_d_dot = reference.evaluate(t)
        tau = kp * (theta_d - x[:n]) + kd * (theta_d_dot - x[n:])
        return np.concatenate([x[n:], accel(x[:n], x[n:], tau)])

    x, t = x0.copy(), t0
    for _ in range(int(round(horizon / h))):
        k1 = f(t, x)
        k2 = f(t + h / 2, x + h / 2 * k1)
        k3 = f(t + h / 2, x + h / 2 * k2)
        k4 = f(t + h, x + h * k3)
        x, t = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4), t + h
    return x[:n]


def part_peer(args):
    """Fit the UR5 by least squares on its regressor; score 2 s-ahead predictions."""
    from rkgnn_ros.core.sim.servo import Servo
    from rkgnn_ros.core.sim.simulate import simulate
    from rkgnn_ros.core.sim.trajectories import paper_reference, SumOfSines
    arm, kp, kd, home = _ur5_setup()
    paper = paper_reference(arm.n_joints)
    train_ref = SumOfSines(home, paper.amplitudes, paper.frequencies_hz, paper.phases)
    test_ref = SumOfSines.random(arm.n_joints, np.random.default_rng(7), n_terms=4,
                                 amplitude=0.45, max_frequency_hz=0.7, min_frequency_hz=0.15,
                                 offsets=home)
    print('== urdf_6dof_peer: least squares on the UR5 regressor', flush=True)
    train = simulate(arm, Servo(kp, kd), train_ref, 40.0, rate=100.0)
    acc = np.gradient(train.theta_dot, train.t, axis=0)
    rows = slice(1, -1)  # central differences only
    y = arm.regressor(train.theta[rows], train.theta_dot[rows], acc[rows])
    p, *_ = np.linalg.lstsq(y.reshape(-1, y.shape[-1]), train.tau[rows].reshape(-1),
                            rcond=1e-10)
    fitted = _FittedArm(arm, p)
    test = simulate(arm, Servo(kp, kd), test_ref, 20.0, rate=100.0)
    theta_range = np.ptp(test.theta, axis=0)
    horizon = args.horizon
    starts = np.arange(0, int((test.t[-1] - horizon) * 100) + 1, 25)
    errors = {'model': [], 'true': [], 'follow': []}
    for k in starts:
        t0, x0 = test.t[k], np.concatenate([test.theta[k], test.theta_dot[k]])
        target = test.theta[k + int(round(horizon * 100))]
        errors['model'].append(_closed_loop_rollout(fitted.accel, kp, kd, test_ref, t0, x0,
                                                    horizon) - target)
        errors['true'].append(_closed_loop_rollout(
            lambda q, v, tau: arm.forward_dynamics(q, v, tau), kp, kd, test_ref, t0, x0,
            horizon) - target)
        errors['follow'].append(test_ref.evaluate(t0 + horizon)[0] - target)
    figures = {name: float(np.mean(np.sqrt(np.mean(np.square(e), axis=0)) / theta_range))
               for name, e in errors.items()}
    result = {'prediction_nrmse': figures['model'], 'follow_reference_nrmse': figures['follow'],
              'true_model_nrmse': figures['true'], 'predictions': int(starts.size),
              'torque_fit_rmse': float(np.sqrt(np.mean(np.square(
                  y.reshape(-1, y.shape[-1]) @ p - train.tau[rows].reshape(-1))))),
              'meta': {'date': datetime.date.today().isoformat(),
                       'setup': 'UR5 of config/sim_arm_ur5.yaml; fit on 40 s of the paper '
                                'sines about home (θ̈ central differences of θ̇), '
                                'predictions every 0.25 s over a held-out 20 s run (4 random '
                                'sines, seed 7), closed loop with the known PD, RK4 2 ms',
                       'metric': '2 s-ahead θ RMSE / θ range, mean over joints'}}
    print(f'  least squares {figures["model"]:.3%}, true model {figures["true"]:.3%}, '
          f'follow reference {figures["follow"]:.3%} of the θ range', flush=True)
    return result


def update_results(key, value, path=RESULTS):
    """Write ``value`` under ``key`` of the results file, keeping the other keys."""
    results = {}
    if os.path.exists(path):
        with open(path, encoding='utf-8') as f:
            results = json.load(f)
    results[key] = value
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, 'w', encoding='utf-8') as f:
        json.dump(results, f, indent=2)
    print(f'wrote {key} to {path}', flush=True)


def main(argv=None):
    """Run the chosen part; return the exit code."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0].strip())
    parser.add_argument('--part', choices=('urdf', 'bag', 'namespaces', 'peer'),
                        default='urdf')
    parser.add_argument('--cases', default='1,3')
    parser.add_argument('--identifier-param', action='append', default=[], metavar='NAME:=VALUE',
                        help='--part urdf: an identifier parameter for every case (repeatable); '
                        'recorded in meta.identifier_params')
    parser.add_argument('--duration', type=float, default=65.0)
    parser.add_argument('--horizon', type=float, default=2.0)
    parser.add_argument('--record', type=float, default=60.0,
                        help='bag: seconds recorded from the first joint_states')
    parser.add_argument('--budget', type=float, default=90.0,
                        help='bag: identify_bag --budget')
    parser.add_argument('--domain', type=int, default=14,
                        help='ROS_DOMAIN_ID of the first run (next runs: +1, ...)')
    args = parser.parse_args(argv)
    log_dir = os.path.join(os.path.dirname(HERE), 'log', 'bench')
    if args.part == 'urdf':
        update_results('urdf_6dof', part_urdf(args, log_dir))
    elif args.part == 'bag':
        update_results('bag', part_bag(args, log_dir))
    elif args.part == 'namespaces':
        update_results('namespaces', part_namespaces(args, log_dir))
    elif args.part == 'peer':
        update_results('urdf_6dof_peer', part_peer(args))
    return 0


if __name__ == '__main__':
    sys.exit(main())

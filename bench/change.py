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
A payload picked up and released: how fast the identifier sees it and predicts well again.

Each cell runs the installed ``sim_arm`` and ``identifier`` (defaults; case 1 from the
effort) for ``--duration`` s of the arm's time: ``paper`` is the paper's arm without a robot
description and a 2 kg payload at the last tip; ``ur5`` is the UR5 of
``config/sim_arm_ur5.yaml``, its description on the topic, and a 3 kg payload at
(0, 0.02, 0.05) m in its last link's frame. The payload is attached at ``--attach`` s and
released at ``--detach`` s of simulation time (sim_arm's ``payload.*``; its servo is not
told). The arm's time of a cell is its joint_states stamps from the first one received; the
events are placed on it by the stamps sim_arm logs for them (the first states can be
missed while the middleware discovers the publisher, which would put them early). Sensors
``exact`` or ``noisy`` (1e-4 rad of encoder noise, θ̇ by differences).

Figures per cell (2 s-ahead error of what ``~/prediction`` published, RMSE over the
predictions started in each 2 s bin / θ range, mean over joints): ``error_before`` (the
predictions whose target lies in the 10 s before the attachment: those started in the 2 s
before it cross it), ``error_after_peak`` (the worst bin of the 20 s after it; per joint
in ``error_bins_after_per_joint``),
``recovery_s`` (from the attachment to the end of the first 2 s span, slid by 0.1 s from
the attachment on, whose error is at most twice ``error_before``; ``recovery_bins_s`` the
same over the 2 s bins from the attachment), ``detection_delay_s`` (the arm's time when
``~/change`` said it, its newest joint_states stamp then, minus the attachment),
``payload_mass_error`` (fraction) and ``payload_com_error_m`` (the last ``~/payload`` before
10 s after the attachment; described arms only), and the same for the release; per cell
``self_check_worst_ratio`` and ``self_check_worst_joint_ratio``
(:func:`self_check_figures`: the worst 10 s window of what was published against the
better baseline, over the joints and per joint), and ``self_check_without_crossing``: the
same without the predictions started in the horizon before a change (made before it, their
horizon crosses it: no self-check can judge them in advance).
``--false-alarms``: one 10-minute run of the UR5 (each arm of ``--false-alarm-arms``) with
noise, no payload and a task switch at 5 minutes (``reference.switch_at``), counting
``~/change`` messages (``false_alarm_run``, ``false_alarm_run_paper``; their sum is
``false_alarms_10min``).

Writes ``bench/results/change.json``: arm → sensors → the figures; top level
``worst_recovery_s_urdf``, ``worst_recovery_s_no_urdf``, ``false_alarms_10min`` and the
two self-check figures' worst over the cells.
"""

import argparse
import datetime
import json
import os
import re
import sys
import threading
import time

from monitor import config, Monitor, NodeProcesses  # bench/monitor.py
import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))
sys.path.insert(0, HERE)

from rkgnn_ros.core.scoring import ahead_errors  # noqa: E402
from urdf_arms import wait_for_identifier  # noqa: E402

ARMS = {'paper': {'files': [], 'mass': 2.0, 'com': [0.0, 0.0, 0.0]},
        'ur5': {'files': ['sim_arm_ur5.yaml'], 'mass': 3.0, 'com': [0.0, 0.02, 0.05]}}
SENSORS = {'exact': [],
           'noisy': ['-p', 'noise.theta_std:=0.0001', '-p', 'sensors.velocity:=difference']}
BIN = 2.0
SLIDE = 0.1
HORIZON = 2.0
MAX_WALL_FACTOR = 3.0


class Listener:
    """Records θd, ~/change and ~/payload with the arm's newest stamp at their arrival."""

    def __init__(self, node, monitor):
        from diagnostic_msgs.msg import DiagnosticStatus
        from geometry_msgs.msg import InertiaStamped
        from rclpy.qos import DurabilityPolicy, QoSProfile, qos_profile_sensor_data
        from rclpy.qos import ReliabilityPolicy
        from sensor_msgs.msg import JointState
        self.monitor = monitor
        self.lock = threading.Lock()
        self.cmd_t, self.theta_d = [], []
        self.changes, self.payloads = [], []
        latched = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        node.create_subscription(JointState, 'joint_commands', self._on_command,
                                 qos_profile_sensor_data)
        node.create_subscription(DiagnosticStatus, 'identifier/change', self._on_change,
                                 latched)
        node.create_subscription(InertiaStamped, 'identifier/payload', self._on_payload,
                                 latched)

    def _newest(self):
        with self.monitor.lock:
            return self.monitor.meas_t[-1] if self.monitor.meas_t else np.nan

    def _on_command(self, msg):
        if len(msg.position):
            with self.lock:
                self.cmd_t.append(msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec)
                self.theta_d.append(np.array(msg.position, dtype=float))

    def _on_change(self, msg):
        values = {kv.key: kv.value for kv in msg.values}
        with self.lock:
            self.changes.append((self._newest(), float(values.get('time', 'nan'))))

    def _on_payload(self, msg):
        com = [msg.inertia.com.x, msg.inertia.com.y, msg.inertia.com.z]
        with self.lock:
            self.payloads.append((self._newest(), float(msg.inertia.m), com))


def _bins(start, t0, error, theta_range, first, last):
    out = []
    for a in np.arange(first, last, BIN):
        sel = (t0 - start >= a) & (t0 - start < a + BIN)
        if np.any(sel):
            out.append((a, float(np.mean(np.sqrt(np.mean(error[sel] ** 2, axis=0))
                                         / theta_range))))
    return out


def _event_figures(start, t0, error, theta_range, at, listener, arm, payload_on):
    # the level before: the predictions whose target lies in the 10 s before the change
    # (those started in the horizon before it cross it: their errors are the change's)
    first, last = at - 10.0 - HORIZON, at - HORIZON
    before = _bins(start, t0, error, theta_range, first, last)
    level = (float(np.mean(np.sqrt(np.mean(error[(t0 - start >= first)
                                                 & (t0 - start < last)] ** 2, axis=0))
                           / theta_range)) if before else None)
    after = _bins(start, t0, error, theta_range, at, at + 20.0)
    joints_after = []
    for a in np.arange(at, at + 20.0, BIN):
        sel = (t0 - start >= a) & (t0 - start < a + BIN)
        if np.any(sel):
            joints_after.append([round(float(a), 2)] + [
                float(v) for v in np.sqrt(np.mean(error[sel] ** 2, axis=0)) / theta_range])
    recovery = recovery_bins = None
    if level is not None:
        for a, value in after:
            if value <= 2.0 * level:
                recovery_bins = a + BIN - at
                break
        for end in np.arange(at + BIN, at + 20.0 + 1e-9, SLIDE):
            sel = (t0 - start >= end - BIN) & (t0 - start < end)
            if np.any(sel) and float(np.mean(np.sqrt(np.mean(error[sel] ** 2, axis=0))
                                             / theta_range)) <= 2.0 * level:
                recovery = round(float(end - at), 2)
                break
    said = [newest - start - at for newest, when in listener.changes
            if when - start >= at - 1.0 and newest - start >= at - 1.0]
    out = {'error_before': level,
           'error_after_peak': max((v for _, v in after), default=None),
           'error_bins_after': after, 'error_bins_after_per_joint': joints_after,
           'recovery_s': recovery, 'recovery_bins_s': recovery_bins,
           'detection_delay_s': min(said) if said else None}
    if payload_on is not None and arm == 'ur5':
        sign = 1.0 if payload_on else -1.0
        late = [(m, com) for newest, m, com in listener.payloads
                if at <= newest - start <= at + 10.0]
        if late:
            mass, com = late[-1]
            truth = ARMS[arm]
            out['payload_mass'] = mass
            out['payload_mass_error'] = abs(sign * mass - truth['mass']) / truth['mass']
            out['payload_com_error_m'] = float(np.linalg.norm(np.array(com)
                                                              - np.array(truth['com'])))
    return out


def self_check_figures(pt0, err, meas_t, meas_theta, listener, theta_range):
    """
    Return the worst 10 s window of what was published against the better baseline.

    ``(over the joints, per joint)``: the published 2 s-ahead RMSE over the predictions
    started in each 10 s window (slid by 1 s) over the better of following the reference
    (θd 2 s on) and holding the start's θ, range-normalised, mean over the joints; and the
    largest per-joint ratio, and where it is: ``(start of the window (s, stamp time), joint
    index)``; and the worst window over the joints: ``(its start, the published and the two
    baselines' errors there, mean over joints, the same per 1 s of prediction starts:
    [start, published, following the reference, holding the last state])``. None where no
    window has predictions and commands.
    """
    with listener.lock:
        cmd_t, theta_d = np.array(listener.cmd_t), np.array(listener.theta_d)
    if pt0.size < 2 or cmd_t.size < 2:
        return None, None, None, None
    order = np.argsort(cmd_t)
    cmd_t, theta_d = cmd_t[order], theta_d[order]
    ahead = pt0 + HORIZON
    keep = (ahead <= meas_t[-1]) & (ahead <= cmd_t[-1]) & (pt0 >= max(meas_t[0], cmd_t[0]))
    pt0, err, ahead = pt0[keep], err[keep], ahead[keep]
    n = meas_theta.shape[1]
    actual = np.column_stack([np.interp(ahead, meas_t, meas_theta[:, j]) for j in range(n)])
    start = np.column_stack([np.interp(pt0, meas_t, meas_theta[:, j]) for j in range(n)])
    planned = np.column_stack([np.interp(ahead, cmd_t, theta_d[:, j]) for j in range(n)])
    errors = {'prediction': err, 'follow_reference': planned - actual, 'hold_last': start - actual}
    scale = np.maximum(theta_range, 1e-12)
    worst = worst_joint = where = worst_at = None
    for a in np.arange(pt0[0], pt0[-1] - 10.0 + 1e-9, 1.0):
        sel = (pt0 >= a) & (pt0 < a + 10.0)
        if sel.sum() < 2:
            continue
        per = {k: np.sqrt(np.mean(e[sel] ** 2, axis=0)) / scale for k, e in errors.items()}
        better = np.minimum(per['follow_reference'], per['hold_last'])
        ratio = float(np.mean(per['prediction']) / max(
            min(np.mean(per['follow_reference']), np.mean(per['hold_last'])), 1e-12))
        joints = per['prediction'] / np.maximum(better, 1e-12)
        joint = float(np.max(joints))
        if worst is None or ratio > worst:
            bins = []
            for b in np.arange(a, a + 10.0 - 1e-9, 1.0):
                part = (pt0 >= b) & (pt0 < b + 1.0)
                if part.any():
                    bins.append([round(float(b), 2)] + [
                        float(np.mean(np.sqrt(np.mean(e[part] ** 2, axis=0)) / scale))
                        for e in errors.values()])
            worst, worst_at = ratio, (float(a), {k: float(np.mean(v)) for k, v in per.items()},
                                      bins)
        if worst_joint is None or joint > worst_joint:
            worst_joint, where = joint, (float(a), int(np.argmax(joints)))
    return worst, worst_joint, where, worst_at


def event_stamps(log_path):
    """Return the stamp times (s) sim_arm's log gives its payload 'attached', 'released'."""
    out = {}
    try:
        with open(log_path, encoding='utf-8', errors='replace') as f:
            for line in f:
                found = re.search(r'payload (?:of .* )?(attached|released) .*stamp ([0-9.]+) s',
                                  line)
                if found and found.group(1) not in out:
                    out[found.group(1)] = float(found.group(2))
    except OSError:
        pass
    return out


def run_cell(arm, sensors, duration, attach, detach, domain, log_dir, extra_sim=(), dump=None):
    """Run sim_arm and the identifier for one cell; return its figures."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    spec = ARMS[arm]
    sim_args = []
    for name in spec['files']:
        sim_args += ['--params-file', config(name)]
    if attach:
        sim_args += ['-p', f"payload.mass:={spec['mass']}", '-p', f"payload.com:={spec['com']}",
                     '-p', f'payload.attach_at:={float(attach)}',
                     '-p', f'payload.detach_at:={float(detach)}']
    sim_args += SENSORS[sensors] + list(extra_sim)
    prefix = f'change_{arm}_{sensors}_' + ('' if attach else 'quiet_')
    identifier = NodeProcesses([('identifier', [])], domain, log_dir, prefix=prefix)
    nodes = None
    load = os.getloadavg()[0]
    try:
        ctx = rclpy.Context()
        rclpy.init(context=ctx, domain_id=domain)
        monitor = Monitor(ctx, HORIZON)
        listener = Listener(monitor.node, monitor)
        executor = SingleThreadedExecutor(context=ctx)
        executor.add_node(monitor.node)
        wait_for_identifier(monitor.node, executor, identifier)
        nodes = NodeProcesses([('sim_arm', sim_args)], domain, log_dir, prefix=prefix)
        t0 = time.monotonic()
        while time.monotonic() - t0 < MAX_WALL_FACTOR * duration:
            executor.spin_once(timeout_sec=0.1)
            nodes.check()
            identifier.check()
            with monitor.lock:
                simulated = monitor.meas_t[-1] - monitor.meas_t[0] if monitor.meas_t else 0.0
            if simulated >= duration:
                break
        snap = monitor.snapshot()
        with monitor.lock:
            frames = list(monitor.pred_frame)
        executor.shutdown()
        monitor.node.destroy_node()
        rclpy.try_shutdown(context=ctx)
    finally:
        codes = (nodes.stop() if nodes is not None else []) + identifier.stop()
    meas_t, meas_theta, t0s, offs, thetas, _, _ = snap
    order = np.argsort(meas_t)
    meas_t, meas_theta = meas_t[order], meas_theta[order]
    start = float(meas_t[0])
    pt0, err = ahead_errors(t0s, offs, thetas, meas_t, meas_theta, HORIZON)
    theta_range = np.ptp(meas_theta, axis=0)
    if dump:    # every prediction, for a look at what was published when
        os.makedirs(dump, exist_ok=True)
        np.savez(os.path.join(dump, f'{prefix}predictions.npz'), start=start, pt0=pt0, err=err,
                 theta_range=theta_range, t0=np.array(t0s), frame=np.array(frames))
    ratio, joint_ratio, where, worst_at = self_check_figures(pt0, err, meas_t, meas_theta,
                                                             listener, theta_range)
    cell = {'exit_codes': codes,
            'load_average': [round(load, 2), round(os.getloadavg()[0], 2)],
            'self_check_worst_ratio': ratio, 'self_check_worst_joint_ratio': joint_ratio,
            'self_check_worst_joint_window': None if where is None else {
                'start_s': round(where[0] - start, 2), 'joint': int(where[1])},
            'self_check_worst_window': None if worst_at is None else {
                'start_s': round(worst_at[0] - start, 2), **worst_at[1],
                'bins_1s': [[round(b[0] - start, 2)] + b[1:] for b in worst_at[2]]},
            'changes_said': [[round(n - start, 3), round(w - start, 3)]
                             for n, w in listener.changes],
            'payloads': [[round(n - start, 3), m, c] for n, m, c in listener.payloads]}
    if attach:
        stamps = event_stamps(os.path.join(log_dir, f'{prefix}sim_arm.log'))
        cell['event_stamps_s'] = {k: round(v - start, 4) for k, v in stamps.items()}
        at = {k: stamps[k] - start if k in stamps else nominal
              for k, nominal in (('attached', attach), ('released', detach))}
        cell['attach'] = _event_figures(start, pt0, err, theta_range, at['attached'],
                                        listener, arm, True)
        cell['detach'] = _event_figures(start, pt0, err, theta_range, at['released'],
                                        listener, arm, False)
        for key in ('error_before', 'error_after_peak', 'recovery_s', 'detection_delay_s',
                    'payload_mass_error', 'payload_com_error_m'):
            if key in cell['attach']:
                cell[key] = cell['attach'][key]
        # the same without the predictions made before a change whose horizon crosses it
        crossing = np.zeros(pt0.shape, dtype=bool)
        for when in at.values():
            crossing |= (pt0 >= start + when - HORIZON) & (pt0 < start + when)
        ratio, joint_ratio, where, _ = self_check_figures(pt0[~crossing], err[~crossing],
                                                          meas_t, meas_theta, listener,
                                                          theta_range)
        cell['self_check_without_crossing'] = {
            'ratio': ratio, 'joint_ratio': joint_ratio,
            'joint_window': None if where is None else {'start_s': round(where[0] - start, 2),
                                                        'joint': int(where[1])}}
    return cell


def main(argv=None):
    """Run the cells; return the exit code."""
    parser = argparse.ArgumentParser(description='payload change: detection and recovery')
    parser.add_argument('--arms', default=','.join(ARMS))
    parser.add_argument('--sensors', default=','.join(SENSORS))
    parser.add_argument('--duration', type=float, default=150.0)
    parser.add_argument('--attach', type=float, default=60.0)
    parser.add_argument('--detach', type=float, default=120.0)
    parser.add_argument('--false-alarms', action='store_true',
                        help='also the 10-minute UR5 run without a change')
    parser.add_argument('--false-alarm-arms', default='ur5',
                        help="the arms of --false-alarms' runs (ur5, paper), comma-separated")
    parser.add_argument('--merge', action='store_true')
    parser.add_argument('--domain', type=int, default=None)
    parser.add_argument('--dump', default=None,
                        help="a directory for each cell's predictions and their errors (npz)")
    parser.add_argument('--out', default=os.path.join(HERE, 'results', 'change.json'))
    args = parser.parse_args(argv)
    log_dir = os.path.join(os.path.dirname(HERE), 'log', 'bench')
    results = {}
    if args.merge and os.path.exists(args.out):
        with open(args.out, encoding='utf-8') as f:
            results = json.load(f)
    cells = [(a, s) for a in args.arms.split(',') if a for s in args.sensors.split(',') if s]
    for i, (arm, sensors) in enumerate(cells):
        domain = 20 + (os.getpid() + 37 * i) % 200 if args.domain is None else args.domain + i
        print(f'== {arm} x {sensors}: {args.duration:.0f} s on ROS_DOMAIN_ID={domain}',
              flush=True)
        cell = run_cell(arm, sensors, args.duration, args.attach, args.detach, domain, log_dir,
                        dump=args.dump)
        results.setdefault(arm, {})[sensors] = cell
        print('  ' + json.dumps({k: cell.get(k) for k in (
            'error_before', 'error_after_peak', 'recovery_s', 'detection_delay_s',
            'payload_mass_error', 'payload_com_error_m')}), flush=True)
    quiet_arms = [a for a in args.false_alarm_arms.split(',') if a] if args.false_alarms else []
    for i, arm in enumerate(quiet_arms):
        domain = 20 + (os.getpid() + 91 + i) % 200 if args.domain is None else args.domain + 50 + i
        print(f'== 10-minute {arm} run without a change on ROS_DOMAIN_ID={domain}', flush=True)
        quiet = run_cell(arm, 'noisy', 600.0, 0.0, 0.0, domain, log_dir,
                         ['-p', 'reference.switch_at:=300.0'])
        results['false_alarm_run' + ('' if arm == 'ur5' else f'_{arm}')] = quiet
    runs = [k for k in results if k.startswith('false_alarm_run')]
    if runs:
        results['false_alarms_10min'] = sum(len(results[k]['changes_said']) for k in runs)

    def worst(arm):
        values = [cell[event].get('recovery_s') for cell in results.get(arm, {}).values()
                  for event in ('attach', 'detach') if event in cell]
        values = [float('inf') if v is None else v for v in values]
        return max(values) if values else None

    cells = [c for a in ARMS for c in results.get(a, {}).values()]
    cells += [results[k] for k in results if k.startswith('false_alarm_run')]
    for key in ('self_check_worst_ratio', 'self_check_worst_joint_ratio'):
        values = [c[key] for c in cells if c.get(key) is not None]
        results[key] = max(values) if values else None
    results['worst_recovery_s_urdf'] = worst('ur5')
    results['worst_recovery_s_no_urdf'] = worst('paper')
    results['meta'] = {'date': datetime.date.today().isoformat(), 'duration_s': args.duration,
                       'attach_s': args.attach, 'detach_s': args.detach,
                       'metric': 'module docstring of bench/change.py'}
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, 'w', encoding='utf-8') as f:
        json.dump(results, f, indent=2)
    print(json.dumps({k: v for k, v in results.items() if not isinstance(v, dict)}, indent=1),
          flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())

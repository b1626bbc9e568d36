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
Tracking before and after the learned feed-forward is switched on, through the nodes.

The installed ``sim_arm`` (the paper's arm under its PD, 100 Hz, ``config/sim_arm.yaml``)
and ``identifier`` (case 1, ``config/identifier.yaml``, ``feedforward.forward_topic`` set
to sim_arm's ``/sim_arm/feedforward``) run as processes on a private ROS domain, as a user
starts them. ``--switch-at`` seconds after the first joint state (60 by default) the script
sets ``feedforward.enabled`` to true through the identifier's ``set_parameters`` service,
as ``ros2 param set`` does; from then on the identifier sends its feed-forward whenever its
model passes the gate, and sim_arm adds it to the PD.

Metric: the tracking RMSE of θd − θ (rad, mean over joints) from ``joint_states`` and
``joint_commands`` at the same stamps, over the ``--window`` seconds (20) before the switch
and the same after it, the after-window starting at the switch itself (so it includes the
time the gate takes to pass the first model and the feed-forward's 0.5 s ramp; the RMSE
from 5 s after the switch on is reported beside it, and per second over the first 5 s). Also
recorded: when ``/diagnostics`` first said the feed-forward was on (its 1 Hz status, so up
to 1 s late), when sim_arm first logged a feed-forward applied (seconds from the
``set_parameters`` call, on the log lines' clock), how often it went off again (and why)
during the after-window, and sim_arm's skips; the tracking error at every stamp goes to
``<log-dir>/control_online_tracking.npz`` (``t`` from the switch, ``error`` θd − θ). How
much the first second costs depends on where on the plan the switch falls, and that moves
with how soon this script hears the first joint state. Writes the ``online`` entry of
``bench/results/control.json`` (the rest of the file is kept); ``--out`` another file.
"""

import argparse
import datetime
import json
import os
import sys
import time

from monitor import identifier_arguments, NodeProcesses  # bench/monitor.py
import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))


FEEDFORWARD_STATUS = 'identifier: feedforward'
SETTLED_AFTER = 5.0  # s: also reported, the after-window without its first seconds


class Recorder:
    """Joint states and commands by stamp, and the feed-forward's diagnostics."""

    def __init__(self, context):
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.node import Node
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import JointState
        self.node = Node('control_online_probe', context=context)
        self.states, self.commands, self.status = {}, {}, []
        qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        self.node.create_subscription(JointState, 'joint_states', self._state, qos)
        self.node.create_subscription(JointState, 'joint_commands', self._command, qos)
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._diagnostics, 100)

    @staticmethod
    def _stamp(msg):
        return msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec

    def _state(self, msg):
        self.states[self._stamp(msg)] = np.array(msg.position)

    def _command(self, msg):
        self.commands[self._stamp(msg)] = np.array(msg.position)

    def _diagnostics(self, msg):
        for status in msg.status:
            if status.name == FEEDFORWARD_STATUS:
                self.status.append((self._stamp(msg), status.message))

    def newest(self):
        return max(self.states) if self.states else None

    def rmse(self, start, end):
        """Return (tracking RMSE over [start, end), samples): mean over joints."""
        stamps = [s for s in self.states if start <= s < end and s in self.commands]
        if not stamps:
            return None, 0
        error = np.array([self.commands[s] - self.states[s] for s in stamps])
        return float(np.mean(np.sqrt(np.mean(np.square(error), axis=0)))), len(stamps)


def log_times(lines, text):
    """Return the clock times (s) of the ROS log lines that contain ``text``."""
    return [float(line.split('[')[2].split(']')[0]) for line in lines
            if text in line and line.count('[') >= 3]


def set_enabled(node, executor, value=True, timeout=30.0):
    """Set the identifier's ``feedforward.enabled`` through its service; return the reason."""
    from rcl_interfaces.srv import SetParameters
    from rclpy.parameter import Parameter
    client = node.create_client(SetParameters, '/identifier/set_parameters')
    if not client.wait_for_service(timeout_sec=timeout):
        raise RuntimeError('the identifier offers no set_parameters service')
    future = client.call_async(SetParameters.Request(
        parameters=[Parameter('feedforward.enabled', value=value).to_parameter_msg()]))
    executor.spin_until_future_complete(future, timeout_sec=timeout)
    result = future.result()
    if result is None or not result.results[0].successful:
        raise RuntimeError(f'feedforward.enabled was refused: {result}')


def main(argv=None):
    """Run the nodes, switch the feed-forward on, write the before / after figures."""
    parser = argparse.ArgumentParser(description='tracking before and after the feed-forward')
    parser.add_argument('--switch-at', type=float, default=60.0,
                        help='seconds after the first joint state')
    parser.add_argument('--window', type=float, default=20.0)
    parser.add_argument('--domain-id', type=int, default=None)
    parser.add_argument('--out', default=os.path.join(HERE, 'results', 'control.json'))
    parser.add_argument('--log-dir', default=os.path.join(os.path.dirname(HERE), 'out'))
    args = parser.parse_args(argv)
    if args.switch_at < args.window:
        parser.error('--switch-at must be at least --window')

    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    domain = args.domain_id if args.domain_id is not None else 20 + os.getpid() % 200
    load_start = os.getloadavg()
    forward = ['-p', 'feedforward.forward_topic:=/sim_arm/feedforward']
    # listening before the arm starts, so the first state heard is (nearly always) the arm's
    # first: the switch then falls at the same point of the plan in every run
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain)
    recorder = Recorder(context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(recorder.node)
    nodes = NodeProcesses([('sim_arm', []),
                           ('identifier', identifier_arguments('torque', extra=forward))],
                          domain, args.log_dir, prefix='control_online_')
    try:

        def spin_until(condition, what, timeout):
            end = time.monotonic() + timeout
            while not condition():
                if time.monotonic() > end:
                    raise RuntimeError(f'timed out waiting for {what}')
                executor.spin_once(timeout_sec=0.1)
                nodes.check()

        spin_until(lambda: recorder.states, 'the first joint state', 120.0)
        first = min(recorder.states)
        spin_until(lambda: recorder.newest() >= first + args.switch_at,
                   f'{args.switch_at:g} s of joint states', 10 * args.switch_at)
        switch = recorder.newest()
        set_wall = time.time()  # the clock of the nodes' log lines
        set_enabled(recorder.node, executor)
        print(f'feedforward.enabled set at {switch - first:.2f} s', flush=True)
        spin_until(lambda: recorder.newest() >= switch + args.window + 0.5,
                   f'{args.window:g} s after the switch', 10 * args.window)
        before, n_before = recorder.rmse(switch - args.window, switch)
        after, n_after = recorder.rmse(switch, switch + args.window)
        settled, _ = recorder.rmse(switch + SETTLED_AFTER, switch + args.window)
        by_second = [recorder.rmse(switch + k, switch + k + 1.0)[0]
                     for k in range(int(SETTLED_AFTER))]
        stamps = sorted(s for s in recorder.states if s in recorder.commands)
        np.savez(os.path.join(args.log_dir, 'control_online_tracking.npz'),
                 t=np.array(stamps) - switch,
                 error=np.array([recorder.commands[s] - recorder.states[s] for s in stamps]))
        status = [(t - switch, m) for t, m in recorder.status
                  if switch <= t < switch + args.window]
        on_at = next((t for t, m in status if m == 'on'), None)
        offs = []
        for (_, previous), (t, message) in zip(status, status[1:]):
            if previous == 'on' and message != 'on':
                offs.append((round(t, 2), message))
        executor.shutdown()
        recorder.node.destroy_node()
        rclpy.try_shutdown(context=context)
    finally:
        codes = nodes.stop()
    with open(os.path.join(args.log_dir, 'control_online_sim_arm.log'), encoding='utf-8') as f:
        lines = f.readlines()
    skips = sum('fell behind' in line for line in lines)
    applied = next((round(t - set_wall, 2) for t in log_times(lines, 'feed-forward applied')
                    if t >= set_wall), None)
    started = log_times(lines, 'simulation started')
    online = {
        'before_rmse': before, 'after_rmse': after,
        'ratio': None if not (before and after) else before / after,
        f'after_from_{SETTLED_AFTER:g}s_rmse': settled,
        'goal': 'before_rmse >= 3 * after_rmse',
        'samples': [n_before, n_after], 'switch_at_s': round(switch - first, 2),
        'window_s': args.window,
        'first_on_after_switch_s': None if on_at is None else round(on_at, 2),
        # when sim_arm first added a feed-forward, from the set_parameters call (log clock)
        'applied_after_set_s': applied,
        # sim_arm stamps its states from the wall clock at its start: ~0 when this script
        # heard the arm's first state (the switch's point on the plan is then the same)
        'first_state_after_arm_start_s': round(first - started[0], 3) if started else None,
        f'after_rmse_first_{SETTLED_AFTER:g}s_by_second': by_second,
        'switched_off_during_after_window': offs, 'sim_arm_skips': skips,
        'exit_codes': codes,
        'meta': {'date': datetime.date.today().isoformat(),
                 'command': 'nice -n 10 python bench/control_online.py '
                            + ' '.join(argv or sys.argv[1:]),
                 'load_start': load_start, 'load_end': os.getloadavg(),
                 'nodes': 'installed sim_arm (config/sim_arm.yaml) and identifier '
                          '(config/identifier.yaml, case torque, forward_topic '
                          '/sim_arm/feedforward), 100 Hz'},
    }
    print(json.dumps(online, indent=2), flush=True)
    try:
        with open(args.out, encoding='utf-8') as f:
            result = json.load(f)
    except (OSError, ValueError):
        result = {}
    result['online'] = online
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, 'w', encoding='utf-8') as f:
        json.dump(result, f, indent=2)
    print(f'wrote the online entry of {args.out}', flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())

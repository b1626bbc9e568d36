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
The main job (``make demo``): the simulated arm and the online identifier, live.

Starts the installed ``sim_arm`` and ``identifier`` executables (found through the ament
index, exactly where ``ros2 run rkgnn_ros <exe>`` looks) on a private ROS domain, watches
their topics from a small monitor node, prints progress every few seconds (generation, best
cost, validation error, the error of the 2 s-ahead predictions against the motion that
followed) and, at the end, stops both nodes and writes a figure: measured vs predicted
joint trajectories with the uncertainty the identifier published beside each prediction
(``~/prediction_uncertainty``: the published predictor's recent error at that horizon, a
band of ± one RMSE), which predictions were the model's and which a baseline's (the
self-check, ``header.frame_id``), the evolution history and the prediction error over time.

``--feedforward`` (``make demo DEMO_ARGS=--feedforward``; cases 1 and 2) also starts the
learned feed-forward: the identifier forwards it to sim_arm's ``/sim_arm/feedforward``,
``feedforward.enabled`` is set at ``--feedforward-at`` seconds (30 by default, so the figure
has a stretch without it), and from then on the identifier sends it whenever its model
passes the gate. The figure then has one more panel: the tracking error |θd − θ| over time,
with the stretches where the feed-forward was on shaded, and the RMSE before and after.
"""

import argparse
import os
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))
sys.path.insert(0, os.path.join(os.path.dirname(HERE), 'bench'))  # bench/monitor.py

from monitor import (CASES, field, identifier_arguments, Monitor, NodeProcesses,  # noqa: E402
                     prediction_score)
import numpy as np  # noqa: E402


class Companions:
    """Records, per prediction stamp, what it was (frame_id) and its uncertainty at the horizon."""

    def __init__(self, node, horizon):
        from trajectory_msgs.msg import JointTrajectory
        self.horizon = horizon
        self.source, self.sigma = {}, {}
        node.create_subscription(JointTrajectory, 'identifier/prediction', self._on_prediction,
                                 10)
        node.create_subscription(JointTrajectory, 'identifier/prediction_uncertainty',
                                 self._on_uncertainty, 10)

    @staticmethod
    def _key(msg):  # the stamp as the monitor keeps it (the same float)
        return msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec

    def _on_prediction(self, msg):
        self.source[self._key(msg)] = msg.header.frame_id.split(';')[0]

    def _on_uncertainty(self, msg):
        times = [p.time_from_start.sec + 1e-9 * p.time_from_start.nanosec for p in msg.points]
        if times and times[-1] >= self.horizon - 1e-9:
            self.sigma[self._key(msg)] = np.array(msg.points[-1].positions, dtype=float)

    def at(self, t0s):
        """Return (is a baseline (M,), σ at the horizon (M, n) or NaN) for stamps ``t0s``."""
        baseline = np.array([self.source.get(t, 'model') != 'model' for t in t0s], dtype=bool)
        sigma = [self.sigma.get(t) for t in t0s]
        n = next((len(v) for v in sigma if v is not None), 0)
        return baseline, np.array([v if v is not None else np.full(n, np.nan) for v in sigma])


class Tracking:
    """The commands (θd by stamp) and the feed-forward's on/off status, for the figure."""

    def __init__(self, node):
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.qos import qos_profile_sensor_data
        from sensor_msgs.msg import JointState
        self.commands, self.status = {}, []
        node.create_subscription(JointState, 'joint_commands', self._command,
                                 qos_profile_sensor_data)
        node.create_subscription(DiagnosticArray, '/diagnostics', self._diagnostics, 100)

    def _command(self, msg):
        stamp = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
        self.commands[stamp] = np.array(msg.position, dtype=float)

    def _diagnostics(self, msg):
        stamp = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
        for status in msg.status:
            if status.name == 'identifier: feedforward':
                self.status.append((stamp, status.message == 'on'))

    def errors(self, meas_t, meas_theta):
        """Return (t, |θd − θ| mean over joints) at the states whose command arrived."""
        pairs = [(t, np.mean(np.abs(self.commands[t] - th)))
                 for t, th in zip(meas_t, meas_theta) if t in self.commands]
        return np.array(pairs).reshape(-1, 2).T


def rmse_text(t, err, start, end):
    """Return the RMSE of ``err`` over [start, end) as text."""
    keep = (t >= start) & (t < end)
    return f'{np.sqrt(np.mean(np.square(err[keep]))):.3g} rad' if keep.any() else 'n/a'


def draw_tracking(ax, tracking, meas_t, meas_theta, start, enabled_at):
    """Draw the tracking error, the feed-forward's on stretches and the enable time."""
    t, err = tracking.errors(meas_t, meas_theta)
    if t.size:
        ax.semilogy(t - start, np.maximum(err, 1e-7), 'k', lw=0.8, label='|θd − θ|')
    on_since = None
    for stamp, on in tracking.status + [(np.inf, False)]:
        if on and on_since is None:
            on_since = stamp
        elif not on and on_since is not None:
            end = min(stamp, t[-1] if t.size else stamp)
            ax.axvspan(on_since - start, end - start, color='C2', alpha=0.15)
            on_since = None
    if enabled_at is not None and t.size:
        window = 20.0
        ax.axvline(enabled_at - start, color='C3', lw=1, label='feedforward.enabled')
        ax.set_title(f'tracking error (shaded: feed-forward on); RMSE over {window:g} s '
                     f'before: {rmse_text(t, err, enabled_at - window, enabled_at)}, after: '
                     f'{rmse_text(t, err, enabled_at, enabled_at + window)}', fontsize=9)
    ax.set_xlabel('t [s]')
    ax.set_ylabel('mean |θd − θ| [rad]')
    ax.legend(loc='upper right', fontsize=8)
    ax.grid(alpha=0.3)


def write_figure(path, snapshot, horizon, case, companions=None, tracking=None,
                 enabled_at=None):
    """Write measured vs predicted trajectories, evolution history and prediction error."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    meas_t, meas_theta, t0s, offs, thetas, evolution, labels = snapshot
    if meas_t.size == 0:
        raise RuntimeError('no joint_states were received')
    start = meas_t.min()
    n = meas_theta.shape[1]
    rows = n + 2 + (tracking is not None)
    fig, axes = plt.subplots(rows, 1, figsize=(11, 2.3 * rows))
    reach = [k for k, off in enumerate(offs) if off[-1] >= horizon - 1e-9]
    ahead_t = np.array([t0s[k] + horizon for k in reach]) - start
    ahead_th = np.array([thetas[k][-1] for k in reach])
    baseline, sigma = (companions.at([t0s[k] for k in reach]) if companions is not None
                       else (np.zeros(len(reach), dtype=bool), np.empty((len(reach), 0))))
    for j in range(n):
        ax = axes[j]
        ax.plot(meas_t - start, meas_theta[:, j], 'k', lw=1.5, label='measured')
        if reach:
            if sigma.shape[1] == n:
                ax.fill_between(ahead_t, ahead_th[:, j] - sigma[:, j],
                                ahead_th[:, j] + sigma[:, j], color='C0', alpha=0.25, lw=0,
                                label='± published uncertainty')
            ax.plot(ahead_t[~baseline], ahead_th[~baseline, j], 'C0.', ms=3,
                    label=f'model, predicted {horizon:g} s earlier')
            ax.plot(ahead_t[baseline], ahead_th[baseline, j], 'C1.', ms=3,
                    label='baseline published (self-check)')
        lo, hi = meas_theta[:, j].min(), meas_theta[:, j].max()
        pad = 0.5 * (hi - lo) + 0.05
        ax.set_ylim(lo - pad, hi + pad)  # far-off predictions leave the frame
        ax.set_ylabel(f'θ{j + 1} [rad]')
        ax.grid(alpha=0.3)
    axes[0].legend(loc='upper right', fontsize=8)
    axes[0].set_title(f'rkgnn_ros demo ({case}): measured vs predicted joint trajectories')
    ax = axes[n]
    gen = field(evolution, labels, 'generation')
    if gen.size:
        ax.semilogy(gen, field(evolution, labels, 'best_cost'), 'C1', label='best cost J')
        ax.semilogy(gen, field(evolution, labels, 'mean_cost'), 'C1', alpha=0.4,
                    label='mean cost J')
        ax.legend(fontsize=8)
    ax.set_xlabel('generation')
    ax.set_ylabel('J')
    ax.grid(alpha=0.3)
    ax = axes[n + 1]
    t0, err, _ = prediction_score(snapshot, horizon)
    if t0.size:
        theta_range = np.ptp(meas_theta, axis=0)
        rolling = [np.mean(np.sqrt(np.mean(np.square(err[(t0 > t - 10.0) & (t0 <= t)]),
                                           axis=0)) / theta_range) for t in t0]
        ax.plot(t0 - start, 100 * np.array(rolling), 'C0')
    ax.set_xlabel('t [s]')
    ax.set_ylabel(f'{horizon:g} s-ahead θ RMSE\n[% of θ range, 10 s window]')
    ax.grid(alpha=0.3)
    if tracking is not None:
        draw_tracking(axes[n + 2], tracking, meas_t, meas_theta, start, enabled_at)
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def enable_feedforward(node, executor):
    """Set the identifier's ``feedforward.enabled``; return the time (s, node clock)."""
    from rcl_interfaces.srv import SetParameters
    from rclpy.parameter import Parameter
    client = node.create_client(SetParameters, 'identifier/set_parameters')
    if not client.wait_for_service(timeout_sec=10.0):
        raise RuntimeError('the identifier offers no set_parameters service')
    future = client.call_async(SetParameters.Request(
        parameters=[Parameter('feedforward.enabled', value=True).to_parameter_msg()]))
    executor.spin_until_future_complete(future, timeout_sec=10.0)
    if future.result() is None or not future.result().results[0].successful:
        raise RuntimeError(f'feedforward.enabled was refused: {future.result()}')
    return node.get_clock().now().nanoseconds * 1e-9


def main(argv=None):
    """Run the demo; return the exit code."""
    parser = argparse.ArgumentParser(description='rkgnn_ros demo: sim_arm + identifier')
    parser.add_argument('--duration', type=float, default=90.0, help='seconds to run')
    parser.add_argument('--case', default='auto', choices=['auto'] + sorted(CASES),
                        help="the identifier's case ('auto', its default, follows the streams)")
    parser.add_argument('--horizon', type=float, default=2.0)
    parser.add_argument('--out', default=os.path.join(os.path.dirname(HERE), 'out',
                                                      'demo.png'))
    parser.add_argument('--domain-id', type=int, default=None)
    parser.add_argument('--print-every', type=float, default=5.0)
    parser.add_argument('--feedforward', action='store_true',
                        help='switch the learned feed-forward on (cases 1 and 2)')
    parser.add_argument('--feedforward-at', type=float, default=30.0,
                        help='seconds after the start at which feedforward.enabled is set')
    args = parser.parse_args(argv)
    case = args.case if args.case == 'auto' else CASES[args.case]
    extra = ['-p', 'feedforward.forward_topic:=/sim_arm/feedforward'] if args.feedforward \
        else []
    identifier_args = (['-p', f'prediction.horizon:={float(args.horizon)}'] + extra
                       if case == 'auto' else identifier_arguments(case, args.horizon, extra))

    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    domain = args.domain_id if args.domain_id is not None else 20 + os.getpid() % 200
    log_dir = os.path.dirname(os.path.abspath(args.out))
    print(f'rkgnn_ros demo: case {case}, {args.duration:.0f} s, ROS_DOMAIN_ID={domain}, '
          f'node logs in {log_dir}/demo_*.log', flush=True)
    nodes = NodeProcesses([('sim_arm', []), ('identifier', identifier_args)],
                          domain, log_dir, prefix='demo_')
    try:
        ctx = rclpy.Context()
        rclpy.init(context=ctx, domain_id=domain)
        monitor = Monitor(ctx, args.horizon)
        companions = Companions(monitor.node, args.horizon)
        executor = SingleThreadedExecutor(context=ctx)
        executor.add_node(monitor.node)
        tracking = Tracking(monitor.node) if args.feedforward else None
        enabled_at = None
        t_start = time.monotonic()
        next_print = t_start + args.print_every
        while time.monotonic() - t_start < args.duration:
            executor.spin_once(timeout_sec=0.1)
            nodes.check()
            if tracking is not None and enabled_at is None and \
                    time.monotonic() - t_start >= args.feedforward_at:
                enabled_at = enable_feedforward(monitor.node, executor)
                print(f'[{time.monotonic() - t_start:5.0f} s] feedforward.enabled set: the '
                      'identifier sends the feed-forward whenever its model passes the gate',
                      flush=True)
            if time.monotonic() >= next_print:
                next_print += args.print_every
                snap = monitor.snapshot()
                evo, labels = snap[5], snap[6]
                _, _, score = prediction_score(snap, args.horizon, window=10.0)
                if evo.size:
                    gen = field(evo[-1:], labels, 'generation')[0]
                    best = field(evo[-1:], labels, 'best_cost')[0]
                    val = field(evo[-1:], labels, 'validation_nrmse')[0]
                    status = (f'generation {gen:5.0f}  best J {best:9.4g}  '
                              f'validation θ-NRMSE {val:7.2%}')
                else:
                    status = 'waiting for the first generation'
                print(f'[{time.monotonic() - t_start:5.0f} s] {status}  '
                      f'{args.horizon:g} s-ahead θ RMSE {score:7.2%} of range  '
                      f'({snap[0].size} states, {len(snap[2])} predictions)', flush=True)
        snap = monitor.snapshot()
        _, _, score = prediction_score(snap, args.horizon, window=10.0)
        write_figure(args.out, snap, args.horizon, case, companions, tracking, enabled_at)
        print(f'final {args.horizon:g} s-ahead θ RMSE (last 10 s): {score:.2%} of the θ range',
              flush=True)
        print(f'figure: {args.out}', flush=True)
        executor.shutdown()
        monitor.node.destroy_node()
        rclpy.try_shutdown(context=ctx)
    finally:
        codes = nodes.stop()
    if any(c != 0 for c in codes):
        print(f'a node exited with a non-zero code: {codes}', flush=True)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())

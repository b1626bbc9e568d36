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
"""

import argparse
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from rkgnn_ros.monitor import (CASES, field, identifier_arguments, Monitor,  # noqa: E402
                               NodeProcesses, prediction_score)


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


def write_figure(path, snapshot, horizon, case, companions=None):
    """Write measured vs predicted trajectories, evolution history and prediction error."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    meas_t, meas_theta, t0s, offs, thetas, evolution, labels = snapshot
    if meas_t.size == 0:
        raise RuntimeError('no joint_states were received')
    start = meas_t.min()
    n = meas_theta.shape[1]
    fig, axes = plt.subplots(n + 2, 1, figsize=(11, 2.3 * (n + 2)))
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
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


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
    args = parser.parse_args(argv)
    case = args.case if args.case == 'auto' else CASES[args.case]
    identifier_args = (['-p', f'prediction.horizon:={float(args.horizon)}'] if case == 'auto'
                       else identifier_arguments(case, args.horizon))

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
        t_start = time.monotonic()
        next_print = t_start + args.print_every
        while time.monotonic() - t_start < args.duration:
            executor.spin_once(timeout_sec=0.1)
            nodes.check()
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
        write_figure(args.out, snap, args.horizon, case, companions)
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

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
Online accuracy: the 2 s-ahead prediction error of the running identifier, per case.

For each case, starts the installed ``sim_arm`` and ``identifier`` (default settings, the
paper's arm at 100 Hz) on a private ROS domain for ``--duration`` seconds, records
``joint_states`` and ``identifier/prediction`` and scores every prediction's θ 2 s ahead
against the motion that followed. The curve is that RMSE over 5 s bins of prediction start
time, divided by the θ range; ``prediction_nrmse_60s`` is the bin ending at 60 s.
``first_prediction_s`` and ``first_model_prediction_s``: seconds from the first
``joint_states`` to the first prediction (a baseline while the model is not yet scored)
and to the first one the model made (``header.frame_id`` 'model').
With ``--switch-at`` (default 60 s) sim_arm's reference turns into another task there
(``reference.switch_at``: sines about a pose moved by 0.4 rad, other frequencies, joined
over 2 s); ``switch_ratio`` is the 2 s-ahead error of the predictions whose target lies in
the 10 s after the switch over that in the 10 s before (ending 1 s early: see the code).
Writes ``bench/results/online.json``.
"""

import argparse
import datetime
import json
import os
import sys
import time

from monitor import identifier_arguments, Monitor, NodeProcesses  # bench/monitor.py
import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from rkgnn_ros.core.selfcheck import ahead_errors  # noqa: E402


def run_case(case, duration, horizon, domain, log_dir, switch_at=0.0, identifier_params=(),
             sim_params=()):
    """
    Run the pair for one case; return (curve [(t_end, nrmse)], nrmse_60s, details).

    ``identifier_params``, ``sim_params``: extra ``NAME:=VALUE`` parameters of each node.
    """
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    arm = ['-p', f'reference.switch_at:={float(switch_at)}'] if switch_at else []
    arm += [a for p in sim_params for a in ('-p', p)]
    extra = [a for p in identifier_params for a in ('-p', p)]
    nodes = NodeProcesses([('sim_arm', arm),
                           ('identifier', identifier_arguments(case, horizon, extra))],
                          domain, log_dir, prefix=f'online_case{case}_')
    try:
        ctx = rclpy.Context()
        rclpy.init(context=ctx, domain_id=domain)
        monitor = Monitor(ctx, horizon)
        executor = SingleThreadedExecutor(context=ctx)
        executor.add_node(monitor.node)
        t0 = time.monotonic()
        while time.monotonic() - t0 < duration:
            executor.spin_once(timeout_sec=0.1)
            nodes.check()
        snap = monitor.snapshot()
        first_model = monitor.first_model
        executor.shutdown()
        monitor.node.destroy_node()
        rclpy.try_shutdown(context=ctx)
    finally:
        codes = nodes.stop()
    meas_t, meas_theta, t0s, offs, thetas, evolution, labels = snap
    order = np.argsort(meas_t)
    meas_t, meas_theta = meas_t[order], meas_theta[order]
    # the first joint_states: the earliest stamp seen, here or as a prediction's start (a
    # prediction is stamped with its state's; the identifier may hear the arm before this
    # node's subscription is matched, 1.4 s earlier in one run)
    start = min([meas_t[0]] + list(t0s))
    pt0, err = ahead_errors(t0s, offs, thetas, meas_t, meas_theta, horizon)
    theta_range = np.ptp(meas_theta, axis=0)
    curve = []
    for end in np.arange(5.0, duration + 1e-9, 5.0):
        sel = (pt0 - start > end - 5.0) & (pt0 - start <= end)
        if np.any(sel):
            rmse = np.sqrt(np.mean(np.square(err[sel]), axis=0))
            curve.append([float(end), float(np.mean(rmse / theta_range))])
    at60 = next((v for t, v in curve if abs(t - 60.0) < 1e-9), None)
    switch = {}
    if switch_at:
        # predictions whose target lies in the 10 s before / after the switch. Time here
        # starts at the first joint_states received, up to ~1 s after sim_arm's time 0:
        # 'before' ends 1 s early, so it holds no motion after the switch
        target = pt0 + horizon - start
        rmse = {}
        for name, sel in (('before', (target > switch_at - 11.0) & (target <= switch_at - 1.0)),
                          ('after', (target > switch_at) & (target <= switch_at + 10.0))):
            rmse[name] = (float(np.mean(np.sqrt(np.mean(np.square(err[sel]), axis=0))
                                        / theta_range)) if np.any(sel) else None)
        switch = {'switch_at_s': float(switch_at), 'switch_nrmse_before': rmse['before'],
                  'switch_nrmse_after': rmse['after'],
                  'switch_ratio': (rmse['after'] / rmse['before']
                                   if rmse['before'] and rmse['after'] is not None else None)}
    details = {'states': int(meas_t.size), 'predictions': len(t0s), 'scored': int(pt0.size),
               'generations': int(evolution[-1][0]) if len(evolution) else 0,
               'exit_codes': codes,
               # from the first joint_states: to the first prediction (a baseline until the
               # self-check has scored the model) and to the first the model made
               'first_prediction_s': float(min(t0s) - start) if t0s else None,
               'first_model_prediction_s': (None if first_model is None
                                            else float(first_model - start)), **switch}
    return curve, at60, details


def main(argv=None):
    """Run the cases; return the exit code."""
    parser = argparse.ArgumentParser(description='online 2 s-ahead accuracy per case')
    parser.add_argument('--cases', default='1,2,3')
    parser.add_argument('--duration', type=float, default=None,
                        help='seconds per case (default 65, or 15 past --switch-at)')
    parser.add_argument('--switch-at', type=float, default=60.0,
                        help="sim_arm's reference switches to another pose and frequencies "
                             'at this time (s; 0: never)')
    parser.add_argument('--horizon', type=float, default=2.0)
    parser.add_argument('--domain', type=int, default=None,
                        help='ROS_DOMAIN_ID of the first case (next cases: +1, ...)')
    parser.add_argument('--identifier-param', action='append', default=[], metavar='NAME:=VALUE',
                        help='an identifier parameter for every case (repeatable); recorded '
                        'in meta.identifier_params')
    parser.add_argument('--sim-param', action='append', default=[], metavar='NAME:=VALUE',
                        help='a sim_arm parameter (repeatable); recorded in meta.sim_params')
    parser.add_argument('--out', default=os.path.join(HERE, 'results', 'online.json'))
    args = parser.parse_args(argv)
    if args.duration is None:
        args.duration = max(65.0, args.switch_at + 15.0) if args.switch_at else 65.0
    log_dir = os.path.join(os.path.dirname(HERE), 'log', 'bench')
    results = {'meta': {'date': datetime.date.today().isoformat(), 'cpus': os.cpu_count(),
                        'duration_s': args.duration, 'horizon_s': args.horizon,
                        'switch_at_s': args.switch_at,
                        'metric': '2 s-ahead θ RMSE over predictions started in the 5 s '
                                  'bin ending at t, divided by the θ range, mean over joints',
                        'identifier_params': list(args.identifier_param),
                        'sim_params': list(args.sim_param)}}
    for i, case in enumerate(c.strip() for c in args.cases.split(',')):
        domain = (20 + (os.getpid() + 37 * i) % 200 if args.domain is None
                  else args.domain + i)
        print(f'== case {case}: {args.duration:.0f} s on ROS_DOMAIN_ID={domain}', flush=True)
        curve, at60, details = run_case(case, args.duration, args.horizon, domain, log_dir,
                                        args.switch_at, args.identifier_param, args.sim_param)
        for t, v in curve:
            print(f'  t = {t:4.0f} s  2 s-ahead θ RMSE {v:8.2%} of range', flush=True)
        results[case] = {'prediction_nrmse_60s': at60, 'curve': curve, **details}
        print(f'  case {case}: at 60 s {at60 if at60 is None else f"{at60:.2%}"}  {details}',
              flush=True)
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, 'w', encoding='utf-8') as f:
        json.dump(results, f, indent=2)
    print(f'wrote {args.out}', flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())

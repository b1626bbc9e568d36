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
The identifier's global predictors offline: the arm on the trigonometric basis, closed loop.

The paper's arm (``core/sim``) runs ``paper_reference`` at 100 Hz under each servo (PD;
PD + gravity compensation on the measured θ; PID, Ki = 20 N m/(rad s)) with each sensor
chain (exact; encoder noise 1e-4 rad with θ̇ by backward differences), fixed seeds. The
first ``--train`` seconds (20 by default: the identifier's default window) are the data,
the newest 20 % of them held out, as the identifier splits them:

- case 1: the servo law learned from the torque (:func:`.case_one.fit_law`) and the arm
  fitted on it (:func:`.trig_loop.fit_trig_loop`);
- case 3: no torque, arm and servo fitted together
  (:func:`.trig_loop.fit_closed_trig_loop`, the PD or PID form chosen on the held-out part).

From the end of the data a prediction starts every 0.5 s for 8 s from the measured state,
its integral term moved on by Ki ∫e of the measured error as the node does, and is scored
2 s ahead against the measured motion: RMSE / range of θ, mean over joints and starts;
``follow_reference`` is the same for θd. Also the held-out equation (case 3) or torque
(case 1) error that gates the predictor online, the fit's wall time and, in case 3, Kp's
ratios and Ki / Kp against the servo's. Writes ``bench/results/trig_loops.json``.
"""

import argparse
from dataclasses import replace
import datetime
import json
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from rkgnn_ros.core.fitting.case_one import fit_law  # noqa: E402
from rkgnn_ros.core.fitting.trig_loop import fit_closed_trig_loop, fit_trig_loop  # noqa: E402
from rkgnn_ros.core.fitting.validation import split_validation  # noqa: E402
from rkgnn_ros.core.sim.plant import PlanarArm  # noqa: E402
from rkgnn_ros.core.sim.sensors import SensorModel  # noqa: E402
from rkgnn_ros.core.sim.servo import Servo  # noqa: E402
from rkgnn_ros.core.sim.simulate import simulate  # noqa: E402
from rkgnn_ros.core.sim.trajectories import paper_reference  # noqa: E402

N = 3
RATE = 100.0
KP = np.array([32.84, 42.05, 42.31])
KD = np.array([42.44, 0.19, 4.86])
KI = 20.0
ARM = PlanarArm.paper()
SERVOS = {'pd': Servo(KP, KD),
          'pd_gravity': Servo(KP, KD, gravity='measured', arm=ARM),
          'pid': Servo(KP, KD, ki=[KI, KI, KI])}
SENSORS = {'exact': SensorModel.exact(), 'noise': SensorModel.differenced(1e-4)}
VALIDATION_FRACTION = 0.2


def ahead_error(loop, data, starts, fitted_until, steps):
    """Return the mean 2 s-ahead θ RMSE / range (the integral moved on from the fit's end)."""
    span = data.theta.max(axis=0) - data.theta.min(axis=0)
    law, errors = loop.law, []
    for k in starts:
        e = data.theta_d[fitted_until:k + 1] - data.theta[fitted_until:k + 1]
        integral = law.integral_term + law.ki * np.trapezoid(e, dx=data.dt, axis=0)
        x0 = np.concatenate([data.theta[k], data.theta_dot[k]])
        rows = slice(k, k + steps + 1)
        states = loop.simulate(x0, data.t[rows] - data.t[k], data.theta_d[rows],
                               data.theta_d_dot[rows], integral)
        rmse = np.sqrt(np.mean((states[:, :N] - data.theta[rows]) ** 2, axis=0))
        errors.append(float(np.mean(rmse / span)))
    return float(np.mean(errors))


def follow_error(data, starts, steps):
    span = data.theta.max(axis=0) - data.theta.min(axis=0)
    return float(np.mean([np.mean(np.sqrt(np.mean(
        (data.theta_d[k:k + steps + 1] - data.theta[k:k + steps + 1]) ** 2, axis=0)) / span)
        for k in starts]))


def run_cell(servo, sensors, train_s, seed):
    """Return the cell's figures for cases 1 and 3."""
    data = simulate(ARM, SERVOS[servo], paper_reference(N), train_s + 10.5, rate=RATE,
                    noise=SENSORS[sensors], rng=seed)
    end = int(round(train_s * RATE))
    steps = int(round(2.0 * RATE))
    starts = range(end - 1, end - 1 + int(8.0 * RATE), int(0.5 * RATE))
    cell = {'follow_reference': follow_error(data, starts, steps)}
    window = data.slice(0, end)
    # case 1: the law from the torque, the arm fitted on it
    t0 = time.perf_counter()
    train, validation, _ = split_validation([window], VALIDATION_FRACTION)
    law = fit_law(train)
    loop = fit_trig_loop(train, validation, law) if law is not None else None
    fitted = time.perf_counter() - t0
    if loop is None:
        cell['1'] = {'prediction_2s': None, 'why': 'no law or no fit'}
    else:
        cell['1'] = {'prediction_2s': ahead_error(loop, data, starts, train[-1].n_samples - 1,
                                                  steps),
                     'heldout_torque_error': loop.torque_error, 'fit_s': round(fitted, 2),
                     'law': law.describe()}
    # case 3: no torque
    t0 = time.perf_counter()
    loop = fit_closed_trig_loop([replace(window, tau=None)], VALIDATION_FRACTION)
    fitted = time.perf_counter() - t0
    if loop is None:
        cell['3'] = {'prediction_2s': None, 'why': 'no fit'}
    else:
        law = loop.law
        cell['3'] = {'prediction_2s': ahead_error(loop, data, starts, end - 1, steps),
                     'heldout_equation_error': loop.torque_error, 'fit_s': round(fitted, 2),
                     'kp_ratios': (law.kp / law.kp.mean()).tolist(),
                     'true_kp_ratios': (KP / KP.mean()).tolist(),
                     'ki_over_kp': (law.ki / law.kp).tolist(),
                     'true_ki_over_kp': ((KI if servo == 'pid' else 0.0) / KP).tolist()}
    for case in ('1', '3'):
        value = cell[case]['prediction_2s']
        cell[case]['ratio_to_follow_reference'] = (
            None if value is None else value / cell['follow_reference'])
    return cell


def main(argv=None):
    """Run every cell; return the exit code."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    parser.add_argument('--train', type=float, default=20.0, help='seconds of data')
    parser.add_argument('--seed', type=int, default=3)
    parser.add_argument('--out', default=os.path.join(HERE, 'results', 'trig_loops.json'))
    args = parser.parse_args(argv)
    results = {'meta': {'date': datetime.date.today().isoformat(), 'seed': args.seed,
                        'train_s': args.train, 'validation_fraction': VALIDATION_FRACTION,
                        'metric': '2 s-ahead θ RMSE / range, mean over joints and 16 starts '
                                  '0.5 s apart after the data',
                        'load_start': os.getloadavg()},
               'cells': {}}
    worst = 0.0
    for servo in SERVOS:
        for sensors in SENSORS:
            cell = run_cell(servo, sensors, args.train, args.seed)
            results['cells'].setdefault(servo, {})[sensors] = cell
            for case in ('1', '3'):
                c = cell[case]
                worst = max(worst, c['ratio_to_follow_reference'] or float('inf'))
                shown = ('-' if c['prediction_2s'] is None else
                         f"{c['prediction_2s']:.3%} (ratio {c['ratio_to_follow_reference']:.4f},"
                         f' fit {c["fit_s"]} s)')
                print(f'{servo:10s} {sensors:6s} case {case}: {shown}; follow reference '
                      f"{cell['follow_reference']:.2%}", flush=True)
    results['worst_ratio_to_follow_reference'] = worst
    results['meta']['load_end'] = os.getloadavg()
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, 'w', encoding='utf-8') as f:
        json.dump(results, f, indent=2)
    print(f'worst ratio {worst:.4f}; wrote {args.out}', flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())

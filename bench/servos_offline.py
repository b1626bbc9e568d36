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
Case 1 with a learned controller, offline: 2 s-ahead predictions on real servos and drivers.

The paper's arm (``core/sim``) runs ``paper_reference`` for 60 s at 100 Hz under each servo
(PD; PD + gravity compensation on the measured θ; PID, Ki = 20 N m/(rad s)) with each
sensor chain (exact; encoder noise 1e-4 rad with θ̇ by backward differences), fixed seeds.
The first 30 s are the training data, as the identifier's buffer would hold them:

- the controller law (:func:`fit_controller`: PD + integral + θ-terms on the 26 products
  of (1, cos θ_k, sin θ_k), both sides filtered, θ̇ as h′ * θ: no velocity needed);
- today's law for comparison (:func:`fit_pd_law`, plain least squares on [e, ė, 1]);
- the case-1 arm model of today's offline pipeline (:func:`fit_best`, ``--budget`` s of
  wall time) on θ, θ̇ (from noisy θ by the centred Savitzky-Golay derivative), τ.

From 30 s on, a prediction starts every 0.25 s from the measured state (θ̇ by the causal
end-point derivative when differenced) and is scored 2 s ahead against the true motion,
as RMSE / range of θ, mean over joints (the issue's metric):

- ``learned_law_true_arm``: the true arm closed with the learned law, its integral a state
  of the loop (the controller's error alone);
- ``learned_law_true_arm_held``: the same with the integral held at its start value;
- ``learned_law_fitted_arm``: the fitted arm model closed with the learned law
  (:func:`closed_loop`, rolled out by the compiled case-2 kernel, the integral by Picard
  iterations, :meth:`ClosedLoop.simulate`): what case 1 can reach;
- ``learned_law_fitted_arm_held``: the same with the integral held;
- ``pd_law_true_arm``: the true arm closed with today's PD law;
- ``follow_reference`` (θd at the target time) and ``hold_last`` (θ at the start).

``ratio_to_follow_reference`` is ``learned_law_fitted_arm`` / ``follow_reference``; the bar
is at most 1/3 and 3 %.
Writes ``bench/results/servos_offline.json``. Timings are not measured.
"""

import argparse
import datetime
import json
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from rkgnn_ros.core.data import Dataset  # noqa: E402
from rkgnn_ros.core.differentiate import causal_derivative, centred_derivative  # noqa: E402
from rkgnn_ros.core.fitting.controller import (closed_loop, fit_controller,  # noqa: E402
                                               fit_pd_law)
from rkgnn_ros.core.fitting.controller_laws import TrigFeatures  # noqa: E402
from rkgnn_ros.core.fitting.identify import fit_best  # noqa: E402
from rkgnn_ros.core.selfcheck import range_normalised_rmse  # noqa: E402
from rkgnn_ros.core.sim.plant import PlanarArm  # noqa: E402
from rkgnn_ros.core.sim.sensors import SensorModel  # noqa: E402
from rkgnn_ros.core.sim.servo import Servo  # noqa: E402
from rkgnn_ros.core.sim.simulate import simulate, SimulationError  # noqa: E402
from rkgnn_ros.core.sim.trajectories import paper_reference  # noqa: E402
from scipy.integrate import solve_ivp  # noqa: E402

N = 3
RATE = 100.0
DURATION = 60.0
SPLIT = 30.0
AHEAD = 2.0
EVERY = 0.25
KP = np.array([32.84, 42.05, 42.31])
KD = np.array([42.44, 0.19, 4.86])
ARM = PlanarArm.paper()
SERVOS = {'pd': Servo(KP, KD),
          'pd_gravity': Servo(KP, KD, gravity='measured', arm=ARM),
          'pid': Servo(KP, KD, ki=[20.0, 20.0, 20.0])}
SENSORS = {'exact': SensorModel.exact(), 'noise_1e-4_differenced': SensorModel.differenced(1e-4)}


class _Controller:
    """A fitted law as a controller of ``simulate`` with its integral held."""

    def __init__(self, law, integral_term=None):
        self.law = law
        self.integral_term = integral_term
        self.n_joints = N

    def torque(self, theta, theta_dot, theta_d, theta_d_dot):
        if self.integral_term is None:
            return self.law.torque(theta, theta_dot, theta_d, theta_d_dot)
        return self.law.torque(theta, theta_dot, theta_d, theta_d_dot, self.integral_term)


def _true_arm_with_integral(law, reference, x0, t, integral0):
    """Return θ at ``t[-1]`` of the true arm under ``law`` with its integral as a state."""
    n = N

    def rate(s, y):
        theta_d, theta_d_dot = reference.evaluate(s)
        tau = law.torque(y[:n], y[n:2 * n], theta_d, theta_d_dot,
                         integral0 + law.ki * y[2 * n:])
        return np.concatenate([ARM.dynamics(y[:2 * n], tau), theta_d - y[:n]])

    y0 = np.concatenate([x0, np.zeros(n)])
    out = solve_ivp(rate, (t[0], t[-1]), y0, method='LSODA', rtol=1e-8, atol=1e-10)
    if not out.success or not np.all(np.isfinite(out.y[:, -1])):
        return None
    return out.y[:n, -1]


def _measured_velocity(data, sensors, k=None):
    """θ̇ as the identifier would take it: measured, or from θ when differenced."""
    if sensors == 'exact':
        return data.theta_dot if k is None else data.theta_dot[k]
    if k is None:
        return centred_derivative(data.theta, data.dt)
    return causal_derivative(data.theta[:k + 1], data.dt)


def run_cell(servo_name, sensors_name, budget, seed):
    """Return the figures of one servo × sensors cell."""
    reference = paper_reference(N)
    truth = simulate(ARM, SERVOS[servo_name], reference, DURATION, rate=RATE)
    data = simulate(ARM, SERVOS[servo_name], reference, DURATION, rate=RATE,
                    noise=SENSORS[sensors_name], rng=seed)
    split = int(round(SPLIT * RATE))
    train = data.slice(0, split + 1)
    train_fit = Dataset(train.t, train.theta, _measured_velocity(train, sensors_name),
                        tau=train.tau, theta_d=train.theta_d, theta_d_dot=train.theta_d_dot)
    law = fit_controller(train, features=TrigFeatures(N), integral=True)
    pd_law = fit_pd_law(train.theta, train.theta_dot, train.tau, train.theta_d,
                        train.theta_d_dot)
    arm_model = fit_best([train_fit], 'torque', time_budget=budget, seed=seed).model
    loop = closed_loop(arm_model, law, theta_samples=train.theta)

    starts = np.arange(split, data.n_samples - int(round(AHEAD * RATE)) - 1,
                       int(round(EVERY * RATE)))
    steps = int(round(AHEAD * RATE))
    names = ('learned_law_true_arm', 'learned_law_true_arm_held', 'learned_law_fitted_arm',
             'learned_law_fitted_arm_held', 'pd_law_true_arm', 'follow_reference', 'hold_last')
    errors = {name: [] for name in names}
    diverged = dict.fromkeys(errors, 0)
    for k in starts:
        target = truth.theta[k + steps]
        x0 = np.concatenate([data.theta[k], _measured_velocity(data, sensors_name, k)])
        # the integral term now: Ki ∫e from the fit's start to this start, measured
        held = law.advance_integral(data.theta[split + 1:k + 1],
                                    data.theta_d[split + 1:k + 1], data.dt).integral_term
        t = data.t[k:k + steps + 1]
        final = _true_arm_with_integral(law, reference, x0, t, held)
        if final is None:
            diverged['learned_law_true_arm'] += 1
        else:
            errors['learned_law_true_arm'].append(final - target)
        for name, controller in (('learned_law_true_arm_held', _Controller(law, held)),
                                 ('pd_law_true_arm', _Controller(pd_law))):
            try:
                run = simulate(ARM, controller, reference, AHEAD, rate=RATE, x0=x0,
                               t0=data.t[k])
                errors[name].append(run.theta[-1] - target)
            except SimulationError:
                diverged[name] += 1
        for name, iterations in (('learned_law_fitted_arm', 3),
                                 ('learned_law_fitted_arm_held', 0)):
            states = loop.simulate(x0, t, data.theta_d[k:k + steps + 1],
                                   data.theta_d_dot[k:k + steps + 1], held, iterations)
            if np.all(np.isfinite(states[-1])):
                errors[name].append(states[-1, :N] - target)
            else:
                diverged[name] += 1
        errors['follow_reference'].append(truth.theta_d[k + steps] - target)
        errors['hold_last'].append(data.theta[k] - target)
    theta_range = np.ptp(truth.theta, axis=0)
    cell = {name: (range_normalised_rmse(np.array(e), theta_range) if len(e) else None)
            for name, e in errors.items()}
    cell['ratio_to_follow_reference'] = (cell['learned_law_fitted_arm']
                                         / cell['follow_reference']
                                         if cell['learned_law_fitted_arm'] is not None
                                         else None)
    cell['predictions'] = int(starts.size)
    cell['diverged'] = {k: v for k, v in diverged.items() if v}
    cell['law'] = law.to_dict()
    cell['law']['fold_error'] = loop.fold_error.tolist()
    cell['pd_law'] = pd_law.to_dict()
    return cell


def main(argv=None):
    """Run every cell; return the exit code."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    parser.add_argument('--budget', type=float, default=30.0,
                        help='wall-time budget of fit_best per cell (s)')
    parser.add_argument('--seed', type=int, default=3)
    parser.add_argument('--servos', default=','.join(SERVOS))
    parser.add_argument('--sensors', default=','.join(SENSORS))
    parser.add_argument('--out', default=os.path.join(HERE, 'results', 'servos_offline.json'))
    args = parser.parse_args(argv)
    results = {'meta': {'date': datetime.date.today().isoformat(), 'seed': args.seed,
                        'fit_best_budget_s': args.budget, 'train_s': SPLIT,
                        'test_s': DURATION - SPLIT, 'ahead_s': AHEAD,
                        'metric': '2 s-ahead θ RMSE over predictions every 0.25 s in the '
                                  'test part, divided by the θ range, mean over joints',
                        'bar': 'learned_law_fitted_arm <= follow_reference / 3 and <= 3 %'},
               'cells': {}}
    worst = 0.0
    for servo in args.servos.split(','):
        for sensors in args.sensors.split(','):
            print(f'== {servo} x {sensors}', flush=True)
            cell = run_cell(servo, sensors, args.budget, args.seed)
            results['cells'].setdefault(servo, {})[sensors] = cell
            for name in ('learned_law_true_arm', 'learned_law_true_arm_held',
                         'learned_law_fitted_arm', 'learned_law_fitted_arm_held',
                         'pd_law_true_arm', 'follow_reference', 'hold_last'):
                value = cell[name]
                print(f'  {name:24s} {"-" if value is None else f"{value:8.2%}"}', flush=True)
            ratio = cell['ratio_to_follow_reference']
            print(f'  ratio to following the reference: {ratio}', flush=True)
            law = cell['law']
            print(f"  law {law['form']}: kp {np.round(law['kp'], 2).tolist()} kd "
                  f"{np.round(law['kd'], 2).tolist()} ki {np.round(law['ki'], 2).tolist()} "
                  f"fit {np.round(law['fit_ratio'], 4).tolist()} fold "
                  f"{np.round(law['fold_error'], 3).tolist()}", flush=True)
            worst = max(worst, ratio if ratio is not None else float('inf'))
    results['worst_ratio_to_follow_reference'] = worst
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, 'w', encoding='utf-8') as f:
        json.dump(results, f, indent=2)
    print(f'worst ratio {worst:.3f}; wrote {args.out}', flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())

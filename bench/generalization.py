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
Does the identified model hold on motion it never saw? Planar 2-, 4-, 6-link arms and the paper's.

Arms: the n-link arms of ``bench/scaling.py`` (masses 6 to 2 kg and lengths 0.3 to 0.1 m
from base to tip, viscous 0.3, Coulomb 0.1, PD Kp 40, Kd 5) for n = 2, 4, 6, and the
paper's 3-link arm with its PD (key ``"3"``). Each is fitted on 20 s of
``paper_reference(n)`` about the hanging pose and scored on 10 s of four random sines
(amplitude 0.4 rad, 0.15-0.7 Hz) about another pose, shifted by +0.6, -0.5, +0.6, ... rad
per joint; the held-out motion reaches configurations the fit never visited. Both runs
start 1 s before the recorded window: at t = 0 the PD meets uncompensated gravity and
θ̈ peaks at 60-70 rad/s² for some 20 ms, which no smoother of 100 Hz samples can follow
(with that transient in the data even the true model scored 3-9 % torque NRMSE). Twice:
clean, and with encoder noise (θ 1e-4 rad, θ̇ 1e-3 rad/s, as ``bench/peers.py``) on both
runs.

Methods, per case (1: torque measured, 2: PD gains known, 3: nothing known), three
levels of structure in the same fit (:class:`~rkgnn_ros.core.fitting.linear.LinearDynamics`):
- ``trig``: ours, the planar chain basis, tied (the arm is known to be planar: M = Sᵀ D S
  with D_kl a cosine and sine of φ_k - φ_l, n² coefficients for M, 2n for U);
- ``trig_entries``: planar modes with a coefficient per entry of M (371 for M at n = 6);
- ``trig_generic``: no planar knowledge, every mode of degree 2 per joint allowed by the
  serial chain (any revolute arm), for n <= 4 only: at n = 6 it takes 22 461 coefficients,
  or 2709 with M's modes capped at 2 joints, and one run of that capped basis scored 84 %
  torque NRMSE with diverging rollouts (20 s of data about one pose do not determine it);
- ``least_squares``: the arm's base parameters from its own rigid-body regressor (as
  ``bench/peers.py``; it knows the arm's kinematics), cases 1 and 2;
- ``true_model``: the simulator itself.

Metrics: ``torque_nrmse``, RMSE of M θ̈ + V + G + F on the held-out run's measured states
over the standard deviation of the applied torque, per joint, joint mean; θ̈ by the
centred Savitzky-Golay window our fit chose on its own validation samples (the same
window for every method, so the true model shows the floor that smoother leaves). Case 3
identifies a model only up to one scale (it is fixed by mean Kp = 1); its torque is
scored after multiplying by the true mean Kp. ``heldout_nrmse_10s``: θ-NRMSE (RMSE / std
of the measured θ, joint mean) of a 10 s rollout from the held-out run's first measured
state: case 1 open loop, driven by the recorded torque (linear between samples); cases 2
and 3 in closed loop with the known or identified gains along the held-out reference.
Our models and least squares are rolled out by the package's Runge-Kutta-Gill
(``core/integration/rkg.py``). A rollout that diverges scores ``null`` and says so.

Writes ``bench/results/generalization.json``: per arm ("2", "3", "4", "6") and case,
ours (``trig``) as ``heldout_nrmse_10s`` and ``torque_nrmse``, the other methods under
``methods``, and the fit's diagnostics; the same under ``noisy``. No timings are written
(the machine is shared); ``--quick`` runs short, clean data only and writes nothing
unless ``--out`` is given (a check, not a result). The (arm, noise) runs go two at a time
in worker processes (``--jobs``): each is single-threaded with fixed seeds, so the figures
are those of a run one after the other.
"""

import argparse
from concurrent.futures import ProcessPoolExecutor
import datetime
import json
import multiprocessing
import os
import sys
import time

# one BLAS thread: the solves here are small, and on a loaded 2-core machine OpenBLAS's
# waiting threads made them hundreds of times slower (set before numpy is imported)
os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')

import numpy as np  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))
sys.path.insert(0, HERE)

from rkgnn_ros.core.fitting.identify import nrmse  # noqa: E402
from rkgnn_ros.core.fitting.linear import (LinearDynamics, samples_from_datasets,  # noqa: E402
                                           torque_nrmse)
from rkgnn_ros.core.integration.rkg import rkg_integrate  # noqa: E402
from rkgnn_ros.core.model.trig import TrigBasis  # noqa: E402
from rkgnn_ros.core.sim.plant import PDController, PlanarArm  # noqa: E402
from rkgnn_ros.core.sim.simulate import NoiseModel, simulate, simulate_open_loop  # noqa: E402
from rkgnn_ros.core.sim.trajectories import (hanging_pose, paper_reference,  # noqa: E402
                                             SumOfSines)
from scaling import arm as scaling_arm  # noqa: E402

CASES = {'1': 'torque', '2': 'pd_gains', '3': 'unknown'}
ARMS = ('2', '3', '4', '6')
RATE = 100.0
WARMUP = 1.0


def plant(key):
    """Return (arm, PD controller) for an arm key."""
    if key == '3':
        return PlanarArm.paper(), PDController.paper()
    return scaling_arm(int(key))


def heldout_reference(n):
    """Four random sines (seed 5), 0.4 rad, 0.15-0.7 Hz, about a shifted pose."""
    shift = np.where(np.arange(n) % 2 == 0, 0.6, -0.5)
    return SumOfSines.random(n, np.random.default_rng(5), n_terms=4, amplitude=0.4,
                             min_frequency_hz=0.15, max_frequency_hz=0.7,
                             offsets=hanging_pose(n) + shift)


def record(arm, pd, reference, duration, noisy, seed):
    """Simulate from ``WARMUP`` s before 0 and keep [0, duration]."""
    data = simulate(arm, pd, reference, duration + WARMUP, rate=RATE, t0=-WARMUP,
                    noise=NoiseModel.realistic() if noisy else None, rng=seed)
    skip = int(round(WARMUP * RATE))
    return data.slice(skip, data.n_samples)


# ----------------------------------------------------------------------------- models

class BaseLeastSquares:
    """The arm's base parameters p from τ = Y_b(θ, θ̇, θ̈) p (it knows the kinematics)."""

    def __init__(self, arm, samples):
        self.arm = arm
        n = arm.n_joints
        y = arm.base_regressor(samples.theta, samples.theta_dot, samples.theta_ddot)
        self.p, *_ = np.linalg.lstsq(y.reshape(-1, 4 * n), samples.tau.reshape(-1),
                                     rcond=None)

    def inverse_dynamics(self, theta, theta_dot, theta_ddot):
        return self.arm.base_regressor(theta, theta_dot, theta_ddot) @ self.p

    def forward_dynamics(self, theta, theta_dot, tau):
        n = self.arm.n_joints
        zeros = np.zeros(n)
        bias = self.inverse_dynamics(theta, theta_dot, zeros)
        gravity = self.inverse_dynamics(theta, zeros, zeros)
        mass = (self.arm.base_regressor(theta, zeros, np.eye(n)) @ self.p - gravity).T
        return np.linalg.solve(mass, tau - bias)


def rollout(forward, x0, t, tau=None, reference=None, gains=None, substeps=4):
    """Roll ``forward(θ, θ̇, τ)`` out with RKG: recorded τ (linear) or PD along a reference."""
    n = x0.size // 2
    if tau is not None:
        def inputs(time):
            return np.array([np.interp(time, t, tau[:, j]) for j in range(n)])

        def f(x, u):
            return np.concatenate([x[n:], forward(x[:n], x[n:], u)])
    else:
        kp, kd = gains

        def inputs(time):
            return np.concatenate(reference.evaluate(float(time)))

        def f(x, u):
            torque = kp * (u[:n] - x[:n]) + kd * (u[n:] - x[n:])
            return np.concatenate([x[n:], forward(x[:n], x[n:], torque)])
    with np.errstate(all='ignore'):
        try:
            states = rkg_integrate(f, t, x0, substeps, inputs)
        except np.linalg.LinAlgError:
            return None
    return states if np.all(np.isfinite(states)) else None


def true_rollout(arm, pd, case, held, reference):
    if case == '1':
        return simulate_open_loop(arm, held.tau, held.t, held.state[0], hold=False).theta
    return simulate(arm, pd, reference, held.t[-1] - held.t[0], rate=RATE,
                    x0=held.state[0], t0=held.t[0]).theta


def score(theta, held):
    return None if theta is None else nrmse(theta, held.theta)


# ----------------------------------------------------------------------------- one arm

def generic_basis(n):
    """Return the basis without the planar knowledge: all degree-2 modes (n <= 4; else None)."""
    return TrigBasis(n, mass_degree=2) if n <= 4 else None


def evaluate_arm(key, noisy, args, log):
    arm, pd = plant(key)
    n = arm.n_joints
    kp, kd = np.diag(pd.kp), np.diag(pd.kd)
    reference = heldout_reference(n)
    fit = record(arm, pd, paper_reference(n), args.fit_s, noisy, seed=0)
    held = record(arm, pd, reference, args.held_s, noisy, seed=1)
    out = {}
    for case, name in CASES.items():
        gains = (kp, kd) if case == '2' else (None, None)
        entry = {}
        models = {}
        for method, basis in (('trig', TrigBasis(n, planar=True, tied=True)),
                              ('trig_entries', TrigBasis(n, planar=True)),
                              ('trig_generic', generic_basis(n))):
            if basis is None:
                continue
            t0 = time.perf_counter()
            model = LinearDynamics(basis).fit(fit, name, *gains)
            models[method] = (model, time.perf_counter() - t0)
        window = models['trig'][0].window_
        acc = samples_from_datasets(held, 'torque', window=window).theta_ddot
        torque = {'true_model': arm.inverse_dynamics(held.theta, held.theta_dot, acc)}
        theta = {'true_model': true_rollout(arm, pd, case, held, reference)}
        for method, (model, _) in models.items():
            physical = model
            if case == '3':
                physical = model.scaled(kp.mean() / model.kp_.mean())
            torque[method] = physical.inverse_dynamics(held.theta, held.theta_dot, acc)
            if case == '1':
                states = model.simulate(held.state[0], held.t, tau=held.tau)
            else:
                states = model.simulate(held.state[0], held.t, reference=reference)
            theta[method] = None if not np.all(np.isfinite(states)) else states[:, :n]
        if case in ('1', '2'):
            samples = samples_from_datasets(fit, name, kp, kd, window)
            ls = BaseLeastSquares(arm, samples)
            torque['least_squares'] = ls.inverse_dynamics(held.theta, held.theta_dot, acc)
            states = rollout(ls.forward_dynamics, held.state[0], held.t,
                             tau=held.tau if case == '1' else None, reference=reference,
                             gains=(kp, kd), substeps=2 if case == '1' else 4)
            theta['least_squares'] = None if states is None else states[:, :n]
        for method in torque:
            result = {'torque_nrmse': torque_nrmse(torque[method], held.tau),
                      'heldout_nrmse_10s': score(theta[method], held),
                      'diverged': theta[method] is None}
            if method in models:
                model, seconds = models[method]
                cert = model.certificate_
                result.update({
                    'coefficients': int(model.layout_.size),
                    'ridge': model.ridge_, 'window_samples': int(model.window_),
                    'condition_number': model.condition_number(),
                    'inertia_floor': model.min_eigenvalue_, 'cuts': int(model.cuts_),
                    'floor_active_share': model.floor_active_,
                    'certified': None if cert is None else bool(cert.certified),
                    'certificate_cells': int(cert.cells) if cert is not None else None})
                if case == '3':
                    result['identified_kp'] = model.kp_.tolist()
                    result['identified_kd'] = model.kd_.tolist()
                    result['true_kp_over_mean'] = (kp / kp.mean()).tolist()
                    result['true_kd_over_mean_kp'] = (kd / kp.mean()).tolist()
                if args.timing:
                    log(f'    {method} fit {seconds:.2f} s (not recorded)')
            entry[method] = result
            shown = ('diverged' if result['diverged']
                     else f"{result['heldout_nrmse_10s']:.2%}")
            log(f"  arm {key} case {case} {'noisy' if noisy else 'clean'} {method:14s} "
                f"torque {result['torque_nrmse']:.2%}  theta {shown}")
        ours = entry['trig']
        out[case] = {'heldout_nrmse_10s': ours['heldout_nrmse_10s'],
                     'torque_nrmse': ours['torque_nrmse'], 'method': 'trig',
                     'methods': entry}
    return out


def _evaluate_task(key, noisy, args, start):
    """Run :func:`evaluate_arm` in a worker process, logging with the run's clock."""
    def log(text):
        print(f'[{time.perf_counter() - start:6.0f} s] {text}', flush=True)
    return evaluate_arm(key, noisy, args, log)


def main(argv=None):
    """Fit and score every arm and case, clean and noisy; write generalization.json."""
    parser = argparse.ArgumentParser(description='held-out accuracy of the linear fit')
    parser.add_argument('--arms', default=','.join(ARMS))
    parser.add_argument('--quick', action='store_true', help='short runs, clean only')
    parser.add_argument('--timing', action='store_true', help='print fit times')
    parser.add_argument('--jobs', type=int, default=2,
                        help='processes running (arm, noise) runs side by side')
    parser.add_argument('--out', default=None,
                        help='default bench/results/generalization.json (--quick: none)')
    args = parser.parse_args(argv)
    args.arms = [a.strip() for a in args.arms.split(',')]
    args.fit_s = 8.0 if args.quick else 20.0
    args.held_s = 4.0 if args.quick else 10.0
    start = time.perf_counter()

    def log(text):
        print(f'[{time.perf_counter() - start:6.0f} s] {text}', flush=True)

    result = {'noisy': {}}
    tasks = [(key, noisy) for noisy in ([False] if args.quick else [False, True])
             for key in args.arms]
    # the (arm, noise) runs are independent and single-threaded, with fixed seeds: two at
    # a time, the largest arms first, give the same figures in about half the time
    tasks.sort(key=lambda task: -int(task[0]))
    with ProcessPoolExecutor(max_workers=min(args.jobs, len(tasks)),
                             mp_context=multiprocessing.get_context('fork')) as pool:
        futures = {task: pool.submit(_evaluate_task, *task, args, start) for task in tasks}
        for (key, noisy), future in futures.items():
            table = result['noisy'] if noisy else result
            table[key] = future.result()
    result = {'noisy': {key: result['noisy'][key] for key in args.arms
                        if key in result['noisy']},
              **{key: result[key] for key in args.arms}}
    result['meta'] = {
        'date': datetime.date.today().isoformat(), 'quick': args.quick,
        'fit_s': args.fit_s, 'heldout_s': args.held_s, 'rate_hz': RATE,
        'warmup_s': WARMUP, 'arms': args.arms,
        'ours': 'trig: LinearDynamics with TrigBasis(n, planar=True, tied=True)',
        'metric': 'torque_nrmse: RMSE / std of the applied torque per joint, joint mean, on '
                  'the held-out measured states (theta_ddot by the Savitzky-Golay window the '
                  'fit chose); heldout_nrmse_10s: theta RMSE / std per joint, joint mean, of '
                  'a 10 s rollout from the first held-out state (case 1 open loop on the '
                  'recorded torque, cases 2-3 closed loop on the held-out reference)',
        'noise': 'theta 1e-4 rad, theta_dot 1e-3 rad/s (NoiseModel.realistic)'}
    out = args.out or (None if args.quick else os.path.join(HERE, 'results',
                                                            'generalization.json'))
    if out:
        os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
        with open(out, 'w', encoding='utf-8') as f:
            json.dump(result, f, indent=2)
        log(f'wrote {out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())

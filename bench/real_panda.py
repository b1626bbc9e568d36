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
A real Franka Panda: the rigid-body fit against the authors' published model (issue 29).

Data: the recording of Gaz et al. (RA-L 2019) in ``--data`` (default
``../shared/data/panda_gaz2019`` beside the repository; read by path, never copied): θ, θ̇
and the link-side joint torque τ of 7 joints, about 1 kHz with stamps jittering 0.7-8.8 ms,
resampled first onto a uniform 1 kHz grid (linear interpolation). The first 70 % of the
time fits, the last 30 % is held out.

Metric (the data's README): held-out torque nMSE per joint, MSE / variance of the measured
torque, θ̈ (central differences of θ̇) and τ low-passed at 20 Hz by a zero-phase
Butterworth filter (order :data:`ORDER`, forward and backward; :func:`parts` says over
which samples); a model's torque is its inverse dynamics at the measured θ, θ̇ and that θ̈.

Models:

- the fit: ``fit_torque`` (case 1) on the rigid-body structure of example-robot-data's
  ``panda.urdf`` (fingers locked), with ``measured_velocity`` True and False (``fits``).
  The headline is the one that scores better on the fit data alone: fitted on the first
  80 % of the training part, scored by the same metric on its last 20 %; the held-out
  part never chooses. ``fit_s``: wall time of building the structure from the URDF and the
  fit call, after a first fit in the process (``first_fit_s``), BLAS on one thread (scipy
  loads its own OpenBLAS: it is imported before the limit, or keeps its threads);
- plain least squares on the base parameters (no consistency, no prior) on the same
  filtered samples as the metric, each joint's rows over its RMS torque;
- the published model, τ = M(q) θ̈ + c(q, q̇) + g(q) + f(q̇), its MATLAB files translated at
  run time (:mod:`_matlab`) and checked: M symmetric positive definite, q̇ᵀ c = ½ q̇ᵀ Ṁ q̇
  (Ṁ by central differences), g beside Pinocchio's gravity of the URDF (same kinematics,
  other masses), its nMSE beside the README's 0.012. A failed check stops the bench.

Writes ``bench/results/real_panda.json``; prints the figures. Goals (issue 29): mean
nMSE ≤ 0.010, no joint above 0.04, the fit ≤ 2 s.
"""

import argparse
import datetime
import json
import os
import sys
import time
from typing import NamedTuple

from _matlab import load_function, MatlabError  # bench/_matlab.py
import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

RESULTS = os.path.join(HERE, 'results', 'real_panda.json')
DEFAULT_DATA = os.path.join('..', 'shared', 'data', 'panda_gaz2019')
URDF = 'example-robot-data:panda_description/urdf/panda.urdf'
N = 7
RATE_HZ = 1000.0
TRAIN_SHARE = 0.7
SELECT_SHARE = 0.2          # the tail of the training part that chooses measured_velocity
CUTOFF_HZ = 20.0
ORDER = 4
PUBLISHED_README_NMSE = 0.012
GRAVITY_SHARE = 0.01        # gravity is compared on joints above this share of the largest
GOALS = {'nmse_mean': 0.010, 'nmse_joint': 0.04, 'fit_s': 2.0}
FILES = {'t': 'exciting_traj_time.txt', 'theta': 'exciting_traj_positions.txt',
         'theta_dot': 'exciting_traj_velocity.txt', 'tau': 'exciting_traj_torques.txt'}
MODEL_FILES = ('get_MassMatrix', 'get_CoriolisVector', 'get_GravityVector',
               'get_FrictionTorque')


class BenchError(RuntimeError):
    """The bench cannot run; the message says why in one line."""


# -- data -------------------------------------------------------------------------------------

def load(data: str):
    """Return (t (N,), θ, θ̇, τ (N, 7)) as recorded in ``data``."""
    if not os.path.isdir(data):
        raise BenchError(f'no Panda recording at {data} (give --data DIR: the folder of '
                         'panda_gaz2019 with exciting_traj_*.txt)')
    out = {}
    for key, name in FILES.items():
        path = os.path.join(data, name)
        if not os.path.isfile(path):
            raise BenchError(f'{path} is missing')
        try:
            out[key] = np.loadtxt(path, dtype=float, ndmin=1)
        except ValueError as error:
            raise BenchError(f'{path}: not one number per line ({error})') from None
    t = out['t']
    for key in ('theta', 'theta_dot', 'tau'):
        if out[key].size != N * t.size:
            raise BenchError(f'{FILES[key]} holds {out[key].size} values, {N} x {t.size} '
                             'expected')
        out[key] = out[key].reshape(t.size, N)
    if not all(np.all(np.isfinite(v)) for v in out.values()):
        raise BenchError(f'{data}: non-finite values')
    if t.size < 100 or np.any(np.diff(t) <= 0.0):
        raise BenchError(f'{data}: the times are not increasing')
    return t, out['theta'], out['theta_dot'], out['tau']


def resample(t, *arrays, rate=RATE_HZ):
    """Return a uniform grid from t[0] at ``rate`` Hz and each array (N, 7) on it (linear)."""
    grid = t[0] + np.arange(int(np.floor((t[-1] - t[0]) * rate)) + 1) / rate
    return grid, [np.stack([np.interp(grid, t, a[:, j]) for j in range(a.shape[1])], 1)
                  for a in arrays]


class Part(NamedTuple):
    """Samples of the resampled recording with θ̈ and τ filtered (module docstring)."""

    t: np.ndarray
    theta: np.ndarray
    theta_dot: np.ndarray
    tau: np.ndarray
    theta_ddot: np.ndarray      # filtered
    tau_f: np.ndarray           # filtered

    @classmethod
    def filtered(cls, t, theta, theta_dot, tau) -> 'Part':
        """Return the samples with θ̈ and τ filtered over exactly these samples."""
        from scipy.signal import butter, sosfiltfilt
        dt = float(t[1] - t[0])
        sos = butter(ORDER, CUTOFF_HZ, fs=1.0 / dt, output='sos')
        return cls(t, theta, theta_dot, tau,
                   sosfiltfilt(sos, np.gradient(theta_dot, dt, axis=0), axis=0),
                   sosfiltfilt(sos, tau, axis=0))

    def take(self, index: slice) -> 'Part':
        """Return the samples ``index``, filtered as here (not anew)."""
        return Part(*(a[index] for a in self))

    def cut(self, share: float) -> int:
        """Return the index that ends the first ``share`` of the time."""
        return int(np.searchsorted(self.t, self.t[0] + share * (self.t[-1] - self.t[0])))

    def dataset(self):
        """Return the raw samples as the fit takes them."""
        from rkgnn_ros.core.data import Dataset
        return Dataset(self.t, self.theta, self.theta_dot, tau=self.tau)

    def nmse(self, torque) -> np.ndarray:
        """Return the nMSE per joint of a model's ``torque`` (K, 7) here."""
        return np.mean((torque - self.tau_f) ** 2, axis=0) / np.var(self.tau_f, axis=0)


def parts(grid, theta, theta_dot, tau):
    """
    Return (train, held): the first 70 % of the time and the last 30 %.

    ``held`` is filtered over the whole recording (the target the scores compare with;
    filtering a part alone adds edge transients), ``train`` over itself alone: the least
    squares reference and the choice of the fit's default see nothing of ``held``.
    """
    whole = Part.filtered(grid, theta, theta_dot, tau)
    cut = whole.cut(TRAIN_SHARE)
    return Part.filtered(*(a[:cut] for a in (grid, theta, theta_dot, tau))), \
        whole.take(slice(cut, None))


# -- models -----------------------------------------------------------------------------------

def fit_rigid(arm, train: Part, measured_velocity: bool):
    """Return (the fitted RigidArm, seconds for the structure and the fit)."""
    from rkgnn_ros.core.fitting.rigid_fit import fit_torque
    from rkgnn_ros.core.rigid.structure import RigidStructure
    start = time.perf_counter()
    structure = RigidStructure(arm.urdf, arm.joint_names)
    fit = fit_torque(structure, [train.dataset()], [], measured_velocity=measured_velocity)
    seconds = time.perf_counter() - start
    if fit is None:
        raise BenchError(f'fit_torque(measured_velocity={measured_velocity}) returned None')
    return fit.arm, seconds


def least_squares(structure, train: Part) -> np.ndarray:
    """Return the full parameters (base ones, the rest zero) of plain least squares."""
    base = structure.base
    rows = structure.rows(train.theta, train.theta_dot, train.theta_ddot, base.independent)
    weights = np.tile(1.0 / np.sqrt(np.mean(train.tau_f ** 2, axis=0)), train.t.size)
    beta, *_ = np.linalg.lstsq(rows * weights[:, None], train.tau_f.reshape(-1) * weights,
                               rcond=None)
    full = np.zeros(structure.n_parameters)
    full[base.independent] = beta
    return full


class Published:
    """The authors' model, τ = M θ̈ + c + g + f, from their MATLAB files (read at run time)."""

    def __init__(self, folder: str):
        self.functions = {}
        for name in MODEL_FILES:
            path = os.path.join(folder, name + '.m')
            if not os.path.isfile(path):
                raise BenchError(f'{path} is missing')
            try:
                self.functions[name] = load_function(path)
            except MatlabError as error:
                raise BenchError(str(error)) from None

    def mass(self, q):
        """Return M(q), (K, 7, 7)."""
        return self.functions['get_MassMatrix'](q)

    def coriolis(self, q, dq):
        """Return c(q, q̇), (K, 7)."""
        return self.functions['get_CoriolisVector'](q, dq)

    def gravity(self, q):
        """Return g(q), (K, 7)."""
        return self.functions['get_GravityVector'](q)

    def friction(self, dq):
        """Return f(q̇), (K, 7)."""
        return self.functions['get_FrictionTorque'](dq)

    def torque(self, q, dq, ddq):
        """Return τ, (K, 7)."""
        return (np.einsum('kij,kj->ki', self.mass(q), ddq) + self.coriolis(q, dq)
                + self.gravity(q) + self.friction(dq))


def published_checks(model: Published, arm, held: Part, nmse_mean: float) -> dict:
    """Return the translation's checks (module docstring); ``ok`` says all passed."""
    q, dq = held.theta, held.theta_dot
    m = model.mass(q)
    eig = np.linalg.eigvalsh(0.5 * (m + np.swapaxes(m, 1, 2)))
    every = slice(None, None, max(1, q.shape[0] // 200))
    qs, dqs = q[every], dq[every]
    h = 1e-6
    m_dot = (model.mass(qs + h * dqs) - model.mass(qs - h * dqs)) / (2.0 * h)
    power = np.einsum('ki,ki->k', dqs, model.coriolis(qs, dqs))
    half = 0.5 * np.einsum('ki,kij,kj->k', dqs, m_dot, dqs)
    g_pub, g_urdf = model.gravity(q), arm.gravity_terms(q)
    rms_urdf = np.sqrt(np.mean(g_urdf ** 2, 0))
    ratio = np.sqrt(np.mean(g_pub ** 2, 0)) / np.maximum(rms_urdf, 1e-300)
    corr = np.array([np.corrcoef(g_pub[:, j], g_urdf[:, j])[0, 1] if np.std(g_urdf[:, j])
                     > 1e-9 else np.nan for j in range(N)])
    # joints whose gravity torque matters (joint 1 turns about the vertical: none; the
    # wrist's last joint carries hundredths of a N m, set by the hand's centre of mass)
    moving = rms_urdf > GRAVITY_SHARE * np.max(rms_urdf)
    out = {
        'mass_matrix_asymmetry': float(np.max(np.abs(m - np.swapaxes(m, 1, 2)))),
        'mass_matrix_min_eigenvalue': float(np.min(eig)),
        'coriolis_power_relative_error': float(np.sqrt(np.mean((power - half) ** 2))
                                               / np.sqrt(np.mean(power ** 2))),
        'gravity_vs_urdf_correlation': [None if not np.isfinite(c) else float(c)
                                        for c in corr],
        'gravity_vs_urdf_rms_ratio': [float(v) for v in ratio],
        'gravity_checked_joints': [int(j) + 1 for j in np.flatnonzero(moving)],
        'gravity_urdf_rms': [float(v) for v in rms_urdf],
        'gravity_joint1_max_abs': float(np.max(np.abs(g_pub[:, 0]))),
    }
    out['ok'] = bool(
        out['mass_matrix_asymmetry'] < 1e-9 and out['mass_matrix_min_eigenvalue'] > 0.0
        and out['coriolis_power_relative_error'] < 1e-4
        and np.all(corr[moving] > 0.9) and np.all((ratio[moving] > 0.5) & (ratio[moving] < 2.0))
        and out['gravity_joint1_max_abs'] < 1e-9
        and 0.5 * PUBLISHED_README_NMSE < nmse_mean < 2.0 * PUBLISHED_README_NMSE)
    return out


# -- the bench --------------------------------------------------------------------------------

def _figures(nmse) -> dict:
    return {'nmse_per_joint': [float(v) for v in nmse], 'nmse_mean': float(np.mean(nmse))}


def run(data: str) -> dict:
    """Return the result dict (module docstring)."""
    from rkgnn_ros.core.sim.urdf_arm import UrdfArm
    t, theta, theta_dot, tau = load(data)
    grid, (theta, theta_dot, tau) = resample(t, theta, theta_dot, tau)
    train, held = parts(grid, theta, theta_dot, tau)
    inner_cut = train.cut(1.0 - SELECT_SHARE)
    inner, choose = train.take(slice(None, inner_cut)), train.take(slice(inner_cut, None))
    arm = UrdfArm(URDF)
    if arm.joint_names != tuple(f'panda_joint{j}' for j in range(1, N + 1)):
        raise BenchError(f'{URDF}: unexpected moving joints {arm.joint_names}')

    fits, first_fit_s = {}, None
    for measured in (True, False):
        small, seconds = fit_rigid(arm, inner, measured)
        first_fit_s = seconds if first_fit_s is None else first_fit_s
        choice = choose.nmse(small.inverse_dynamics(choose.theta, choose.theta_dot,
                                                    choose.theta_ddot))
        fits[f'measured_velocity_{measured}'] = {'selection_nmse_mean': float(np.mean(choice))}
    for measured in (True, False):
        fitted, seconds = fit_rigid(arm, train, measured)
        entry = fits[f'measured_velocity_{measured}']
        torque = fitted.inverse_dynamics(held.theta, held.theta_dot, held.theta_ddot)
        entry.update(_figures(held.nmse(torque)))
        entry.update({'fit_s': seconds, 'consistent': fitted.consistent(),
                      'samples': int(fitted.info['samples']),
                      'evaluations': int(fitted.info['evaluations'])})
    chosen = min((True, False),
                 key=lambda m: fits[f'measured_velocity_{m}']['selection_nmse_mean'])
    head = fits[f'measured_velocity_{chosen}']

    structure = fitted.structure
    ls = least_squares(structure, train)
    ls_nmse = held.nmse(structure.inverse_dynamics(ls, held.theta, held.theta_dot,
                                                   held.theta_ddot))
    model = Published(os.path.join(data, 'published_model'))
    pub_nmse = held.nmse(model.torque(held.theta, held.theta_dot, held.theta_ddot))
    checks = published_checks(model, arm, held, float(np.mean(pub_nmse)))
    if not checks['ok']:
        raise BenchError(f"the published model's translation fails its checks: {checks}")

    result = {
        'nmse_per_joint': head['nmse_per_joint'], 'nmse_mean': head['nmse_mean'],
        'published_nmse_per_joint': [float(v) for v in pub_nmse],
        'published_nmse_mean': float(np.mean(pub_nmse)),
        'least_squares_nmse_per_joint': [float(v) for v in ls_nmse],
        'least_squares_nmse_mean': float(np.mean(ls_nmse)),
        'fit_s': head['fit_s'], 'first_fit_s': first_fit_s,
        'measured_velocity': chosen, 'consistent': head['consistent'],
        'goals': dict(GOALS),
        'goals_met': bool(head['nmse_mean'] <= GOALS['nmse_mean']
                          and max(head['nmse_per_joint']) <= GOALS['nmse_joint']
                          and head['fit_s'] <= GOALS['fit_s']),
        'fits': fits, 'published_checks': checks,
    }
    result['meta'] = _meta(data, grid, train, held, structure)
    return result


def single_threaded_blas() -> str:
    """Limit every BLAS (numpy's and scipy's own) to one thread; return what was limited."""
    import scipy.linalg  # noqa: F401 - scipy's OpenBLAS must be loaded to be limited
    import scipy.optimize  # noqa: F401
    import scipy.signal  # noqa: F401
    try:
        from threadpoolctl import threadpool_info, threadpool_limits
    except ImportError:
        return 'threadpoolctl missing: BLAS kept its threads'
    threadpool_limits(limits=1, user_api='blas')
    return ', '.join(f"{os.path.basename(i['filepath'])}: {i['num_threads']} thread(s)"
                     for i in threadpool_info() if i['user_api'] == 'blas')


def _meta(data, grid, train, held, structure) -> dict:
    return {
        'date': datetime.date.today().isoformat(),
        'data': f'{os.path.relpath(os.path.abspath(data), ROOT)} (Gaz et al. RA-L 2019, '
                'exciting trajectory 1, real Franka Panda, link-side torque sensors)',
        'resampling': f'linear interpolation onto a uniform {RATE_HZ:g} Hz grid '
                      f'({grid.size} samples, {grid[-1] - grid[0]:.3f} s) from stamps '
                      'jittering 0.7-8.8 ms',
        'split': f'first {TRAIN_SHARE:.0%} of the time fits ({train.t.size} samples), last '
                 f'{1 - TRAIN_SHARE:.0%} held out ({held.t.size} samples)',
        'metric': 'held-out torque nMSE per joint = MSE / variance of the measured torque; '
                  f'theta_ddot (central differences of theta_dot) and tau low-passed at '
                  f'{CUTOFF_HZ:g} Hz by a zero-phase Butterworth filter of order {ORDER} '
                  '(scipy sosfiltfilt, forward and backward); the held-out scores compare with '
                  'the whole recording filtered once, the least squares reference and the '
                  "choice of the fit's default use the training part filtered alone; model "
                  'torque = inverse dynamics at the measured theta, theta_dot and that '
                  'theta_ddot',
        'model': f'{URDF} (fingers locked): {structure.describe()}',
        'fit': 'rkgnn_ros.core.fitting.rigid_fit.fit_torque (case 1, physically '
               'consistent), measured_velocity chosen by the fit data alone: fitted on the '
               f'first {1 - SELECT_SHARE:.0%} of the training part, scored by the metric '
               f'on its last {SELECT_SHARE:.0%}',
        'fit_s': 'wall time of RigidStructure(urdf, joints) (base parameters included) plus '
                 'fit_torque on the training part, BLAS limited to one thread; the data '
                 'loading and filtering excluded; first_fit_s is the first fit in the '
                 'process (compiled kernels loaded from their cache)',
        'least_squares': 'plain least squares on the base parameters (no consistency, no '
                         'prior) on the filtered training samples of the metric, each '
                         "joint's rows divided by its RMS torque",
        'published': 'tau = M(q) theta_ddot + c(q, q_dot) + g(q) + f(q_dot) from the '
                     "authors' get_MassMatrix.m, get_CoriolisVector.m, get_GravityVector.m, "
                     'get_FrictionTorque.m, translated at run time by bench/_matlab.py',
        'goals': 'issue 29: nmse_mean <= 0.010, no joint above 0.04, fit_s <= 2',
    }


def main(argv=None) -> int:
    """Run the bench and write bench/results/real_panda.json."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0].strip())
    parser.add_argument('--data', default=os.path.join(ROOT, DEFAULT_DATA),
                        help='the panda_gaz2019 folder (default ../shared/data/panda_gaz2019 '
                             'beside the repository)')
    parser.add_argument('--out', default=RESULTS, help='the JSON to write')
    args = parser.parse_args(argv)
    blas = single_threaded_blas()
    try:
        result = run(args.data)
    except BenchError as error:
        print(f'real_panda: {error}', file=sys.stderr)
        return 2
    result['meta']['blas'] = blas
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, 'w', encoding='utf-8') as f:
        json.dump(result, f, indent=2)
    print(json.dumps({k: v for k, v in result.items() if k not in ('meta', 'fits')},
                     indent=1), flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())

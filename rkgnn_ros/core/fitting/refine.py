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
Levenberg-Marquardt refinement of a genome on the rollout (output-error) residuals.

The residuals are the weighted differences between the RKG rollout and every measured
state, ``(x̂_k - x_k) · w`` with w = [1/spread(θ), 0.3/rms(θ̇)]. Their Jacobian comes from
forward differences: the N + 1 perturbed genomes form one population that the compiled
kernel rolls out in parallel, so one Jacobian costs one generation of N + 1 individuals.

Long rollouts of a poor model diverge, which makes the residuals discontinuous. The
refinement therefore starts on short multiple-shooting windows (restarts from the measured
state every ``shooting`` samples; nearly linear residuals) and continues on longer ones
(continuation), ending with the full rollout. A diverged prediction contributes a fixed
residual, so a trust-region step into divergence is rejected.
"""

from contextlib import contextmanager
import ctypes
import time
from typing import List, NamedTuple, Optional, Sequence

import numpy as np
from scipy.optimize import least_squares

from .fitness import FitnessProblem, Interrupted
from ..model.network import BatchedNetwork

DIVERGED_RESIDUAL = 10.0


class _Deadline(Exception):
    pass


def _openblas_controls():
    """(get, set) thread-count functions of every OpenBLAS loaded in this process (Linux)."""
    try:
        with open('/proc/self/maps') as maps:
            paths = {line.split()[-1] for line in maps if 'openblas' in line.lower()}
    except OSError:  # pragma: no cover - not Linux
        return []
    controls = []
    for path in sorted(paths):
        try:
            lib = ctypes.CDLL(path)
        except OSError:  # pragma: no cover
            continue
        for prefix in ('scipy_', ''):
            for suffix in ('64_', ''):
                get = getattr(lib, f'{prefix}openblas_get_num_threads{suffix}', None)
                put = getattr(lib, f'{prefix}openblas_set_num_threads{suffix}', None)
                if get is not None and put is not None:
                    controls.append((get, put))
    return controls


@contextmanager
def blas_threads(count=1):
    """
    Limit OpenBLAS (numpy's and scipy's) to ``count`` threads inside the block.

    The least-squares steps factorise small dense Jacobians between parallel kernel calls;
    multithreaded OpenBLAS on such matrices, on a machine that is busy anyway, spins and
    can be slower than one thread by orders of magnitude (README, numerical core).
    """
    controls = _openblas_controls()
    before = [get() for get, _ in controls]
    for _, put in controls:
        put(int(count))
    try:
        yield
    finally:
        for (_, put), value in zip(controls, before):
            put(int(value))


def residual_weights(problem: FitnessProblem) -> np.ndarray:
    """Weights of the state residuals, shape (2n,): 1/spread(θ) and 0.3/rms(θ̇)."""
    s = problem.scales
    return np.concatenate([1.0 / s.theta_spread, 0.3 / s.velocity])


def refine_lm(problem_for, genome, shootings: Sequence[int] = (20, 0), max_nfev=30,
              deadline: Optional[float] = None, callback=None):
    """
    Refine ``genome`` by trust-region least squares over a continuation of shooting windows.

    Parameters
    ----------
    problem_for : callable
        ``problem_for(shooting) -> FitnessProblem`` (same data, scales and settings).
    genome : ndarray, shape (N,)
        Start genome.
    shootings : sequence of int
        Multiple-shooting intervals, one stage each (0 = the full rollout).
    max_nfev : int
        Residual evaluations per stage (scipy's ``max_nfev``).
    deadline : float, optional
        ``time.perf_counter()`` value at which to stop (the best genome so far is kept; so
        it is when the thread's stop event interrupts a rollout, :func:`.fitness.interrupt_on`).
    callback : callable, optional
        Called with a dict after every stage.

    Returns
    -------
    genome : ndarray, shape (N,)
    history : list of dict
        One entry per stage: shooting, cost (mean squared weighted residual), evaluations.

    """
    g = np.array(genome, dtype=float)
    history: List[dict] = []
    evaluations = 0
    for shooting in shootings:
        problem = problem_for(int(shooting))
        w = residual_weights(problem)
        x_meas = problem.x_meas
        best = {'cost': np.inf, 'g': g.copy()}

        def residuals(population):
            pred = problem.rollouts(population)
            r = ((pred - x_meas[None]) * w).reshape(population.shape[0], -1)
            return np.nan_to_num(r, nan=DIVERGED_RESIDUAL, posinf=DIVERGED_RESIDUAL,
                                 neginf=-DIVERGED_RESIDUAL)

        def fun(x):
            nonlocal evaluations
            if deadline is not None and time.perf_counter() > deadline:
                raise _Deadline()
            r = residuals(x[None])[0]
            evaluations += 1
            cost = float(np.mean(np.square(r)))
            if cost < best['cost']:
                best['cost'] = cost
                best['g'] = x.copy()
            return r

        def jac(x):
            nonlocal evaluations
            if deadline is not None and time.perf_counter() > deadline:
                raise _Deadline()
            step = 1e-6 * np.maximum(1.0, np.abs(x))
            pop = np.vstack([x[None], x[None] + np.diag(step)])
            r = residuals(pop)
            evaluations += pop.shape[0]
            return ((r[1:] - r[0]) / step[:, None]).T

        try:
            with blas_threads(1):
                least_squares(fun, g, jac=jac, method='trf', x_scale='jac', max_nfev=max_nfev)
        except (_Deadline, Interrupted):  # past the deadline or the thread's stop event
            interrupted = True
        else:
            interrupted = False
        g = best['g']
        entry = {'phase': 'lm', 'shooting': int(shooting), 'cost': best['cost'],
                 'evaluations': evaluations}
        history.append(entry)
        if callback is not None:
            callback(entry)
        if interrupted or (deadline is not None and time.perf_counter() > deadline):
            break
    return g, history


def _equation_data(spec, datasets, kp, kd, window, max_samples):
    """States, θ̈ (Savitzky-Golay), inputs and target torques of the equation error."""
    from .warmstart import estimate_acceleration
    x = np.vstack([d.state for d in datasets])
    acc = np.vstack([estimate_acceleration(d.theta_dot, d.dt, window) for d in datasets])
    n = spec.n_joints
    if spec.case == 'torque':
        u = np.zeros((x.shape[0], n))
        tau = np.vstack([d.tau for d in datasets])
    else:
        u = np.hstack([np.vstack([d.theta_d for d in datasets]),
                       np.vstack([d.theta_d_dot for d in datasets])])
        if spec.case == 'pd_gains':
            err, derr = u[:, :n] - x[:, :n], u[:, n:] - x[:, n:]
            tau = err * np.asarray(kp, dtype=float) + derr * np.asarray(kd, dtype=float)
        else:
            tau = None  # the torque network's output
    step = max(1, -(-x.shape[0] // int(max_samples)))
    sel = slice(None, None, step)
    return x[sel], acc[sel], u[sel], None if tau is None else tau[sel]


def equation_residuals(spec, scales, genomes, data, kp=None, kd=None, gauge_weight=1.0,
                       compiled=True):
    """
    Inverse-dynamics residuals of a population, one row per genome.

    Parameters
    ----------
    spec : NetworkSpec
        Network structure.
    scales : Scales
        Decoding scales.
    genomes : ndarray, shape (P, N)
        Normalised genomes.
    data : (x, acc, u, tau)
        ``x`` (S, 2n): measured states [θ, θ̇]; ``acc`` (S, n): θ̈ at the same samples;
        ``u`` (S, 2n): [θd, θ̇d] (shape (S, n) and ignored in case 'torque'); ``tau``
        (S, n) or None: applied torque (cases 'torque' and 'pd_gains'; None: the torque
        network's output).
    kp, kd : array_like, optional
        Known gains (case 'pd_gains').
    gauge_weight : float
        Case 'unknown': weight of the extra residual mean(diag M / inertia scale) - 1.
    compiled : bool
        M θ̈ + V + G by the compiled kernel (parallel over genomes), else by the batched
        numpy network (the reference).

    Returns
    -------
    ndarray, shape (P, S * n [+ 1])
        (M θ̈ + V + G + F - τ) / (torque scale · sqrt(S)), so the squared sum is the mean
        over samples; the gauge residual is appended in case 'unknown'.

    """
    x, acc, u, tau = data
    genomes = np.atleast_2d(np.asarray(genomes, dtype=float))
    pop, samples = genomes.shape[0], x.shape[0]
    n = spec.n_joints
    params = spec.decode(genomes, scales)
    xt = np.tile(x, (pop, 1))
    ut = np.tile(u, (pop, 1))

    def network():
        # one network row per (genome, sample): it evaluates one state per row
        return BatchedNetwork(spec, params.repeat(samples), scales, kp, kd)

    with np.errstate(all='ignore'):
        if compiled:
            from ..model.kernels import inverse_dynamics_terms
            c = np.ascontiguousarray
            mv = np.empty((pop, samples, n))
            diag = np.empty((pop, samples, n))
            inverse_dynamics_terms(c(x), c(acc), spec.constants(scales), params, mv, diag)
            fric = (params.viscous[:, None] * x[None, :, n:] + params.coulomb[:, None]
                    * np.tanh(x[None, :, n:] / spec.coulomb_velocity))
            lhs = (mv + fric).reshape(pop * samples, n)
            diag = diag.reshape(pop * samples, n)
            target = network().torque(xt, ut) if tau is None else np.tile(tau, (pop, 1))
        else:
            t = network().terms(xt, ut)
            lhs = (np.einsum('pij,pj->pi', t['M'], np.tile(acc, (pop, 1))) + t['V'] + t['G']
                   + t['F'])
            target = t['tau'] if tau is None else np.tile(tau, (pop, 1))
            diag = np.diagonal(t['M'], axis1=1, axis2=2)
        r = ((lhs - target) / scales.torque).reshape(pop, samples * n) / np.sqrt(samples)
        if spec.case == 'unknown':
            level = np.mean((diag / scales.inertia).reshape(pop, -1), axis=1)
            r = np.hstack([r, gauge_weight * (level - 1.0)[:, None]])
    return np.nan_to_num(r, nan=DIVERGED_RESIDUAL, posinf=DIVERGED_RESIDUAL,
                         neginf=-DIVERGED_RESIDUAL)


class EquationFitOptions(NamedTuple):
    """The limits of :func:`refine_equation_error`'s fit (see there)."""

    max_nfev: object = 200
    window: object = 7
    max_samples: object = 600
    deadline: Optional[float] = None
    ftol: object = 1e-10
    ridge: object = 0.0


def refine_equation_error(spec, datasets, scales, genome, kp=None, kd=None, **options):
    """
    Fit a genome to the inverse dynamics: M θ̈ + V + G + F = τ at every sample.

    The equation error needs no rollout, so a residual costs one network evaluation over
    the samples and a forward-difference Jacobian one evaluation of N + 1 genomes at once:
    a fast first stage that places M, G and friction where the data put them before the
    output-error stages (:func:`refine_lm`), which no short shooting window constrains
    well (gravity against the slow modes). θ̈ comes from a Savitzky-Golay derivative of θ̇.
    τ is the measured torque (case 1), the known PD law (case 2) or the torque network
    (case 3; one more residual then fixes the gauge: mean diag(M) over the data equals the
    inertia scale).

    Parameters
    ----------
    spec : NetworkSpec
        Network structure.
    datasets : list of Dataset
        Training segments.
    scales : Scales
        Decoding scales.
    genome : ndarray, shape (N,)
        Start genome.
    kp, kd : array_like, optional
        Known gains (case 'pd_gains').
    max_nfev : int
        Residual evaluations (scipy's ``max_nfev``).
    window : int
        Savitzky-Golay window for θ̈ (samples).
    max_samples : int
        The data are thinned to at most this many samples.
    deadline : float, optional
        ``time.perf_counter()`` value at which to stop (the best genome so far is kept).
    ftol : float
        Relative cost decrease that ends the fit.
    ridge : float
        Weight of the extra residuals sqrt(ridge) · (genome - start genome): keeps elements
        the data do not determine near the start (smoother, better off the training path).

    Returns
    -------
    genome : ndarray, shape (N,)
    cost : float
        Sum of squared residuals (mean squared torque error in units of its RMS).

    """
    max_nfev, window, max_samples, deadline, ftol, ridge = EquationFitOptions(**options)
    x, acc, u, tau = _equation_data(spec, list(datasets), kp, kd, window, max_samples)

    start = np.array(genome, dtype=float)
    root = np.sqrt(float(ridge))

    def residuals(pop):
        if deadline is not None and time.perf_counter() > deadline:
            raise _Deadline()
        r = equation_residuals(spec, scales, pop, (x, acc, u, tau), kp, kd)
        return np.hstack([r, root * (pop - start)]) if ridge > 0 else r

    best = {'g': start.copy(), 'cost': np.inf}

    def fun(g):
        r = residuals(g[None])[0]
        cost = float(np.sum(np.square(r)))
        if cost < best['cost']:
            best['cost'], best['g'] = cost, g.copy()
        return r

    def jac(g):
        step = 1e-6 * np.maximum(1.0, np.abs(g))
        r = residuals(np.vstack([g[None], g[None] + np.diag(step)]))
        return ((r[1:] - r[0]) / step[:, None]).T

    try:
        with blas_threads(1):
            least_squares(fun, best['g'], jac=jac, method='trf', x_scale='jac',
                          max_nfev=max_nfev, ftol=ftol, xtol=1e-10, gtol=1e-10)
    except _Deadline:
        pass
    return best['g'], best['cost']

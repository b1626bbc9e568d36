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
The arm's own controller, estimated from measured torque, to predict case 1 in closed loop.

In case 1 the applied torque is measured, so a model of the arm alone predicts the future
only if the future torque is known. When the arm is servoed to a commanded trajectory, the
torque it will apply is the controller's answer to the state it will reach: fitting the
controller's law from the buffered torque and commands (from ``joint_commands``, or the
plan sampled at the state times: the fit takes arrays, whatever their source) lets the
case-1 arm model be rolled out in closed loop along the plan, by the compiled case-2
kernels, with gains that were measured instead of given.

Two fits live here (the laws they return are records of :mod:`.controller_laws`):

- :func:`fit_pd_law` (:class:`PDLaw`): τ = Kp e + Kd ė + c by least squares on the raw
  samples, e = θd − θ. Exact on a pure PD with exact sensors.
- :func:`fit_controller` (:class:`ControllerLaw`): the general law a real servo runs,

      τ = Kp e + Kd ė + Ki ∫e + c + W φ(θ or θd) [+ K_v θ̇d],

  with the pure PD as its special case. φ are the **arm model's own θ-features** (its RBF
  units, :class:`RBFFeatures`), so a gravity compensation Ĝ(θ) regressed on them folds
  exactly into the model's gravity output: the closed loop "arm model + law" is again a
  case-2 model (:func:`closed_loop`) with the fitted gains, G − W φ in the gravity weights,
  and everything that depends on time or on the commands only (c, the integral held at its
  current value, W φ(θd), K_v θ̇d) folded into a shifted command θd' = θd + (…) / Kp.

Encoder noise. With θ̇ differenced from noisy θ, the regressor ė carries white noise of
about √2 σ_θ / dt while the servo acted on the true ė: least squares then shrinks Kd
towards zero (errors in variables). :func:`fit_controller` filters **both sides** of the
regression with one Gaussian low-pass h (``filter_sigma``, passing about
1 / (2π σ) Hz) and takes h * θ̇ as h′ * θ, the derivative of the kernel applied to the
positions (:func:`rkgnn_ros.core.differentiate.gaussian_kernels`). A linear filter keeps
the law's equation exact (every regressor and the torque get the same h), the noise above
the band of the motion is removed from every regressor at once, the derivative has no lag,
and no velocity measurement is needed at all (a driver without velocity works the same).
Instrumental variables would be consistent too but need instruments for every θ-feature
and have a large variance with the weak instruments a well-tracking servo leaves; total
least squares needs the noise ratio of every column, which differs by orders of magnitude.

The integral term. A held integral folds into the command shift, so the compiled kernels
roll the loop out unchanged, but over 2 s it moves by Ki ∫e, and with an integral time
Kp / Ki of the order of the horizon that is not small (on the paper's arm with Ki = 20, a
held integral alone costs 4 % of the θ range 2 s ahead). Rather than a state the kernels do
not have, :meth:`ClosedLoop.simulate` iterates: roll out with the integral held, integrate
Ki (θd − θ̂) along that rollout, fold the resulting I(t) into the command, roll out again
(Picard iteration of the integral's equation; each pass is one compiled rollout). A
saturating servo is detected from the torque's plateaus: saturated samples are left out of
the fit and the level is kept in ``tau_limit`` (the closed-loop rollout itself does not
saturate).
"""

from dataclasses import dataclass, replace
from typing import List, Optional, Sequence, Union

import numpy as np

from .controller_laws import (ControllerLaw, DEFAULT_FILTER_SIGMA, PDLaw, RBFFeatures,
                              THETA_INPUTS)
from ..data import Dataset
from ..differentiate import gaussian_kernels
from ..model.model import RKGNNModel

__all__ = ['fit_pd_law', 'closed_loop_model', 'open_loop_model', 'fit_controller',
           'ClosedLoop', 'closed_loop']

#: Default Picard iterations of the integral term over a closed-loop rollout
#: (:meth:`ClosedLoop.simulate`).
INTEGRAL_ITERATIONS = 3


def fit_pd_law(theta, theta_dot, tau, theta_d, theta_d_dot,
               min_samples: int = 20) -> Optional[PDLaw]:
    """
    Fit τ_i = kp_i e_i + kd_i ė_i + c_i per joint by least squares.

    Parameters
    ----------
    theta, theta_dot, tau, theta_d, theta_d_dot : array_like, shape (K, n)
        Paired samples: measured state, applied torque, commanded state.
    min_samples : int
        Fewer finite samples than this give None.

    Returns
    -------
    PDLaw or None
        None when there are too few samples or a joint's regressors are degenerate (the
        error never varied, so the gains are not identifiable).

    """
    inputs = (theta, theta_dot, tau, theta_d, theta_d_dot)
    arrays = [np.asarray(a, dtype=float) for a in inputs]
    shape = arrays[0].shape
    if len(shape) != 2 or any(a.shape != shape for a in arrays):
        raise ValueError(f'all inputs must have the same shape (K, n), got '
                         f'{[a.shape for a in arrays]}')
    theta, theta_dot, tau, theta_d, theta_d_dot = arrays
    finite = np.all([np.isfinite(a).all(axis=1) for a in arrays], axis=0)
    if int(finite.sum()) < max(int(min_samples), 3):
        return None
    e = (theta_d - theta)[finite]
    e_dot = (theta_d_dot - theta_dot)[finite]
    tau = tau[finite]
    n = shape[1]
    kp, kd, bias, ratio = (np.empty(n) for _ in range(4))
    for i in range(n):
        a = np.column_stack([e[:, i], e_dot[:, i], np.ones(e.shape[0])])
        scale = np.sqrt(np.mean(a * a, axis=0))
        scale[scale == 0.0] = 1.0
        coef, _, rank, sv = np.linalg.lstsq(a / scale, tau[:, i], rcond=None)
        if rank < 3 or sv[-1] < 1e-8 * sv[0]:
            return None
        coef = coef / scale
        residual = tau[:, i] - a @ coef
        rms_tau = np.sqrt(np.mean(tau[:, i] ** 2))
        kp[i], kd[i], bias[i] = coef
        ratio[i] = np.sqrt(np.mean(residual ** 2)) / rms_tau if rms_tau > 0 else np.inf
    return PDLaw(kp, kd, bias, ratio, int(finite.sum()))


def closed_loop_model(model: RKGNNModel, law: PDLaw) -> RKGNNModel:
    """
    Return the case-1 ``model`` closed with the fitted ``law``, as a case-2 model.

    Its inputs are the commanded θd + ``law.shift()`` and θ̇d. The genome is shared: a
    case-1 and a case-2 network have the same layout.
    """
    if model.case != 'torque':
        raise ValueError(f"closed_loop_model needs a case 'torque' model, got {model.case!r}")
    if law.kp.shape != (model.n_joints,):
        raise ValueError(f'the law is for {law.kp.size} joints, the model has '
                         f'{model.n_joints}')
    spec = replace(model.spec, case='pd_gains')
    return RKGNNModel(spec, model.scales, model.genome, joint_names=model.joint_names,
                      kp=law.kp, kd=law.kd, dt=model.dt, substeps=model.substeps,
                      info=dict(model.info, closed_loop='fitted PD law'))


def open_loop_model(model: RKGNNModel, info=None) -> RKGNNModel:
    """
    Return the arm model of a closed-loop (case-2) ``model`` as a case-1 model.

    The inverse of :func:`closed_loop_model`: same genome, torque as the input. ``info``
    replaces the model's info when given.
    """
    if model.case != 'pd_gains':
        raise ValueError(f"open_loop_model needs a case 'pd_gains' model, got {model.case!r}")
    spec = replace(model.spec, case='torque')
    return RKGNNModel(spec, model.scales, model.genome, joint_names=model.joint_names,
                      dt=model.dt, substeps=model.substeps,
                      info=dict(model.info if info is None else info))


def _segments(data) -> List[Dataset]:
    segments = [data] if isinstance(data, Dataset) else list(data)
    if not segments:
        raise ValueError('no data')
    for seg in segments:
        if not isinstance(seg, Dataset):
            raise TypeError(f'expected Dataset segments, got {type(seg).__name__}')
        if seg.tau is None or seg.theta_d is None or seg.theta_d_dot is None:
            raise ValueError('the controller fit needs tau, theta_d and theta_d_dot')
    dt = segments[0].dt
    if any(abs(seg.dt - dt) > 1e-6 * dt for seg in segments):
        raise ValueError('every segment must have the same sampling interval')
    return segments


def _saturation(segments: Sequence[Dataset]):
    """Return per-joint saturation levels (inf: none) and per-segment masks (N, n)."""
    tau_abs = [np.abs(seg.tau) for seg in segments]
    level = np.max(np.vstack(tau_abs), axis=0)
    masks = [a >= level * (1.0 - 1e-6) for a in tau_abs]
    plateau = np.sum([m.sum(axis=0) for m in masks], axis=0) >= 3
    limit = np.where(plateau & (level > 0.0), level, np.inf)
    return limit, [m & plateau for m in masks]


def _rows(seg: Dataset, h, h_prime, features, theta_input, integral, feedforward,
          measured_velocity):
    """Return the filtered regressors of one segment: (N − 2m, n) or (N − 2m, F) arrays."""
    def filt(x):
        x = np.asarray(x, dtype=float)
        return np.stack([np.convolve(x[:, j], h, 'valid') for j in range(x.shape[1])], 1)

    e = seg.theta_d - seg.theta
    if measured_velocity:
        theta_dot = filt(seg.theta_dot)
    else:
        theta_dot = np.stack([np.convolve(seg.theta[:, j], h_prime, 'valid')
                              for j in range(seg.n_joints)], 1)
    rows = {'e': filt(e), 'e_dot': filt(seg.theta_d_dot) - theta_dot, 'tau': filt(seg.tau)}
    if integral:
        z = np.zeros_like(e)
        z[1:] = np.cumsum(0.5 * (e[1:] + e[:-1]), axis=0) * seg.dt
        rows['z'] = filt(z)
        rows['z_end'] = z[-1]
    if feedforward:
        rows['v'] = filt(seg.theta_d_dot)
    if features is not None:
        rows['phi'] = filt(features(seg.theta if theta_input == 'measured' else seg.theta_d))
    return rows


def _solve(columns: List[np.ndarray], target: np.ndarray, keep: np.ndarray):
    a = np.column_stack(columns)[keep]
    y = target[keep]
    scale = np.sqrt(np.mean(a * a, axis=0))
    scale[scale == 0.0] = 1.0
    coef, _, _, _ = np.linalg.lstsq(a / scale, y, rcond=1e-9)
    coef = coef / scale
    residual = y - a @ coef
    rms_y = np.sqrt(np.mean(y * y))
    ratio = np.sqrt(np.mean(residual ** 2)) / rms_y if rms_y > 0 else np.inf
    return coef, ratio


def _filtered_segments(segments, sigma: float):
    """
    Return the Gaussian filter of width ``sigma`` (s) and the segments it can filter.

    ``(sigma, h, h_prime, m, limit, used)``: the width used (a ``sigma`` below the sampling
    interval is the interval), the kernel and its derivative's, their half width m
    (samples), the saturation limit and the (segment, saturated samples) pairs longer than
    the kernel.
    """
    dt = segments[0].dt
    sigma = max(float(sigma), dt)  # data sampled coarser than the filter: the narrowest one
    h, h_prime = gaussian_kernels(dt, sigma)
    m = h.size // 2
    limit, sat = _saturation(segments)
    used = [(seg, s) for seg, s in zip(segments, sat) if seg.n_samples > 2 * m + 2]
    return sigma, h, h_prime, m, limit, used


def _fit_one(segments, features, theta_input, integral, feedforward, measured_velocity,
             sigma, min_samples):
    sigma, h, h_prime, m, limit, used = _filtered_segments(segments, sigma)
    if not used:
        return None
    n = segments[0].n_joints
    parts = [_rows(seg, h, h_prime, features, theta_input, integral, feedforward,
                   measured_velocity) for seg, _ in used]
    # a filtered row touched by a saturated sample does not follow the law
    window = np.ones(2 * m + 1)
    blocked = [np.stack([np.convolve(s[:, j].astype(float), window, 'valid') > 0
                         for j in range(n)], 1) for _, s in used]
    n_rows = [p['e'].shape[0] for p in parts]
    total = int(sum(n_rows))
    if total < max(int(min_samples), 3):
        return None
    # one constant per segment with an integral term (its start value differs), else one
    n_const = len(parts) if integral else 1
    const = np.zeros((total, n_const))
    start = 0
    for k, rows in enumerate(n_rows):
        const[start:start + rows, k if integral else 0] = 1.0
        start += rows

    def stack(key, j=None):
        return np.concatenate([p[key] if j is None else p[key][:, j] for p in parts])

    phi = stack('phi') if features is not None else np.zeros((total, 0))
    kp, kd, ki, bias, kv, ratio = (np.zeros(n) for _ in range(6))
    weights = np.zeros((n, phi.shape[1]))
    for i in range(n):
        keep = ~np.concatenate([b[:, i] for b in blocked])
        if keep.sum() < max(int(min_samples), 3):
            return None
        e, e_dot = stack('e', i), stack('e_dot', i)
        core = np.column_stack([e, e_dot, np.ones(total)])[keep]
        sv = np.linalg.svd(core / np.maximum(np.sqrt(np.mean(core ** 2, 0)), 1e-300),
                           compute_uv=False)
        if sv[-1] < 1e-8 * sv[0]:
            return None          # the error never varied: the gains are not identifiable
        columns = [e, e_dot]
        if integral:
            columns.append(stack('z', i))
        if feedforward:
            columns.append(stack('v', i))
        columns += [phi, const]
        coef, ratio[i] = _solve(columns, stack('tau', i), keep)
        kp[i], kd[i] = coef[0], coef[1]
        k = 2
        if integral:
            ki[i] = coef[k]
            k += 1
        if feedforward:
            kv[i] = coef[k]
            k += 1
        weights[i] = coef[k:k + phi.shape[1]]
        bias[i] = coef[-1]                    # the last segment's constant
    integral_term = ki * parts[-1]['z_end'] if integral else np.zeros(n)
    samples = int(sum(seg.n_samples for seg, _ in used))
    return ControllerLaw(kp=kp, kd=kd, ki=ki, bias=bias, integral_term=integral_term,
                         feedforward=kv, theta_weights=weights, theta_input=theta_input,
                         features=features, fit_ratio=ratio, samples=samples,
                         tau_limit=limit, filter_sigma=float(sigma))


def fit_controller(data: Union[Dataset, Sequence[Dataset]],
                   features: Optional[RBFFeatures] = None, theta_input: str = 'auto',
                   integral: bool = False, feedforward: bool = False,
                   measured_velocity: bool = False,
                   filter_sigma: float = DEFAULT_FILTER_SIGMA,
                   min_samples: int = 50) -> Optional[ControllerLaw]:
    """
    Fit the arm's servo law from measured torque and commands, robust to encoder noise.

    Every regressor and the torque are filtered by one Gaussian low-pass (see the module
    docstring); θ̇ enters as the kernel's derivative applied to θ unless
    ``measured_velocity``.

    Parameters
    ----------
    data : Dataset or sequence of Dataset
        Uniformly sampled, gap-free segments with ``tau`` (the applied torque) and the
        commands ``theta_d``, ``theta_d_dot`` (from ``joint_commands`` or the plan sampled
        at the same times). ``theta_dot`` is used only with ``measured_velocity``.
    features : callable, optional
        A θ-basis ``features(θ) -> (..., F)`` for the terms W φ a servo adds (gravity
        compensation, θ-dependent feed-forward): :class:`TrigFeatures` holds any arm's
        gravity exactly; the arm model's own :class:`RBFFeatures` fold into it exactly.
        None: no θ-dependent term.
    theta_input : {'auto', 'measured', 'desired'}
        Evaluate φ at θ or at θd; 'auto' fits both and keeps the one with the smaller
        residual (a servo compensates gravity on one or the other).
    integral : bool
        Fit an integral gain on ∫e (one constant per segment, for the integral's unknown
        start value).
    feedforward : bool
        Fit a velocity feed-forward gain on θ̇d.
    measured_velocity : bool
        Use the data's θ̇ (filtered like the rest) instead of h′ * θ.
    filter_sigma : float
        Standard deviation of the Gaussian filter (s); one sample where it is less (data
        sampled coarser); about 4 σ at each end of every segment is not used.
    min_samples : int
        Fewer usable filtered rows than this give None.

    Returns
    -------
    ControllerLaw or None
        None with too few samples or a degenerate error signal (the gains are then not
        identifiable).

    """
    segments = _segments(data)
    if theta_input not in THETA_INPUTS + ('auto',):
        raise ValueError(f"theta_input must be 'auto' or one of {THETA_INPUTS}, "
                         f'got {theta_input!r}')
    if features is None:
        inputs = ('measured',)
    else:
        inputs = THETA_INPUTS if theta_input == 'auto' else (theta_input,)
    best = None
    for where in inputs:
        law = _fit_one(segments, features, where, integral, feedforward, measured_velocity,
                       filter_sigma, min_samples)
        if law is not None and (best is None
                                or np.mean(law.fit_ratio) < np.mean(best.fit_ratio)):
            best = law
    return best


@dataclass(frozen=True)
class ClosedLoop:
    """
    A case-1 arm model closed with a fitted :class:`ControllerLaw`, for prediction.

    Attributes
    ----------
    model : RKGNNModel
        A case-2 model: the arm model's genome, the law's gains, its θ-terms on θ folded
        into the gravity output.
    law : ControllerLaw
        The law; its command-only terms shift θd (:meth:`ControllerLaw.shift`).
    offset : ndarray, shape (n,)
        A further constant shift of θd (rad): the constant part of the law's θ-terms
        projected on the model's units (see :func:`closed_loop`).
    fold_error : ndarray, shape (n,)
        RMS of what the model's units could not hold of the law's θ-terms on θ, over the
        samples projected on, relative to the RMS of those terms (0: folded exactly).

    """

    model: RKGNNModel
    law: ControllerLaw
    offset: np.ndarray
    fold_error: np.ndarray

    def simulate(self, x0, t, theta_d, theta_d_dot, integral_term=None,
                 iterations: int = INTEGRAL_ITERATIONS) -> np.ndarray:
        """
        Roll the closed loop out from ``x0`` (2n,) over the uniform times ``t`` (K,).

        Parameters
        ----------
        x0 : array_like, shape (2n,)
            Start state [θ, θ̇].
        t : array_like, shape (K,)
            Uniform times, ``t[0]`` the start.
        theta_d, theta_d_dot : array_like, shape (K, n)
            The commands (the plan) at ``t``.
        integral_term : array_like, shape (n,), optional
            The integral term at the start (default the law's).
        iterations : int
            With an integral gain, the integral is not held: the rollout is repeated with
            I(t) = I(t0) + Ki ∫ (θd − θ̂) from the previous rollout's θ̂ folded into θd
            (Picard iteration of the integral's equation); 0 holds it. Without an integral
            gain there is one rollout.

        Returns
        -------
        ndarray, shape (K, 2n)

        """
        theta_d = np.asarray(theta_d, dtype=float)
        theta_d_dot = np.asarray(theta_d_dot, dtype=float)
        t = np.asarray(t, dtype=float)
        start = self.law.integral_term if integral_term is None else np.asarray(integral_term)
        integral = np.broadcast_to(start, theta_d.shape)
        passes = 1 + (int(iterations) if np.any(self.law.ki != 0.0) else 0)
        n = theta_d.shape[1]
        for _ in range(passes):
            shifted = theta_d + self.law.shift(theta_d, theta_d_dot, integral) + self.offset
            states = self.model.simulate(x0, t, theta_d=shifted, theta_d_dot=theta_d_dot)
            if not np.all(np.isfinite(states)):
                break
            e = theta_d - states[:, :n]
            grown = np.zeros_like(e)
            grown[1:] = np.cumsum(0.5 * (e[1:] + e[:-1]) * np.diff(t)[:, None], axis=0)
            integral = start + self.law.ki * grown
        return states


def _fold_weights(model: RKGNNModel, law: ControllerLaw, theta_samples):
    """Return (W (n, K), constant (n,), relative error (n,)) of W φ_model + c ≈ law's θ-terms."""
    n = model.n_joints
    if model.spec.basis == 'rbf':
        units = RBFFeatures.from_model(model)
        if isinstance(law.features, RBFFeatures) and law.features.same_as(units):
            return law.theta_weights, np.zeros(n), np.zeros(n)
    else:       # any other basis (e.g. 'trig'): the features of the model's own network
        units = model._net.features
    if theta_samples is None:
        raise ValueError("the law's θ-basis is not this model's features: give "
                         'theta_samples to project it on them')
    theta = np.asarray(theta_samples, dtype=float).reshape(-1, n)
    target = law._theta_terms(theta, None)                             # (S, n)
    basis = np.column_stack([units(theta), np.ones(theta.shape[0])])   # (S, K + 1)
    coef, _, _, _ = np.linalg.lstsq(basis, target, rcond=1e-10)
    residual = target - basis @ coef
    spread = np.sqrt(np.mean(np.square(target - target.mean(axis=0)), axis=0))
    error = np.sqrt(np.mean(residual ** 2, axis=0)) / np.maximum(spread, 1e-300)
    return coef[:-1].T, coef[-1], error


def closed_loop(model: RKGNNModel, law: ControllerLaw, theta_samples=None) -> ClosedLoop:
    """
    Return the case-1 ``model`` closed with ``law``, rolled out by the case-2 kernels.

    M θ̈ + V + G + F = Kp e + Kd ė + c + I + W φ(θ) + … is
    M θ̈ + V + (G − W φ(θ)) + F = Kp (θd' − θ) + Kd ė: the law's θ-terms on θ are subtracted
    from the gravity rows of the model's θ-weights, the rest shifts θd.

    When the law's basis is the model's own RBF units the fold is exact. Otherwise (e.g. a
    :class:`TrigFeatures` law) its θ-terms are projected by least squares on the model's
    units and a constant over ``theta_samples`` (the θ of the data the arm model was
    fitted on): the arm model holds the arm's gravity as such a projection along its data,
    so the two projections cancel where the servo compensates that gravity.
    ``ClosedLoop.fold_error`` says how much of the terms the units could not hold.

    Parameters
    ----------
    model : RKGNNModel
        A case-1 ('torque') model.
    law : ControllerLaw
        A law with Kp > 0 on every joint.
    theta_samples : array_like, shape (S, n), optional
        Where to project a foreign basis (needed only then).

    """
    if model.case != 'torque':
        raise ValueError(f"closed_loop needs a case 'torque' model, got {model.case!r}")
    n = model.n_joints
    if law.n_joints != n:
        raise ValueError(f'the law is for {law.n_joints} joints, the model has {n}')
    if not np.all(law.kp > 0.0):
        raise ValueError(f'the law needs Kp > 0 on every joint to fold its terms into θd, '
                         f'got {law.kp.tolist()}')
    genome = model.genome.copy()
    offset, error = np.zeros(n), np.zeros(n)
    if law.theta_input == 'measured' and law.theta_weights.size:
        fold, constant, error = _fold_weights(model, law, theta_samples)
        spec = model.spec
        block = next(b for b in spec.blocks() if b.name == 'theta_weights')
        weights = genome[block.start:block.stop].reshape(block.shape)   # (n_out, K), view
        rows = np.arange(spec.n_outputs)[spec.output_slices()['gravity']]
        out_scale = spec.output_scales(model.scales)
        weights[rows] -= fold / out_scale[rows, None]
        offset = constant / law.kp
    spec = replace(model.spec, case='pd_gains')
    closed = RKGNNModel(spec, model.scales, genome, joint_names=model.joint_names,
                        kp=law.kp, kd=law.kd, dt=model.dt, substeps=model.substeps,
                        info=dict(model.info, closed_loop=law.describe()))
    return ClosedLoop(closed, law, offset, error)

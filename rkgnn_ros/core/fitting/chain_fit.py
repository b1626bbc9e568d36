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
A serial revolute arm without a robot description: its chain and dynamics from joint data.

Case 1 (torque measured). The arm's equation Y(θ, θ̇, θ̈; chain) π = τ is linear in the
inertial and friction parameters π for a given chain, so a chain is scored by the residual
of its best π (variable projection, :class:`~.chain_rows.ChainScore`), and only the chain's
4 n − 4 numbers are searched (:class:`~.chain_search.ChainCoding`):

1. search: random starts, each refined by Levenberg-Marquardt's kind on
   :data:`ChainSettings.search_rows` rows of Gaussian-filtered states
   (:func:`~.chain_rows.state_rows`), until the best cost was reached twice
   (:func:`~.chain_search.multistart`); the best start's axes are turned one at a time
   (the near-symmetry of a light, round body) where that refines lower;
2. refinement on exact rows (parallel filtering on blocks, :func:`~.chain_rows.block_rows`),
   where the lightest bodies show, with a pull towards a compact arm
   (:data:`ChainSettings.length_pull`) where the data leave a length nearly free, and the
   axes turned once more;
3. the chain and physically consistent parameters refined together on the same rows
   (:func:`~.chain_consistent.refine_jointly`): a weakly fixed part of the chain moves to
   where bodies that exist explain the torque;
4. how well the data fix each axis (:func:`~.chain_search.determinacy`);
5. the physically consistent fit of the chosen chain on all the data
   (:func:`~.rigid_fit.fit_torque` on a :class:`~..rigid.chain.ChainStructure`, the joint
   refinement's parameters as its prior), scored on the validation segments.

:func:`fit_chain` returns a :class:`ChainFit`: the chain, the identified
:class:`~.rigid_fit.RigidArm` (inverse and forward dynamics, mass matrix, parameters), the
report (the chain as modified DH numbers and as lines, the determinacy, the search) and
:meth:`ChainFit.urdf`, the learned arm as a URDF with its identified inertials. The chain is
known up to a mirror image of the whole arm (the same dynamics: no data tell them apart).
Data sampled faster than :data:`SEARCH_RATE` are thinned for steps 1-4
(:func:`decimated`); step 5 takes them whole. BLAS runs on one thread during the fit (its
threads only slow these small products).

Case 3 (no torque, a PD servo of unknown gains; ``case='unknown'``). The closed loop's
equation Y π = Kp (θd − θ) + Kd (θ̇d − θ̇) is linear in π and the gains together, and
homogeneous: the gains' mean Kp is made the unit
(:meth:`~.chain_rows.ChainRows.with_unknown_gains`), the gains are unknowns of the variable
projection beside π, and the same steps run on it; by default (``ChainSettings.integral``)
the servo may have an integral term: its gain and each segment's start are unknowns too.
Each joint's equation is weighted by its tracking error for the search, by the servo's
torque the search's chain implies after it. Masses and gains are known up to one common
factor; the joint refinement takes the prior's total mass as the masses' unit (its
consistent start, :data:`CASE_THREE_START_EVALUATIONS`), step 5 is case 3's
:func:`~.rigid_fit.fit_closed_forms` on the learned chain (the servo's form, PD, PID or with
θ-terms, as the held-out data support; the gains in N m/rad of that unit;
:func:`~.rigid_fit.fit_closed`'s PD without the integral), and the report holds the gains
relative to their mean Kp.
"""

import dataclasses
import math
import time
from typing import Callable, NamedTuple, Optional, Sequence

import numpy as np

from .chain_consistent import JOINT_PRIOR_WEIGHT, refine_jointly
from .chain_rows import block_rows, ChainScore, state_rows, torque_weights
from .chain_search import (ChainCoding, determinacy, multistart, refine, SEARCH_PRIOR,
                           turn_axes)
from .rigid_data import choose_sigma
from .rigid_fit import fit_closed, fit_closed_forms, fit_torque, RigidArm, RigidFit
from ..data import Dataset
from ..rigid.chain import Chain, ChainStructure, dh_of_lines, lines
from ..rigid.solve import fit_consistent
from ..rigid.urdf_out import identified_urdf
from ..servo_law import pd_torque

__all__ = ['case_signals', 'ChainFit', 'ChainSettings', 'MAX_JOINTS', 'SEARCH_RATE', 'decimated',
           'fit_chain']

#: Most joints a chain is searched for.
MAX_JOINTS = 7

#: Highest sampling rate (Hz) the search and the refinement take the data at.
SEARCH_RATE = 250.0

#: Most solver evaluations of case 3's consistent start (its bodies begin at the prior's
#: shapes, scaled to the prior's total mass, far from the data's).
CASE_THREE_START_EVALUATIONS = 2000


def decimated(segment: Dataset, rate: float = SEARCH_RATE) -> Dataset:
    """
    Return the segment at about ``rate`` Hz or below: every k-th sample, τ averaged over k.

    θ and θ̇ are taken as sampled (smooth), τ as its mean over the k samples centred on
    each kept one, so its noise is averaged rather than dropped.
    """
    k = int(math.floor(1.0 / (segment.dt * rate)))
    if k <= 1:
        return segment
    box = np.ones(k) / k
    tau = None if segment.tau is None else np.stack(
        [np.convolve(segment.tau[:, j], box, 'same') for j in range(segment.tau.shape[1])],
        1)[::k]
    desired = [None if x is None else x[::k]
               for x in (segment.theta_d, segment.theta_d_dot)]
    return Dataset(segment.t[::k], segment.theta[::k], segment.theta_dot[::k], tau=tau,
                   theta_d=desired[0], theta_d_dot=desired[1],
                   joint_names=segment.joint_names)


@dataclasses.dataclass(frozen=True)
class ChainSettings:
    """
    How :func:`fit_chain` searches (module docstring).

    Attributes
    ----------
    integral : bool
        Case 3: the servo may have an integral term (PID): its gain and each segment's
        start are unknowns beside the PD gains
        (:meth:`~.chain_rows.ChainRows.with_unknown_gains`; a PD servo's Ki comes out near
        0). False: a PD servo.
    search_rows : int
        Filtered states the search scores a chain on.
    refine_blocks, block_length : int
        Blocks of exact rows the refinement uses, and rows per block.
    max_starts : int
        Most random starts of the search.
    agree : int
        Starts that must reach the best cost before the search stops.
    time_budget : float
        Seconds the search may take (the refinement and the final fit come on top).
    seed : int
        Of the starts and the rows drawn.
    sigma : float or None
        The rows' low-pass (s); None: :func:`~.rigid_data.choose_sigma`.
    measured_velocity : bool
        θ̇ as measured (else from θ).
    gravity : float
        Gravity's magnitude (m/s²).
    joint_iterations : int
        Most iterations of the chain and consistent parameters refined together.
    length_pull : float
        The refinement's pull towards a compact arm, λ, in units of the residual per
        equation (a length of :data:`~.chain_search.LENGTH_SCALE` costs that much).
    refine_iterations : int
        Most iterations of each of the refinement's local fits (its axes turned: 40 at
        most).

    """

    integral: bool = True
    search_rows: int = 150
    refine_blocks: int = 120
    block_length: int = 16
    max_starts: int = 40
    agree: int = 2
    time_budget: float = 420.0
    seed: int = 0
    sigma: Optional[float] = None
    measured_velocity: bool = False
    gravity: float = 9.81
    joint_iterations: int = 100
    length_pull: float = 30.0
    refine_iterations: int = 60


class ChainFit(NamedTuple):
    """What :func:`fit_chain` found."""

    chain: Chain
    arm: RigidArm
    fit: RigidFit
    report: dict

    def urdf(self, note: Optional[str] = None) -> str:
        """Return the learned arm as URDF XML, with its identified inertials and friction."""
        return identified_urdf(self.arm.structure, self.arm.parameters,
                               note or 'a chain learned from joint data (no robot description)')


def case_signals(seg: Dataset, case: str = 'torque'):
    """
    Return the arrays a chain's fit of ``case`` takes from ``seg``, or None if one is missing.

    'torque': θ, θ̇ and τ; 'unknown' (the servo's gains unknown) and a servo's torque of known
    gains: θ, θ̇, θd and θ̇d.
    """
    needed = ((seg.theta, seg.theta_dot, seg.tau) if case == 'torque'
              else (seg.theta, seg.theta_dot, seg.theta_d, seg.theta_d_dot))
    return None if any(a is None for a in needed) else needed


def _usable(segments: Sequence[Dataset], case: str = 'torque'):
    out = []
    for seg in segments:
        needed = case_signals(seg, case)
        if needed is not None and all(np.all(np.isfinite(a)) for a in needed):
            out.append(seg)
    return out


def _servo_weights(segments: Sequence[Dataset], kp, kd) -> np.ndarray:
    """Return 1 / RMS of Kp e + Kd ė per joint over the segments (1 where it is 0)."""
    return _inverse_rms(np.concatenate([pd_torque(kp, kd, seg.theta_d - seg.theta,
                                                  seg.theta_d_dot - seg.theta_dot)
                                        for seg in segments]))


def _inverse_rms(tau: np.ndarray) -> np.ndarray:
    """Return 1 / RMS per joint of torques (K, n) (1 where it is 0 or not finite)."""
    rms = np.sqrt(np.mean(tau * tau, axis=0))
    return np.where(np.isfinite(rms) & (rms > 0.0), 1.0 / np.where(rms > 0.0, rms, 1.0), 1.0)


def _chain_report(chain: Chain) -> dict:
    axes, points = lines(chain)
    dh = dh_of_lines(axes, points, chain.gravity)
    g = dh.gravity / np.linalg.norm(dh.gravity)
    return {'modified_dh': {'alpha_deg': np.degrees(dh.alpha).tolist(), 'a_m': dh.a.tolist(),
                            'offset_deg': np.degrees(dh.offset).tolist(),
                            'd_m': dh.d.tolist()},
            'gravity_direction': g.tolist(),
            'axes': (axes @ dh.rotation).tolist(),
            'points_m': ((points - dh.origin) @ dh.rotation).tolist()}


def fit_chain(train: Sequence[Dataset], validation: Sequence[Dataset] = (),
              settings: ChainSettings = ChainSettings(),
              joint_names: Optional[Sequence[str]] = None,
              log: Optional[Callable[[str], None]] = None,
              case: str = 'torque') -> Optional[ChainFit]:
    """
    Return the chain and dynamics of a serial revolute arm from ``train``.

    ``case`` 'torque' (case 1): ``train`` and ``validation`` are segments with θ, θ̇ and τ;
    'unknown' (case 3): with θ, θ̇, θd and θ̇d under a PD servo of unknown gains (the
    chain's rows carry the gains as unknowns, :meth:`~.chain_rows.ChainRows.with_unknown_gains`;
    the masses and gains are known up to one common factor, the mean Kp the unit). Other
    segments are left out. None when the data are too short for the search's rows. ``log``
    takes one line per stage.

    Raises
    ------
    ValueError
        With more than :data:`MAX_JOINTS` joints, or segments of differing joint counts.

    """
    import scipy.linalg  # noqa: F401 - its BLAS must be loaded to be limited
    import scipy.optimize  # noqa: F401
    from threadpoolctl import threadpool_limits
    if case not in ('torque', 'unknown'):
        raise ValueError(f"case must be 'torque' or 'unknown', got {case!r}")
    train, validation = _usable(train, case), _usable(validation, case)
    if not train:
        return None
    n = train[0].theta.shape[1]
    if any(seg.theta.shape[1] != n for seg in list(train) + list(validation)):
        raise ValueError('the segments differ in their number of joints')
    if not 1 <= n <= MAX_JOINTS:
        raise ValueError(f'a chain of 1 to {MAX_JOINTS} joints is searched, got {n}')
    names = joint_names or train[0].joint_names or [f'joint{i + 1}' for i in range(n)]
    with threadpool_limits(limits=1, user_api='blas'):
        return _fit(train, validation, settings, tuple(names), log or (lambda text: None),
                    case)


def _fit(train, validation, settings: ChainSettings, names, log,
         case='torque') -> Optional[ChainFit]:
    began = time.monotonic()
    n = train[0].theta.shape[1]
    rng = np.random.default_rng(settings.seed)
    sigma = choose_sigma(train) if settings.sigma is None else float(settings.sigma)
    servo = case == 'unknown'
    # case 3: each joint's equation weighted first by its tracking error alone (gains 1)
    weights = _servo_weights(train, 1.0, 0.0) if servo else torque_weights(train)
    reduced = [decimated(seg, SEARCH_RATE) for seg in train]
    coarse_rows = state_rows(reduced, settings.search_rows, rng, sigma,
                             settings.measured_velocity, servo)
    fine_rows = block_rows(reduced, settings.refine_blocks, settings.block_length, rng, sigma,
                           settings.measured_velocity, servo)
    if coarse_rows is None or fine_rows is None:
        return None
    if servo:
        coarse_rows = coarse_rows.with_unknown_gains(settings.integral)
        fine_rows = fine_rows.with_unknown_gains(settings.integral)
    coarse = ChainScore(coarse_rows, weights)
    coding = ChainCoding(n, settings.gravity)
    found = multistart(coarse, coding, rng, settings.max_starts, settings.time_budget,
                       settings.agree)
    log(f'search: {found.message}, best cost {found.best.cost:.3e} after '
        f'{len(found.minima)} starts, {found.seconds:.1f} s')
    if servo:     # then by the servo's torque of the gains the best chain implies
        tree = coding.tree(found.best.x)
        if settings.integral:   # the servo's torque is Y π's (its integral's start unknown)
            weights = _inverse_rms(coarse_rows.torques(tree, coarse.parameters(tree))
                                   .reshape(-1, n))
        else:
            weights = _servo_weights(train, *coarse_rows.gains(coarse.extra(tree)))
    fine = ChainScore(fine_rows, weights)
    stage = time.monotonic()
    best = refine(fine, coding, found.best.x, max_iterations=settings.refine_iterations,
                  prior=SEARCH_PRIOR)
    # the pull towards a compact arm: a share of the residual per equation (module docstring)
    prior = settings.length_pull * best.cost / fine.target.size
    best = refine(fine, coding, best.x, max_iterations=settings.refine_iterations,
                  prior=prior)
    best = turn_axes(fine, coding, best, min(40, settings.refine_iterations), prior=prior)
    log(f'refinement: cost {best.cost:.3e}, {time.monotonic() - stage:.1f} s')
    refined_s = time.monotonic() - stage
    stage = time.monotonic()
    structure = ChainStructure(coding.chain(best.x), names)
    unit = 1.0
    if servo:   # the unit: the prior's bodies' torque on these rows (the mean Kp's is arbitrary)
        fitted = fine_rows.torques(structure.tree, fine.parameters(structure.tree))
        prior_torque = fine_rows.torques(structure.tree, structure.prior)
        unit = float(np.linalg.norm(prior_torque) / max(np.linalg.norm(fitted), 1e-300))
        fine_rows = fine_rows.scaled(unit)
        fine = ChainScore(fine_rows, weights)
    w = np.tile(weights, fine_rows.n_rows)
    extra = None if fine_rows.extra is None else fine_rows.extra * w[:, None]
    start = fit_consistent(structure, fine_rows.design(structure.tree) * w[:, None],
                           fine.target, extra, prior_weight=JOINT_PRIOR_WEIGHT,
                           max_evaluations=CASE_THREE_START_EVALUATIONS if servo else 200)
    start_cost = start.rms_residual ** 2 * start.rows / fine.norm ** 2
    joint = refine_jointly(fine_rows, weights, coding, best.x, start.parameters,
                           structure.prior, prior, max_iterations=settings.joint_iterations,
                           extra0=None if extra is None else start.extra)
    log(f'joint refinement: consistent cost {start_cost:.3e} -> {joint.cost:.3e}, '
        f'{time.monotonic() - stage:.1f} s')
    chain = coding.chain(joint.x)
    report = {'case': case,
              'search': {'message': found.message, 'starts': len(found.minima),
                         'agreeing': found.agreeing,
                         'costs': [m.cost for m in found.minima],
                         'evaluations': found.evaluations, 'seconds': found.seconds},
              'refinement': {'cost': best.cost, 'rows': int(fine_rows.n_rows),
                             'seconds': refined_s},
              'joint_refinement': {'cost': joint.cost, 'evaluations': joint.evaluations,
                                   'seconds': time.monotonic() - stage},
              'determinacy': determinacy(fine, coding, joint.x),
              'chain': _chain_report(chain), 'sigma': sigma,
              'symmetry': 'known up to a mirror image of the whole arm (same dynamics)'}
    if servo:
        gains = joint.extra / unit
        kp, kd = fine_rows.gains(gains)
        report['gains'] = {'kp': kp.tolist(), 'kd': kd.tolist(),
                           'ki': fine_rows.integral_gains(gains).tolist(),
                           'unit': 'the mean Kp (masses and gains share one unknown factor)'}
    stage = time.monotonic()
    learned = ChainStructure(chain, names, prior=joint.parameters)
    if servo and settings.integral:     # the servo's form as the held-out data say
        fit = fit_closed_forms(learned, train, validation, sigma=sigma,
                               measured_velocity=settings.measured_velocity)
    elif servo:
        fit = fit_closed(learned, train, validation, sigma=sigma,
                         measured_velocity=settings.measured_velocity)
    else:
        fit = fit_torque(learned, train, validation, sigma=sigma,
                         measured_velocity=settings.measured_velocity)
    if fit is None:
        return None
    report['consistent_fit'] = {'seconds': time.monotonic() - stage,
                                'heldout_errors': fit.errors.tolist(),
                                'evaluations': fit.arm.info.get('evaluations')}
    report['seconds'] = time.monotonic() - began
    log(f'consistent fit: cost {fit.arm.info.get("rms_residual")}, '
        f'{report["seconds"]:.1f} s in all')
    fit.arm.info['chain_report'] = report
    return ChainFit(chain, fit.arm, fit, report)

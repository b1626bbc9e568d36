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
Case 1 online: the arm's servo law, learned from the measured torque, closes the loop.

With the torque measured, a model of the arm alone predicts nothing without the future
torque; the servo decides that torque from the state it will reach. The online policy
(:mod:`.online`) takes three steps between the buffered data and a prediction, all here:

- :func:`fit_law`: the servo's law by :func:`.controller.fit_controller` (PD, an integral
  where the data need one, θ-terms on the trigonometric products that hold any revolute
  arm's gravity, both sides of the regression filtered so encoder noise does not bias it,
  no velocity needed), on segments whose commands are ``joint_commands`` or, on an arm
  without that topic, the plan sampled at the state times. An integral costs every
  prediction several rollouts (:meth:`.controller.ClosedLoop.simulate`), so it is kept
  only where it explains the torque.
- :func:`search_segments`: the data of the closed-loop search. The law is
  τ = Kp e + Kd ė + [c + Ki ∫e + K_v θ̇d + W φ(θd)] + W φ(θ); the bracket depends on the data
  only and folds into a shifted command θd' = θd + [...] / Kp, so a case-2 search with the
  law's gains fits the closed loop exactly. θ-terms on the measured θ (a gravity
  compensation) stay in the data: the model's gravity output then holds G − W φ(θ), with
  no projection.
- :func:`arm_model`: the case-1 model of the arm from the closed-loop search's genome, for
  control: the law's θ-terms on θ projected on the model's units and a constant, added back
  to its gravity output (``info['controller_fold_error']``: what the units could not hold,
  relative). The prediction does not use it: it rolls the searched closed-loop model out.
"""

from dataclasses import replace
import math
from typing import List, NamedTuple, Optional, Sequence, Tuple

import numpy as np

from .controller import closed_loop, ClosedLoop, fit_controller, open_loop_model
from .controller_laws import ControllerLaw, RBFFeatures, TrigFeatures
from .online_records import ClosedLoop as PredictionLoop
from .policy import (INTEGRAL_MIN_RESIDUAL, LAW_AGREEMENT_RTOL, LAW_FORM_GAIN, LAW_GAIN_RTOL,
                     LAW_KI_ZERO, LAW_THETA_SAMPLES, MAX_LAW_FIT_RATIO, MIN_LAW_SAMPLES,
                     MIN_SEGMENT_SAMPLES, NEWEST_SHARE, retry_wait, still_holds,
                     TRIG_FIRST_RETRY_S, TRIG_MAX_TORQUE_ERROR, TRIG_MIN_SAMPLES, TRIG_RETRY_S,
                     YOUNG_DATA_S)
from .rigid_law import fit_gravity_law
from .trig_loop import data_span, fit_trig_loop, trig_torque_error, TrigLoop
from .validation import newest_share, split_validation
from ..data import Dataset
from ..model.model import RKGNNModel

__all__ = ['fit_law', 'judge_law', 'search_segments', 'arm_model', 'prediction_loop', 'LawKeeper',
           'Refit']


def fit_law(segments: Sequence[Dataset], theta_input: str = 'auto',
            min_samples: int = MIN_LAW_SAMPLES, max_fit_ratio: float = MAX_LAW_FIT_RATIO,
            features=None) -> Optional[ControllerLaw]:
    """
    Return the servo law fitted on ``segments`` (with ``tau``, ``theta_d``, ``theta_d_dot``).

    ``theta_input`` is where the θ-terms are evaluated ('auto': both tried, the smaller
    residual kept; a running law passes its own so refits do not flip between two
    equivalent forms). The law is fitted with and without an integral term; the integral is
    kept only when it explains a share of the torque the PD form leaves
    (:func:`_needs_integral`), and its gain is set to zero on joints where it is below
    :data:`~.policy.LAW_KI_ZERO` × Kp.

    A law that explains the torque (residual at most ``max_fit_ratio``) is returned only
    when the data determine it: the same form fitted on the newest share of the data
    (:data:`~.policy.NEWEST_SHARE`) must have the same gains within
    :data:`~.policy.LAW_AGREEMENT_RTOL`: with many θ-terms a few seconds of encoder noise
    fit almost any gains, and the residual alone does not show it. A law that does not
    explain the torque is returned as it is (not usable).
    None: too few samples, an error that never varied, or gains not determined yet.
    ``features``: the θ-basis of the law's terms (default :class:`TrigFeatures`; a robot
    description's :class:`~.rigid_law.GravityFeatures`, whose weights all joints share).
    """
    law, determined = judge_law(segments, theta_input, min_samples, max_fit_ratio, features)
    return law if determined or law is None or not law.usable(max_fit_ratio) else None


def judge_law(segments: Sequence[Dataset], theta_input: str = 'auto',
              min_samples: int = MIN_LAW_SAMPLES, max_fit_ratio: float = MAX_LAW_FIT_RATIO,
              features=None) -> Tuple[Optional[ControllerLaw], bool]:
    """
    Return the law fitted on ``segments`` and whether the data determine it.

    The rules of :func:`fit_law`, which returns the law only when it is determined; here a
    usable law whose gains the newest share does not confirm yet comes back with False
    (the caller may predict with it while the prediction's own trial judges it).
    """
    law = _fit(segments, theta_input, min_samples, None, features)
    if law is None or not law.usable(max_fit_ratio):
        return law, False
    half = _fit(newest_share(segments, NEWEST_SHARE), law.theta_input, min_samples,
                bool(np.any(law.ki != 0.0)), features)
    return law, half is not None and law.close_to(half, LAW_AGREEMENT_RTOL)


def _with_terms(segments, features, theta_input: str, integral: bool, min_samples: int):
    """Return the law with θ-terms on ``features`` (tied weights where they are per joint)."""
    if getattr(features, 'per_joint', False):
        return fit_gravity_law(segments, features, theta_input=theta_input, integral=integral,
                               min_samples=min_samples)
    return fit_controller(segments, features=features, theta_input=theta_input,
                          integral=integral, min_samples=min_samples)


def _fit(segments, theta_input: str, min_samples: int, integral: Optional[bool],
         features=None) -> Optional[ControllerLaw]:
    """Return the law of ``segments`` (``integral`` None: chosen by the data)."""
    segments = [seg for seg in segments if seg.tau is not None and seg.theta_d is not None]
    if not segments:
        return None
    if features is None:
        features = TrigFeatures(segments[0].n_joints)
    plain = None
    if not integral:
        plain = _with_terms(segments, features, theta_input, False, min_samples)
        bare = fit_controller(segments, theta_input=theta_input, min_samples=min_samples)
        if _simpler_holds(bare, plain):
            plain = bare
        if plain is None or integral is False:
            return plain
    law = _with_terms(segments, features, theta_input, True, min_samples)
    if law is None or (plain is not None and not _needs_integral(plain, law)):
        return plain
    negligible = np.abs(law.ki) < LAW_KI_ZERO * np.abs(law.kp)
    if np.any(negligible):
        law = replace(law, ki=np.where(negligible, 0.0, law.ki),
                      integral_term=np.where(negligible, 0.0, law.integral_term),
                      bias=law.bias + np.where(negligible, law.integral_term, 0.0))
    return law


def _simpler_holds(bare: Optional[ControllerLaw], full: Optional[ControllerLaw]) -> bool:
    """
    Return whether the law without θ-terms explains the torque as well as the one with.

    The θ-terms (78 trigonometric products on a 3-joint arm) fit a pure PD servo's torque
    to rounding too, with weights that only the visited configurations constrain: on the
    paper's PD, 20 s about the hanging pose gave weights up to 1.7 N m and a constant of
    1.0 N m, which cancel there and predicted 9× worse 2 s ahead once the arm moved to
    another pose (offline replica of ``bench/online.py``'s switch). So the θ-terms are kept
    only where the law without them leaves more than :data:`INTEGRAL_MIN_RESIDUAL` of the
    torque and they halve what it leaves (a gravity compensation, a θ-dependent feed-forward).
    """
    if bare is None or full is None:
        return bare is not None
    before, after = float(np.mean(bare.fit_ratio)), float(np.mean(full.fit_ratio))
    return not (before > INTEGRAL_MIN_RESIDUAL and after < LAW_FORM_GAIN * before)


def _needs_integral(plain: ControllerLaw, integral: ControllerLaw) -> bool:
    """
    Return whether the integral form explains the torque clearly better than the PD one.

    On short windows ∫e is nearly collinear with the slow θ-terms, and with exact data both
    forms fit to rounding: an integral is kept only when the PD form leaves more than
    :data:`INTEGRAL_MIN_RESIDUAL` of the torque and the integral halves it, with Ki >= 0
    (a servo's integral never destabilises on purpose).
    """
    before, after = float(np.mean(plain.fit_ratio)), float(np.mean(integral.fit_ratio))
    return bool(before > INTEGRAL_MIN_RESIDUAL and after < LAW_FORM_GAIN * before
                and np.all(integral.ki >= 0.0))


def _integral_along(seg: Dataset) -> np.ndarray:
    """Return ∫ (θd − θ) dt from the segment's start at each sample (N, n), trapezoid."""
    e = seg.theta_d - seg.theta
    z = np.zeros_like(e)
    z[1:] = np.cumsum(0.5 * (e[1:] + e[:-1]), axis=0) * seg.dt
    return z


def search_segments(segments: Sequence[Dataset], law: ControllerLaw) -> List[Dataset]:
    """
    Return ``segments`` with θd shifted by the law's data-only terms (module docstring).

    The integral runs from each segment's start with the constant the law fitted for the
    newest segment (older segments' constants are not kept: with one gap-free window, the
    usual case, there is one segment).
    """
    out = []
    for seg in segments:
        integral = law.ki * _integral_along(seg)
        shift = law.shift(seg.theta_d, seg.theta_d_dot, integral)
        out.append(replace(seg, theta_d=seg.theta_d + shift))
    return out


def arm_model(closed: RKGNNModel, law: ControllerLaw, theta_samples=None,
              info=None) -> RKGNNModel:
    """
    Return the case-1 arm model of a closed-loop search's case-2 model ``closed``.

    Its gravity output gets the law's θ-terms on the measured θ back (projected on the
    model's units and its constant term over ``theta_samples`` (S, n), the θ of the data
    searched on); ``info`` replaces the model's info.
    """
    info = dict(closed.info if info is None else info)
    genome = closed.genome.copy()
    error = np.zeros(closed.n_joints)
    if law.theta_input == 'measured' and law.theta_weights.size and theta_samples is not None:
        spec = closed.spec
        theta = np.asarray(theta_samples, dtype=float).reshape(-1, closed.n_joints)
        # the model's own θ-features: its RBF units, or any other basis's (e.g. 'trig')
        units = (RBFFeatures.from_model(closed) if closed.spec.basis == 'rbf'
                 else closed.theta_features)
        target = law._theta_terms(theta, None)                           # (S, n)
        basis = np.column_stack([units(theta), np.ones(theta.shape[0])])
        coef, _, _, _ = np.linalg.lstsq(basis, target, rcond=1e-10)
        residual = target - basis @ coef
        spread = np.sqrt(np.mean(np.square(target - target.mean(axis=0)), axis=0))
        error = np.sqrt(np.mean(residual ** 2, axis=0)) / np.maximum(spread, 1e-300)
        blocks = {b.name: b for b in spec.blocks()}
        rows = np.arange(spec.n_outputs)[spec.output_slices()['gravity']]
        out_scale = spec.output_scales(closed.scales)
        block = blocks['theta_weights']
        weights = genome[block.start:block.stop].reshape(block.shape)   # (n_out, K), view
        weights[rows] += coef[:-1].T / out_scale[rows, None]
        if 'theta_bias' in blocks:
            bias = genome[blocks['theta_bias'].start:blocks['theta_bias'].stop]
            bias[rows] += coef[-1] / out_scale[rows]
    info['controller_fold_error'] = error.tolist()
    model = RKGNNModel(closed.spec, closed.scales, genome, joint_names=closed.joint_names,
                       kp=closed.kp, kd=closed.kd, dt=closed.dt, substeps=closed.substeps,
                       info=info)
    return open_loop_model(model, info=info)


def prediction_loop(closed: RKGNNModel, law: ControllerLaw) -> ClosedLoop:
    """Return the searched closed-loop model and the law as one rollout (no projection)."""
    n = closed.n_joints
    return ClosedLoop(closed, law, np.zeros(n), np.zeros(n))


class Refit(NamedTuple):
    """What a refit did: ``kind`` 'keep', 'moved' (same form, new gains) or 'changed'."""

    kind: str
    law: Optional[ControllerLaw]          # the law to run with
    line: Optional[Tuple[str, str]] = None  # (level, text) to log


class LawKeeper:
    """
    Case 1's law over the refreshes of the data: refitted, kept while its form holds.

    ``law`` is the law in use, ``time`` the stamp (s) its integral term refers to and
    ``theta`` (S, n) the θ it was fitted on (where a foreign basis is projected).
    """

    def __init__(self):
        self.law: Optional[ControllerLaw] = None
        self.time = math.nan
        self.theta: Optional[np.ndarray] = None
        self.trig: Optional[TrigLoop] = None    # the global arm closed with the law
        self._trig_tried = -math.inf             # when it was last fitted (clock s)
        self._trig_failures = 0                  # fits in a row that did not hold
        self.after_change = False                # see :meth:`changed`

    def changed(self) -> None:
        """
        Say that the arm's dynamics changed: the trigonometric arm is dropped.

        If it held before (the basis holds this arm), then until the search publishes a model
        of the arm after the change (:attr:`after_change`, cleared by the caller) the arm is
        fitted again at every call while the data since are young, and an arm fitted since
        stays in use when a refit does not hold: the model it would go back to is the arm
        before the change.
        """
        self.after_change = self.after_change or self.trig is not None
        self.trig = None

    @property
    def trig_tried(self) -> bool:
        """Return True once the trigonometric arm was fitted; it holds when :attr:`trig` is set."""
        return self._trig_tried > -math.inf

    def fit_trig(self, paired: Sequence[Dataset], validation_fraction: float,
                 now: float, prior=None) -> Tuple[bool, Optional[Tuple[str, str]]]:
        """
        Fit the trigonometric arm on ``paired`` and close it with the law in use.

        The newest ``validation_fraction`` is held out; the arm predicts (:meth:`close`)
        while its torque error there is at most :data:`TRIG_MAX_TORQUE_ERROR`, fitted again
        on all of ``paired`` once it held (``torque_error`` stays the held-out one). Until
        :data:`TRIG_MIN_SAMPLES` training samples are buffered it is not tried. Where it did
        not hold, it is fitted again :data:`TRIG_FIRST_RETRY_S` after the try (clock ``now``,
        s); once the data span :data:`~.policy.YOUNG_DATA_S` (young data grow fast, and each
        second more is what makes the fit hold), that wait doubles with each further failure up to
        :data:`TRIG_RETRY_S`: an arm the planar basis does not hold (a spatial one) would
        pay the fit at every refresh for nothing.
        After a change of the dynamics see :meth:`changed`.
        ``prior`` (:class:`~.linear.Samples`, the excitation memory's) joins the training
        samples, so the arm keeps what it learned where the window no longer goes.
        Returns whether it was fitted, and the (level, text) to log when whether it predicts
        changed.
        """
        young = data_span(paired) < YOUNG_DATA_S
        wait = 0.0 if self.after_change and young else retry_wait(
            self._trig_failures, young, TRIG_FIRST_RETRY_S, TRIG_RETRY_S)
        if self.trig is None and now - self._trig_tried < wait:
            return False, None
        train, validation, _ = split_validation(paired, validation_fraction,
                                                MIN_SEGMENT_SAMPLES)
        if self.trig is None and sum(seg.n_samples for seg in train
                                     if seg.tau is not None) < TRIG_MIN_SAMPLES:
            return False, None   # too few to try: tried again at the next refresh
        self._trig_tried = now
        before = self.trig is not None
        loop = (fit_trig_loop(train, validation, self.law, TRIG_MIN_SAMPLES, prior)
                if self.law is not None else None)
        why = 'no law or too few samples'
        if loop is not None and not loop.torque_error <= TRIG_MAX_TORQUE_ERROR:
            why = f'held-out torque error {loop.torque_error:.1%}'
            loop = None
        elif loop is not None:   # it held: the arm is fitted again on the newest data too
            whole = fit_trig_loop(paired, [], self.law, TRIG_MIN_SAMPLES, prior)
            if whole is not None:
                whole.torque_error, loop = loop.torque_error, whole
        if loop is None and before:
            error = trig_torque_error(self.trig, validation)
            if still_holds(error, TRIG_MAX_TORQUE_ERROR) or self.after_change:
                self._trig_failures = 0
                return True, None
            why += f'; the arm in use {error:.1%}'
        self.trig = loop
        self._trig_failures = 0 if loop is not None else self._trig_failures + 1
        if loop is not None and not before:
            return True, ('info', 'predictions roll out the arm fitted on the trigonometric '
                          f'basis (held-out torque error {loop.torque_error:.2%}) closed with '
                          "the learned law; ~/model stays the search's model")
        if loop is None and before:
            return True, ('info', f"predictions go back to the search's model ({why} on "
                          'the trigonometric basis)')
        return True, None

    def refit(self, segments: Sequence[Dataset], origin: float,
              running: Optional[ControllerLaw], after_change: bool = False) -> Refit:
        """
        Fit the law on ``segments`` (``origin``: the stamp of their t = 0) and say what to do.

        ``running`` is the law a running search uses. Too few paired samples change
        nothing ('keep'); a refit of the same form (gains within :data:`LAW_GAIN_RTOL`,
        θ-terms evaluated alike) keeps the running law, its integral moved on to the data's
        end ('keep'); new gains are 'moved'; a law that appears or stops explaining the
        torque is 'changed', with the line that says so. ``after_change`` (the segments are
        the few seconds after a change of the dynamics, which leaves the servo as it was): a
        refit that explains the torque with gains no servo has (Kp <= 0 or Kd < 0) changes
        nothing ('keep').
        """
        where = running.theta_input if running is not None else 'auto'
        fresh = fit_law(segments, where, MIN_LAW_SAMPLES, MAX_LAW_FIT_RATIO) \
            if segments else None
        if fresh is not None and running is not None and not fresh.usable(MAX_LAW_FIT_RATIO):
            fresh = fit_law(segments, 'auto', MIN_LAW_SAMPLES, MAX_LAW_FIT_RATIO)
        if fresh is None:
            return Refit('keep', running)
        if after_change and not fresh.usable(MAX_LAW_FIT_RATIO) and \
                np.all(fresh.fit_ratio <= MAX_LAW_FIT_RATIO):
            # it explains the torque, with gains no servo has (Kp <= 0, Kd < 0): the data
            # (a few seconds after a change) do not determine them yet; the law stays
            return Refit('keep', running)
        new = fresh if fresh.usable(MAX_LAW_FIT_RATIO) else None
        end = origin + float(segments[-1].t[-1])
        if running is not None and new is not None and _same_form(running, new):
            self.law = _advance(running, segments, origin, self.time, end)
            self.time = end
            return Refit('keep', self.law)
        if running is None and new is None and self.law is None:
            return Refit('keep', None)
        line = _law_log_line(new, self.law, fresh)
        if new is not None:
            self.time = end
            theta = np.concatenate([seg.theta for seg in segments])
            self.theta = theta[::max(1, theta.shape[0] // LAW_THETA_SAMPLES)]
        self.law = new
        moved = running is not None and new is not None
        return Refit('moved' if moved else 'changed', new, line)

    def published(self, model: RKGNNModel,
                  case: str) -> Tuple[RKGNNModel, Optional[RKGNNModel]]:
        """
        Return the model to publish for a search's best ``model`` (settings' ``case``).

        A closed-loop search's (case 'torque' with the law: a case-2 model) is the arm's
        (:func:`arm_model`, the law in ``info``), returned with the searched model itself;
        any other is returned as it is, with None.
        """
        law = self.law
        if model.case == 'pd_gains' and case == 'torque' and law is not None:
            return arm_model(model, law, self.theta,
                             info=dict(model.info, controller_law=law.to_dict())), model
        return model, None

    def close(self, model: Optional[RKGNNModel],
              closed: Optional[RKGNNModel] = None) -> Optional[PredictionLoop]:
        """
        Return the case-1 ``model`` closed with the law for prediction (None if it cannot be).

        The trigonometric arm (:meth:`fit_trig`) when it holds the arm (also with ``model``
        None: it predicts before the search has published a model); else ``closed``, the
        closed-loop search's own model (rolled out as it was searched); else the law's
        θ-terms are projected on the model's units over :attr:`theta`.
        """
        law = self.law
        if law is None or not np.all(law.kp > 0.0) or \
                model is not None and law.n_joints != model.n_joints:
            return None
        if self.trig is not None and self.trig.law is law:
            return PredictionLoop(model, self.trig, self.time)
        if model is None:
            return None
        if closed is not None:
            return PredictionLoop(model, prediction_loop(closed, law), self.time)
        return PredictionLoop(model, closed_loop(model, law, theta_samples=self.theta),
                              self.time)


def _same_form(running: ControllerLaw, new: ControllerLaw) -> bool:
    """Return whether a refit ``new`` keeps the running search valid (gains and form)."""
    return new.close_to(running, LAW_GAIN_RTOL) and new.theta_input == running.theta_input


def _advance(law: ControllerLaw, segments, origin: float, since: float,
             until: float) -> ControllerLaw:
    """Return ``law`` with its integral term moved on from stamp ``since`` to ``until`` (s)."""
    if not np.any(law.ki != 0.0) or not math.isfinite(since):
        return law
    for seg in segments:
        t = origin + seg.t
        keep = (t > since) & (t <= until)
        if np.any(keep):
            law = law.advance_integral(seg.theta[keep], seg.theta_d[keep], seg.dt)
    return law


def _law_log_line(new: Optional[ControllerLaw], old: Optional[ControllerLaw],
                  fresh: ControllerLaw) -> Optional[Tuple[str, str]]:
    """Return the (level, text) saying that the law in use changed (None: it did not)."""
    if new is not None and not new.close_to(old, LAW_AGREEMENT_RTOL):
        return ('info',
                f'controller law learned from effort and the commands ({new.describe()}): '
                'the search and the predictions run in closed loop along the plan with Kp '
                f'{np.round(new.kp, 3).tolist()}, Kd {np.round(new.kd, 3).tolist()}, Ki '
                f'{np.round(new.ki, 3).tolist()} (residual '
                f'{np.round(100 * new.fit_ratio, 2).tolist()} % of the torque)')
    if new is None and old is not None:
        return ('warning',
                'the commands no longer explain the measured torque as a servo law '
                f'(residual {np.round(100 * fresh.fit_ratio, 1).tolist()} %): the search runs '
                'on the measured torque and no model prediction is possible (a baseline is '
                'published)')
    return None

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
When a learned feed-forward may reach an arm: the gate between a model and an effort.

A feed-forward pushes the arm with the drive's full authority wherever the model says; a
wrong model pushes it off its plan and the servo has to fight it. :class:`FeedforwardGate`
lets efforts out only while every condition below holds, and when one fails it switches
off at once and keeps the reason (what ``/diagnostics`` says). After any switch-off only a
new passing :meth:`FeedforwardGate.assess` switches it on again.

1. **The torque scale is identifiable.** Case 1 measures torque, case 2 computes it from
   the known PD law: the model is in N m. In case 3 M, V, G, F and the controller can be
   scaled together without changing any motion, so the model's torque unit is arbitrary;
   its feed-forward is refused unless a torque scale fixed by something measured is given
   (:func:`~rkgnn_ros.core.fitting.torque_check.torque_scale_from_effort` fits it to a
   measured effort; a single known gain fixes it as known Kp / the model's implied Kp).
2. **The model explains held-out torque.** On the newest validation samples (data the fit
   did not use) the model's inverse dynamics at the measured state, M(θ) θ̈ + V + G + F,
   is compared with the torque: measured (case 1, and case 3 when the samples carry it),
   the known PD law (case 2), or the identified controller's torque times the scale (case
   3 otherwise), as :mod:`rkgnn_ros.core.fitting.torque_check` computes it. The error is
   per joint, RMSE / std of that joint's torque over the samples (the std floored at 1 %
   of the largest joint's, so a joint that barely moves cannot fail alone on rounding),
   and the worst joint must be at most ``max_error``: every joint's feed-forward is
   applied, so one bad joint is enough to refuse.
3. **The model is finite and has not diverged.** A non-finite torque on the validation
   samples or on the plan, or a rollout the caller reports as diverged
   (:meth:`FeedforwardGate.model_diverged`, or a non-finite ``rollout_nrmse``), switches
   the feed-forward off.
4. **The data is fresh.** No joint data for more than ``stale_after`` seconds (or the
   clock running backwards) switches it off.

Every effort that leaves :meth:`FeedforwardGate.release` is finite and within
±``max_effort`` per joint: the plan is clipped joint by joint, and a plan with any
non-finite entry is refused whole (and switches the gate off). The clock is injected (a
callable returning seconds, the node's clock), so the node only calls these methods and
tests drive them with a fake clock.
"""

from dataclasses import dataclass
import math
from typing import Callable, NamedTuple, Optional, Sequence, Tuple

import numpy as np

from ..data import Dataset
from ..fitting.torque_check import model_case, paired_torques, torque_error

#: Fewest validation samples (after trimming the segment ends) a verdict is based on.
DEFAULT_MIN_SAMPLES = 50


def _positive(name: str, value) -> float:
    value = float(value)
    if not (math.isfinite(value) and value > 0.0):
        raise ValueError(f'{name} must be finite and > 0, got {value}')
    return value


@dataclass(frozen=True)
class GateSettings:
    """
    Thresholds of the gate.

    Attributes
    ----------
    max_error : float
        Largest held-out torque error allowed, RMSE / std per joint (worst joint), > 0.
    max_effort : ndarray, shape (n,)
        Clip level per joint (N m), finite and > 0 (a scalar is broadcast by
        :meth:`for_joints`).
    stale_after : float
        Seconds without joint data after which the feed-forward stops, > 0.
    min_samples : int
        Fewest validation samples a verdict is based on, >= 1.

    """

    max_error: float
    max_effort: np.ndarray
    stale_after: float
    min_samples: int = DEFAULT_MIN_SAMPLES

    def __post_init__(self):
        object.__setattr__(self, 'max_error', _positive('max_error', self.max_error))
        object.__setattr__(self, 'stale_after', _positive('stale_after', self.stale_after))
        effort = np.asarray(self.max_effort, dtype=float)
        if effort.ndim != 1 or effort.size < 1:
            raise ValueError(f'max_effort must have one entry per joint, got shape '
                             f'{effort.shape}')
        if not np.all(np.isfinite(effort)) or np.any(effort <= 0.0):
            raise ValueError(f'max_effort must be finite and > 0, got {effort.tolist()}')
        object.__setattr__(self, 'max_effort', effort.copy())
        if int(self.min_samples) != self.min_samples or self.min_samples < 1:
            raise ValueError(f'min_samples must be an integer >= 1, got {self.min_samples}')
        object.__setattr__(self, 'min_samples', int(self.min_samples))

    @classmethod
    def for_joints(cls, n_joints: int, max_error: float, max_effort, stale_after: float,
                   min_samples: int = DEFAULT_MIN_SAMPLES) -> 'GateSettings':
        """Return settings with ``max_effort`` a scalar or (n,), broadcast to n joints."""
        effort = np.asarray(max_effort, dtype=float)
        if effort.ndim == 0:
            effort = np.full(int(n_joints), float(effort))
        if effort.shape != (int(n_joints),):
            raise ValueError(f'max_effort must be a scalar or have {n_joints} entries, got '
                             f'shape {effort.shape}')
        return cls(max_error, effort, stale_after, min_samples)

    @property
    def n_joints(self) -> int:
        """Count of joints, n."""
        return self.max_effort.size


class Assessment(NamedTuple):
    """
    A verdict on a model.

    Attributes
    ----------
    passed : bool
        Whether the model's feed-forward may be used.
    reason : str
        Why not (or, when it passed, the error it passed with).
    error : ndarray, shape (n,) or None
        Held-out torque error per joint, RMSE / std (None when not measured).
    samples : int
        Validation samples the error is based on.

    """

    passed: bool
    reason: str
    error: Optional[np.ndarray] = None
    samples: int = 0


class Release(NamedTuple):
    """
    What :meth:`FeedforwardGate.release` lets out.

    Attributes
    ----------
    effort : ndarray, shape (N, n) or None
        The clipped, finite efforts; None when nothing may be sent.
    reason : str
        Why nothing is sent, or '' when the effort is released.
    clipped : int
        Entries that were clipped to ±max_effort.

    """

    effort: Optional[np.ndarray]
    reason: str
    clipped: int = 0


def torque_scale_problem(case: str, torque_scale: Optional[float]) -> Optional[str]:
    """
    Return why a model of ``case`` has no usable torque scale, or None if it has.

    Parameters
    ----------
    case : {'torque', 'pd_gains', 'unknown'}
        The model's identification case.
    torque_scale : float, optional
        N m per model unit, fixed by a measurement (case 3 only; None: not fixed).

    """
    if case in ('torque', 'pd_gains'):
        if torque_scale is not None and torque_scale != 1.0:
            return (f'case {case!r} is identified in N m; a torque scale '
                    f'({torque_scale}) would distort it')
        return None
    if case != 'unknown':
        return f'unknown identification case {case!r}'
    if torque_scale is None:
        return ('case 3: the torque scale is not identifiable (M, V, G, F and the controller '
                'scale together without changing the motion); fix it from a measurement '
                'first (measured effort, or one known gain)')
    if not (math.isfinite(torque_scale) and torque_scale > 0.0):
        return f'case 3: the torque scale must be finite and > 0, got {torque_scale}'
    return None


def model_parameters(model) -> np.ndarray:
    """Return a model's parameters (``genome`` or ``coef_``) as a flat array (empty: none)."""
    for name in ('genome', 'coef_'):
        value = getattr(model, name, None)
        if value is not None:
            return np.asarray(value, dtype=float).ravel()
    return np.empty(0)


class FeedforwardGate:
    """
    Whether the feed-forward is on, why not, and the only way efforts leave.

    Parameters
    ----------
    settings : GateSettings
        Thresholds.
    clock : callable
        ``clock() -> float``, the current time (s) on the clock joint data is stamped with.

    """

    def __init__(self, settings: GateSettings, clock: Callable[[], float]):
        self.settings = settings
        self._clock = clock
        self._on = False
        self._reason = 'no model assessed yet'
        self._last_data: Optional[float] = None
        self.assessment: Optional[Assessment] = None
        self.torque_scale = 1.0

    # ----- inputs
    def data_received(self, stamp: Optional[float] = None) -> None:
        """Note joint data stamped ``stamp`` (s; default now)."""
        stamp = self._clock() if stamp is None else float(stamp)
        if math.isfinite(stamp) and (self._last_data is None or stamp > self._last_data):
            self._last_data = stamp

    def model_diverged(self, reason: str = 'the model diverged') -> None:
        """Switch the feed-forward off at once: the model's rollout diverged."""
        self._switch_off(reason)

    def switch_off(self, reason: str) -> None:
        """Switch the feed-forward off at once for a reason of the caller's (e.g. disabled)."""
        self._switch_off(reason)

    def assess(self, model, validation: Sequence[Dataset], torque_scale: Optional[float] = None,
               rollout_nrmse: Optional[float] = None) -> Assessment:
        """
        Judge ``model`` on held-out data and switch the feed-forward on or off accordingly.

        Parameters
        ----------
        model : RKGNNModel
            The model whose feed-forward would be sent.
        validation : sequence of Dataset
            The newest held-out segments.
        torque_scale : float, optional
            Case 3: N m per model unit, fixed by a measurement. Cases 1 and 2: None.
        rollout_nrmse : float, optional
            The caller's validation rollout error; non-finite means the model diverged.

        Returns
        -------
        Assessment

        """
        verdict = self._verdict(model, validation, torque_scale, rollout_nrmse)
        self.assessment = verdict
        if not verdict.passed:
            self._switch_off(verdict.reason)
            return verdict
        self.torque_scale = 1.0 if torque_scale is None else float(torque_scale)
        stale = self._stale_reason()
        if stale is not None:
            self._switch_off(stale)
        else:
            self._on = True
            self._reason = ''
        return verdict

    # ----- outputs
    def status(self) -> Tuple[bool, str]:
        """Return (on, reason): the reason is '' while on."""
        if self._on:
            stale = self._stale_reason()
            if stale is not None:
                self._switch_off(stale)
        return self._on, self._reason

    @property
    def on(self) -> bool:
        """Return whether the feed-forward may be sent now."""
        return self.status()[0]

    def release(self, times, effort) -> Release:
        """
        Return the efforts that may be sent for a plan, clipped, or None and why not.

        Parameters
        ----------
        times : array_like, shape (N,)
            The plan's point times (s, on the gate's clock).
        effort : array_like, shape (N, n)
            The planned feed-forward (e.g. :attr:`FeedforwardPlan.effort`).

        """
        on, reason = self.status()
        if not on:
            return Release(None, reason)
        n = self.settings.n_joints
        try:
            effort = np.asarray(effort, dtype=float)
            times = np.asarray(times, dtype=float)
        except (TypeError, ValueError) as exc:
            return Release(None, f'the plan is not numeric ({exc})')
        if effort.ndim != 2 or effort.shape[1] != n or times.shape != (effort.shape[0],):
            return Release(None, f'the plan has times {times.shape} and efforts '
                                 f'{effort.shape}; expected (N,) and (N, {n})')
        if effort.shape[0] == 0:
            return Release(None, 'the plan has no points')
        if not np.all(np.isfinite(effort)):
            self._switch_off('the model gave a non-finite torque on the plan')
            return Release(None, self._reason)
        if not np.all(np.isfinite(times)) or times[-1] < self._clock():
            return Release(None, 'the plan has ended (its last point is in the past)')
        limit = self.settings.max_effort
        clipped = int(np.count_nonzero(np.abs(effort) > limit))
        return Release(np.clip(effort, -limit, limit), '', clipped)

    # ----- internals
    def _switch_off(self, reason: str) -> None:
        self._on = False
        self._reason = reason

    def _stale_reason(self) -> Optional[str]:
        now = self._clock()
        if self._last_data is None:
            return 'no joint data yet'
        age = now - self._last_data
        if not math.isfinite(age):
            return 'the clock is not finite'
        if age < -self.settings.stale_after:
            return f'the clock jumped back by {-age:.3g} s'
        if age > self.settings.stale_after:
            return (f'stale: no joint data for {age:.3g} s (limit '
                    f'{self.settings.stale_after:.3g} s)')
        return None

    def _verdict(self, model, validation, torque_scale, rollout_nrmse) -> Assessment:
        if getattr(model, 'n_joints', None) != self.settings.n_joints:
            return Assessment(False, f'the model has {getattr(model, "n_joints", None)} '
                                     f'joints, the gate {self.settings.n_joints}')
        problem = torque_scale_problem(model_case(model)[0], torque_scale)
        if problem is not None:
            return Assessment(False, problem)
        if not np.all(np.isfinite(model_parameters(model))):
            return Assessment(False, 'the model has non-finite parameters')
        if rollout_nrmse is not None and not math.isfinite(rollout_nrmse):
            return Assessment(False, 'the model diverges on the validation samples')
        scale = 1.0 if torque_scale is None else float(torque_scale)
        try:
            predicted, reference = paired_torques(model, validation, scale)
        except ValueError as exc:
            return Assessment(False, str(exc))
        samples = predicted.shape[0]
        if samples < self.settings.min_samples:
            return Assessment(False, f'{samples} validation samples; at least '
                                     f'{self.settings.min_samples} are needed', None, samples)
        if not np.all(np.isfinite(predicted)):
            return Assessment(False, 'the model gives non-finite torque on the validation '
                                     'samples', None, samples)
        error = torque_error(predicted, reference)
        worst = int(np.argmax(error))
        if error[worst] > self.settings.max_error:
            return Assessment(False, f'held-out torque error {error[worst]:.3g} (RMSE / std) '
                                     f'on joint {worst} exceeds max_error '
                                     f'{self.settings.max_error:.3g}', error, samples)
        return Assessment(True, f'held-out torque error at most {error[worst]:.3g} '
                                f'(RMSE / std, joint {worst})', error, samples)

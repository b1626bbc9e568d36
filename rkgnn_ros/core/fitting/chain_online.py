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
The chain learned online: an arm without a robot description gets its kinematics from data.

:class:`ChainLearner` gathers the buffered data of case 'torque' (θ, θ̇ and τ), of case
'pd_gains' with the servo's torque τ = Kp (θd − θ) + Kd (θ̇d − θ̇) of the known gains
(:func:`servo_torque`: the rigid policy then fits the closed loop on the chain), or of case
'unknown' with θd and θ̇d (the gains are learned with the chain, up to the common factor
of case 3: :func:`~.chain_fit.fit_chain`), beyond the
buffer's window, the newest :data:`MAX_DATA_S` seconds kept. Once :data:`CHAIN_DATA_S`
seconds are gathered on a spatial arm (:data:`MIN_JOINTS` joints or more) it runs
:func:`~.chain_fit.fit_chain` on them (:data:`ONLINE_SETTINGS`, the newest
:data:`VALIDATION_FRACTION` held out) in a thread of its own at the lowest CPU priority:
:meth:`ChainLearner.poll` starts the fit and looks whether it ended, it never waits for it.

A learned chain is accepted when its held-out torque error (RMSE / std of the worst joint,
:func:`~.rigid_fit.fit_torque`'s figure) is at most :data:`MAX_ERROR`: its
:class:`~..rigid.chain.ChainStructure` (the fit's parameters as the prior, the learned
chain's report in ``report``) is then what :class:`~.online.OnlineIdentification` hands the
rigid-body policy as it would a robot description's, so its models are fitted, closed with
the servo law and judged by the self-check as any other. A chain refused is tried again once
:data:`RETRY_S` more seconds are gathered, at most :data:`MAX_ATTEMPTS` fits; a fit still
running :data:`MAX_FIT_S` wall seconds after its start is abandoned at its next stage (the
search, the refinement, the joint refinement and the final fit each end a stage).

An accepted chain is judged again at every refit of its rigid body
(:meth:`ChainLearner.judge_in_use`): after :data:`REJUDGE_REFITS` refits in a row whose
held-out torque error is above :data:`MAX_ERROR` (the bar it was accepted under; new motion
the first data did not show can expose a chain they did not determine) it is dropped, and
learned again from data gathered afresh.
"""

from dataclasses import replace
import math
import os
import threading
import time
import traceback
from typing import Callable, List, Optional, Sequence, Tuple

import numpy as np

from .chain_fit import case_signals, ChainSettings, fit_chain, MAX_JOINTS
from .rigid_change import since
from .validation import MIN_SEGMENT_SAMPLES, split_validation
from ..data import Dataset
from ..rigid.chain import ChainStructure
from ..servo_law import pd_torque

__all__ = ['ChainSteps', 'CHAIN_DATA_S', 'chain_case', 'ChainLearner', 'judged', 'learn_chain',
           'LEARNED_CASES', 'MAX_ATTEMPTS',
           'MAX_DATA_S', 'MAX_ERROR', 'MAX_FIT_S', 'MIN_JOINTS', 'ONLINE_SETTINGS',
           'REJUDGE_REFITS', 'RETRY_S', 'VALIDATION_FRACTION']

#: Fewest joints whose chain is learned (fewer: the planar bases serve).
MIN_JOINTS = 3
#: Seconds of gathered data (gaps left out) before the first fit.
CHAIN_DATA_S = 25.0
#: Newest seconds of data kept for a fit.
MAX_DATA_S = 60.0
#: More seconds gathered before a refused chain is learned again.
RETRY_S = 30.0
#: Most fits in all (each refused).
MAX_ATTEMPTS = 3
#: Newest share of the gathered data held out to judge the chain.
VALIDATION_FRACTION = 0.2
#: A chain is accepted while its held-out torque error (worst joint, RMSE / std) is at most.
MAX_ERROR = 0.1
#: Refits in a row of an accepted chain's rigid body with a held-out torque error (worst joint)
#: above :data:`MAX_ERROR` after which the chain is dropped and learned again.
REJUDGE_REFITS = 10
#: Wall seconds after which a running fit is abandoned (at its next stage).
MAX_FIT_S = 300.0
#: Lowest CPU priority: the fit's thread takes the cores the node's callbacks leave.
FIT_NICE = 19
#: :func:`~.chain_fit.fit_chain`'s settings online: fewer starts, rows and iterations.
ONLINE_SETTINGS = ChainSettings(search_rows=100, refine_blocks=40, max_starts=12,
                                time_budget=60.0, joint_iterations=20, refine_iterations=20)


#: The cases whose data teach a chain (τ measured, or computed from the known gains, or the
#: servo's errors with the gains unknown).
LEARNED_CASES = ('torque', 'pd_gains', 'unknown')


def chain_case(case: str) -> str:
    """Return :func:`~.chain_fit.fit_chain`'s case of an online case ('unknown': case 3)."""
    return 'unknown' if case == 'unknown' else 'torque'


def servo_torque(segments: Sequence[Dataset], kp, kd) -> List[Dataset]:
    """
    Return ``segments`` with τ = Kp (θd − θ) + Kd (θ̇d − θ̇) (N m) of the known gains.

    Segments without θd are left out; none at all when the gains do not give one value
    per joint.
    """
    kp, kd = np.asarray(kp, dtype=float), np.asarray(kd, dtype=float)
    out = []
    for seg in segments:
        if seg.theta_d is None or kp.shape != (seg.n_joints,) or kd.shape != (seg.n_joints,):
            continue
        tau = pd_torque(kp, kd, seg.theta_d - seg.theta, seg.theta_d_dot - seg.theta_dot)
        out.append(Dataset(seg.t, seg.theta, seg.theta_dot, tau=tau, theta_d=seg.theta_d,
                           theta_d_dot=seg.theta_d_dot, joint_names=seg.joint_names))
    return out


class Abandoned(Exception):
    """A running fit was abandoned (a reset, or :data:`MAX_FIT_S` passed)."""


class _Job:
    """One fit: its data, its stage lines, its result."""

    def __init__(self, train, validation, names, seconds: float, started: float,
                 case: str = 'torque'):
        self.train, self.validation, self.names = train, validation, names
        self.case = case                # fit_chain's
        self.seconds = seconds          # of data
        self.started = started          # wall clock (time.monotonic)
        self.cancelled = False
        self.done = threading.Event()
        self.found = None
        self.error: Optional[str] = None
        self.stages: List[str] = []
        self.wall = math.nan

    def stage(self, text: str) -> None:
        """Record a stage's line; raise :class:`Abandoned` if the fit is to end."""
        self.stages.append(text)
        if self.cancelled or time.monotonic() - self.started > MAX_FIT_S:
            raise Abandoned(text)


def _lower_priority() -> None:
    """Give the calling thread the lowest CPU priority (Linux: nice is per thread)."""
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), FIT_NICE)
    except (AttributeError, OSError):  # not Linux, or not permitted: equal priority
        pass


def _thread(target: Callable[[], None]) -> None:
    threading.Thread(target=target, name='rkgnn_chain_learner', daemon=True).start()


def _stacked(last, part):
    return None if last is None or part is None else np.vstack([last, part])


def _joined(last: Dataset, part: Dataset) -> Optional[Dataset]:
    """Return ``part`` appended to ``last`` when it continues it on its grid, else None."""
    dt = last.dt
    if (part.n_joints != last.n_joints or abs(part.dt - dt) > 1e-6 * dt
            or abs(part.t[0] - last.t[-1] - dt) > 0.25 * dt):
        return None
    n = last.n_samples + part.n_samples
    return Dataset(last.t[0] + dt * np.arange(n), np.vstack([last.theta, part.theta]),
                   np.vstack([last.theta_dot, part.theta_dot]),
                   tau=_stacked(last.tau, part.tau),
                   theta_d=_stacked(last.theta_d, part.theta_d),
                   theta_d_dot=_stacked(last.theta_d_dot, part.theta_d_dot),
                   joint_names=last.joint_names)


class ChainLearner:
    """
    Learns the chain of an arm without a description in the background (module docstring).

    Parameters
    ----------
    settings : ChainSettings
        Of each fit.
    spawn : callable
        Runs its argument (a callable without arguments) in the background; default a
        daemon thread. Tests pass one that starts a thread and joins it, to fit at once: the
        fit lowers the priority of the thread it runs in, for good (an unprivileged
        process cannot raise it again).
    clock : callable
        Wall clock of the fit's deadline (s).
    min_data_s, max_error : float
        :data:`CHAIN_DATA_S` and :data:`MAX_ERROR` (tests lower the first).
    enabled : bool
        False: gathers nothing, learns nothing (an offline run learns its chain first,
        :func:`learn_chain`).

    """

    def __init__(self, settings: ChainSettings = ONLINE_SETTINGS,
                 spawn: Callable[[Callable[[], None]], None] = _thread,
                 min_data_s: float = CHAIN_DATA_S, max_error: float = MAX_ERROR,
                 enabled: bool = True):
        self.settings = settings
        self.enabled = bool(enabled)
        self._spawn = spawn
        self.min_data_s = float(min_data_s)
        self.max_error = float(max_error)
        self._joints: Optional[Tuple[str, ...]] = None
        self._job: Optional[_Job] = None
        self._case = 'torque'       # fit_chain's case of the data gathered
        self.reset()

    def reset(self) -> None:
        """Forget the data and the chain; abandon a running fit (its result is dropped)."""
        if getattr(self, '_job', None) is not None:
            self._job.cancelled = True
        self._job = None
        self._segments: List[Dataset] = []
        self._origin: Optional[float] = None   # stamp time of the gathered data's t = 0
        self._end = -math.inf                  # stamp time of the newest gathered sample
        self._epoch = None
        self._attempts = 0
        self._total_s = 0.0                    # seconds ever gathered (the trim aside)
        self._next_s = self.min_data_s         # of _total_s, for the next fit
        self.structure: Optional[ChainStructure] = None
        self.error = math.nan                  # the accepted chain's held-out torque error
        self._judged = None                    # the newest rigid-body fit judged
        self._failing = 0                      # its refits in a row above the bar

    def close(self) -> None:
        """Abandon a running fit (the node shuts down)."""
        if self._job is not None:
            self._job.cancelled = True

    @property
    def gathered_s(self) -> float:
        """Return the seconds of data gathered (gaps left out)."""
        return float(sum(seg.duration for seg in self._segments))

    @property
    def running(self) -> bool:
        """Return whether a fit runs in the background."""
        return self._job is not None

    def wants_data(self, joints) -> bool:
        """Return whether :meth:`feed` would keep data of ``joints`` now."""
        if not self.enabled or joints is None or not MIN_JOINTS <= len(joints) <= MAX_JOINTS:
            return False
        if tuple(joints) != self._joints:
            return True
        return self.structure is None and self._attempts < MAX_ATTEMPTS

    def feed(self, joints, segments: Sequence[Dataset], origin: float, epoch=None,
             case: str = 'torque') -> None:
        """
        Gather the new part of ``segments`` (``origin``: the stamp time of their t = 0).

        Only samples after the newest gathered one are taken, with τ (``case`` 'torque') or
        θd and θ̇d (``case`` 'unknown': the servo's gains unknown), finite; a part that
        continues the newest segment on its grid extends it. Another joint list or case
        starts afresh; another ``epoch`` (the buffer was cleared) starts a new segment.
        """
        if joints is None:
            return
        joints = tuple(joints)
        if joints != self._joints or case != self._case:
            self.reset()
            self._joints, self._case = joints, case
        if not self.wants_data(joints):
            return
        if epoch != self._epoch:
            self._epoch, self._end = epoch, -math.inf
        fresh = [seg for seg in segments
                 if seg.n_joints == len(joints) and case_signals(seg, case) is not None]
        if not fresh:
            return
        if self._origin is None:
            self._origin = float(origin)
        step = min(seg.dt for seg in fresh)
        for part in since(fresh, origin, self._end + 0.5 * step):
            end = float(origin + part.t[-1])
            part = Dataset(part.t + (origin - self._origin), part.theta, part.theta_dot,
                           tau=part.tau if case == 'torque' else None,
                           theta_d=None if case == 'torque' else part.theta_d,
                           theta_d_dot=None if case == 'torque' else part.theta_d_dot,
                           joint_names=joints)
            joined = None
            if self._segments and math.isfinite(self._end):
                joined = _joined(self._segments[-1], part)
            if joined is not None:
                self._segments[-1] = joined
            else:
                self._segments.append(part)
            self._end = end
            self._total_s += part.duration
        self._trim()

    def judge_in_use(self, fit) -> List[Tuple[str, str]]:
        """
        Judge a refit of the accepted chain's rigid body (a :class:`~.rigid_fit.RigidFit`).

        Returns log lines; the chain is dropped (:attr:`structure` None, the data gathered
        afresh, the attempts counted anew) after :data:`REJUDGE_REFITS` refits in a row
        with a held-out torque error above the learner's ``max_error``. The same fit seen
        twice counts once; a fit without held-out samples does not count.
        """
        if self.structure is None or fit is None or fit is self._judged:
            return []
        self._judged = fit
        error = fit.error
        if not math.isfinite(error):
            return []
        self._failing = self._failing + 1 if error > self.max_error else 0
        if self._failing < REJUDGE_REFITS:
            return []
        joints = self._joints
        self.reset()
        self._joints = joints
        return [('warning', f'the learned chain no longer explains the torque: held-out error '
                            f'above {self.max_error:.0%} in {REJUDGE_REFITS} refits in a row '
                            f'(newest {error:.2%}); it is learned again from new data')]

    def changed(self, stamp: float) -> None:
        """
        Say that the arm's dynamics changed at ``stamp`` (s): the data before it go.

        A chain not learned yet is fitted on data of one arm only: a fit running on data
        from before the change is abandoned (it does not count as an attempt), and the
        next starts once :data:`CHAIN_DATA_S` after it are gathered. A chain already
        learned stays (a payload changes the dynamics, not the kinematics).
        """
        if self.structure is not None or self._origin is None:
            return
        if self._job is not None:
            self._job.cancelled = True
            self._job = None
            self._attempts = max(0, self._attempts - 1)
        self._segments = since(self._segments, self._origin, stamp)
        self._next_s = self._total_s + max(0.0, self.min_data_s - self.gathered_s)

    def _trim(self) -> None:
        """Keep the newest :data:`MAX_DATA_S` seconds."""
        excess = self.gathered_s - MAX_DATA_S
        while excess > 0.0 and self._segments:
            first = self._segments[0]
            if first.duration <= excess + first.dt:
                self._segments.pop(0)
                excess -= first.duration
                continue
            k = int(np.searchsorted(first.t, first.t[0] + excess))
            if first.n_samples - k < 2:
                self._segments.pop(0)
            else:
                self._segments[0] = first.slice(k, first.n_samples)
            break

    def poll(self, case: str) -> List[Tuple[str, str]]:
        """
        Judge a fit that ended; start one when due; return log lines (level, text).

        A fit is due in a case of :data:`LEARNED_CASES` whose data were gathered
        (:func:`chain_case`) once they reach the next goal (:data:`CHAIN_DATA_S`, then
        :data:`RETRY_S` more after each refusal).
        """
        lines: List[Tuple[str, str]] = []
        job = self._job
        if job is not None and job.done.is_set():
            self._job = None
            lines.extend(self._judge(job))
        if (self._job is None and case in LEARNED_CASES and chain_case(case) == self._case
                and self._joints is not None
                and self.wants_data(self._joints) and self._total_s >= self._next_s
                and self.gathered_s >= min(self.min_data_s, MAX_DATA_S)):
            lines.append(self._start())
        return lines

    def _start(self) -> Tuple[str, str]:
        segments = [seg for seg in self._segments if seg.n_samples >= MIN_SEGMENT_SAMPLES]
        train, validation, seconds = split_validation(segments, VALIDATION_FRACTION,
                                                      MIN_SEGMENT_SAMPLES)
        self._attempts += 1
        self._next_s = self._total_s + RETRY_S
        job = _Job(train, validation, self._joints, seconds, time.monotonic(), self._case)
        self._job = job
        settings = replace(self.settings, seed=self.settings.seed + self._attempts - 1)
        self._spawn(lambda: self._run(job, settings))
        return ('info', f'no robot description: learning the chain of the '
                        f'{len(self._joints)} joints from {seconds:.1f} s of data in the '
                        f'background (fit {self._attempts} of at most {MAX_ATTEMPTS})')

    @staticmethod
    def _run(job: _Job, settings: ChainSettings) -> None:
        """Fit (in the background thread); the result goes to ``job``."""
        _lower_priority()
        began = time.monotonic()
        try:
            job.found = fit_chain(job.train, job.validation, settings, job.names, job.stage,
                                  job.case)
        except Abandoned:
            job.error = 'abandoned'
        except Exception as exc:  # noqa: B902 - a failed fit is reported, the node goes on
            job.error = f'{exc!r}\n{traceback.format_exc()}'
        finally:
            job.wall = time.monotonic() - began
            job.done.set()

    def _judge(self, job: _Job) -> List[Tuple[str, str]]:
        """Return the lines of an ended fit; accept its chain if it predicts the held-out τ."""
        if job.cancelled:
            return []
        if job.error == 'abandoned':
            return [('warning', f'chain learning abandoned after {job.wall:.0f} s (more '
                                f'than {MAX_FIT_S:.0f} s)')]
        if job.error is not None:
            return [('error', f'chain learning failed: {job.error}')]
        structure, line = judged(job.found, job.names, self.max_error,
                                 f'chain learned in {job.wall:.0f} s from {job.seconds:.1f} '
                                 's of data')
        if structure is None:
            more = (f'; again with {RETRY_S:.0f} s more data' if self._attempts < MAX_ATTEMPTS
                    else '; no more tries (~/reset starts afresh)')
            return [(line[0], line[1] + more)]
        structure.report.update(data_s=job.seconds, fit_wall_s=job.wall)
        self.structure, self.error = structure, float(np.max(
            structure.report['held_out_errors']))
        return [line]


def judged(found, names, max_error: float = MAX_ERROR, head: str = 'chain learned'):
    """
    Return ``(structure, (level, line))`` of a :func:`~.chain_fit.fit_chain` result.

    ``structure``: the chain's :class:`~..rigid.chain.ChainStructure` (its fitted parameters
    the prior, ``report`` the chain, how well the data fixed it and the held-out errors),
    None when ``found`` is None or its held-out torque error (worst joint) is above
    ``max_error``.
    """
    if found is None:
        return None, ('warning', 'chain learning: too few data for its rows')
    error = found.fit.error
    what = ('closed-loop equation error' if found.report.get('case') == 'unknown'
            else 'torque error')
    head = f'{head}: held-out {what} {error:.2%} (worst joint)'
    if not error <= max_error:
        return None, ('warning', f'{head}, above {max_error:.0%}: not used')
    determined = found.report['determinacy']
    report = {'chain': found.report['chain'],
              'determinacy': {key: determined[key] for key in (
                  'axis_deg', 'line_m', 'gravity_tilt_deg', 'free_directions')},
              'symmetry': found.report['symmetry'],
              'held_out_errors': found.fit.errors.tolist()}
    structure = ChainStructure(found.chain, names, prior=found.arm.parameters,
                               source='the chain learned from joint data')
    structure.report = report
    dh = report['chain']['modified_dh']
    return structure, ('info', f'{head}: its rigid body is identified from now on as with a '
                               'robot description (modified DH alpha '
                               f"{np.round(dh['alpha_deg'], 1).tolist()} deg, a "
                               f"{np.round(dh['a_m'], 3).tolist()} m, d "
                               f"{np.round(dh['d_m'], 3).tolist()} m)")


def learn_chain(segments: Sequence[Dataset], names=None,
                settings: ChainSettings = ChainSettings(),
                validation_fraction: float = VALIDATION_FRACTION, max_error: float = MAX_ERROR,
                log: Optional[Callable[[str, str], None]] = None,
                case: str = 'torque') -> Optional[ChainStructure]:
    """
    Return the chain learned from ``segments``, or None (offline; module docstring).

    ``case`` 'torque': the segments with τ; 'unknown': with θd and θ̇d, the servo's gains
    unknown. The newest ``validation_fraction`` is held out to judge it (:func:`judged`);
    ``log`` takes ``(level, text)`` lines. None too for fewer than :data:`MIN_JOINTS` joints.
    """
    log = log or (lambda level, text: None)
    segments = [seg for seg in segments if seg.n_samples >= MIN_SEGMENT_SAMPLES
                and case_signals(seg, case) is not None]
    if not segments or not MIN_JOINTS <= segments[0].n_joints <= MAX_JOINTS:
        return None
    names = tuple(names or segments[0].joint_names)
    train, validation, seconds = split_validation(segments, validation_fraction,
                                                  MIN_SEGMENT_SAMPLES)
    began = time.monotonic()
    found = fit_chain(train, validation, settings, names,
                      lambda text: log('info', f'chain learning: {text}'), case)
    structure, line = judged(found, names, max_error, f'chain learned in '
                             f'{time.monotonic() - began:.0f} s from {seconds:.1f} s of data')
    log(*line)
    if structure is not None:
        structure.report.update(data_s=seconds, fit_wall_s=time.monotonic() - began)
    return structure


class ChainSteps:
    """The learned chain's steps of :class:`~.online.OnlineIdentification` (module docstring)."""

    def close(self) -> None:
        """Abandon what runs in the background (the chain learner's fit)."""
        self._chain.close()

    def _with_learned(self, obs):
        """Return ``obs`` with the learned chain as its structure where none is given."""
        chain = self._chain.structure
        if (obs.structure is None and chain is not None and obs.joints is not None
                and tuple(obs.joints) == chain.joint_names):
            return obs._replace(structure=chain)
        return obs

    def _chain_case(self, case: str) -> str:
        """Return the case the learner may fit in ('' where the planar trigonometric arm holds)."""
        return case if self._laws.trig is None and self._arm3.loop is None else ''

    def _chain_step(self, obs):
        """Without a description: judge or start the chain learner's fit (the module docstring)."""
        if obs.structure is not None:
            return obs
        if obs.reset:
            self._chain.reset()
        keeper = self._rigid.keeper
        if keeper is not None and keeper.structure is self._chain.structure:
            for level, text in self._chain.judge_in_use(keeper.fit):
                self._out.log(level, text)
        for level, text in self._chain.poll(self._chain_case(obs.settings.case)):
            self._out.log(level, text)
        return self._with_learned(obs)

    def _chain_feed(self, settings, joints, segments, capture) -> None:
        """Give the learner the buffered segments (with τ); start a fit now due."""
        if settings.case in LEARNED_CASES and self._chain.wants_data(joints):
            if settings.case == 'pd_gains':
                segments = servo_torque(segments, settings.kp, settings.kd)
            self._chain.feed(joints, segments, capture.time_origin,
                             getattr(capture, 'epoch', None), chain_case(settings.case))
            # a fit due now starts before this step's generation
            for level, text in self._chain.poll(self._chain_case(settings.case)):
                self._out.log(level, text)

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
Ingestion: the joint streams into the buffer, every rejection counted and logged.

:class:`Ingestion` turns joint_states and joint_commands (raw CDR bytes) and the reference
trajectory into buffered arrays (:class:`~rkgnn_ros.streams.buffer.StreamBuffer`), learns
the joints from the first message when none are configured, and keeps the newest state and
command for predictions. It holds the node's drop accounting
(:class:`~rkgnn_ros.identification.drops.DropAccount`, :attr:`Ingestion.drops`), which
every other part reports to as well. Nothing it is given raises: bad bytes are a counted
reason.

The two streams can come at 1 kHz each. Waking rclpy's executor for every message costs
more than handling the message (README, *Responsiveness*), so their subscriptions sit in a
callback group the executor never waits on (:class:`PolledGroup`) and the ingest thread
(:meth:`Ingestion.start`) takes what is queued on them every :data:`INGEST_PERIOD_S`. A
lock, also taken while the joints, the buffer or the settings change, keeps a message
from seeing them half changed. The parts are testable with bytes, no middleware: the
handlers take exactly what the subscriptions deliver.

What a driver leaves out is decided by :class:`~rkgnn_ros.identification.sources.Sources`
(the case of ``case: auto``, θ̇ estimated from θ, the plan standing in for
``joint_commands``). Every accepted state and command also goes, as ``(kind, stamp, θ)``,
into :attr:`Ingestion.feed`, a bounded queue the predictor's self-check drains.
"""

from collections import deque
from dataclasses import replace
import math
import threading
import time
from typing import Callable, Dict, NamedTuple, Optional, Tuple

import numpy as np
from rclpy.callback_groups import CallbackGroup
from rclpy.exceptions import InvalidHandle
from rkgnn_ros.identification.drops import DropAccount
from rkgnn_ros.identification.parameters import MAX_JOINTS
from rkgnn_ros.identification.plausibility import PlausibilityFilter
from rkgnn_ros.identification.sources import read_joint_state, Sources
from rkgnn_ros.streams.buffer import Capture, PlannedReference, StreamBuffer
from rkgnn_ros.wire.cdr import encapsulation_problem
from rkgnn_ros.wire.conversions import (joint_trajectory_cdr_to_arrays, joint_trajectory_to_arrays,
                                        parse_joint_state_cdr, Rejection)

__all__ = ['INGEST_PERIOD_S', 'Ingestion', 'PolledGroup', 'StateSample']

DRAIN_LIMIT = 100        # queued stream messages taken per stream and pass
FEED_LIMIT = 20000       # states and commands kept for the self-check (at 1 kHz: 10 s)
INGEST_PERIOD_S = 0.001  # the ingest thread takes the queued stream messages this often
JOIN_TIMEOUT_S = 10.0


class StateSample(NamedTuple):
    """The newest accepted joint_states sample."""

    stamp: Tuple[int, int]  # header stamp (sec, nanosec), copied into what derives from it
    t: float                # the stamp in seconds
    theta: np.ndarray       # (n,)
    theta_dot: np.ndarray   # (n,), measured or estimated from θ
    tau: Optional[np.ndarray]  # (n,), case 'torque' only
    received_ns: int        # when the middleware received it (time.time_ns clock)
    velocity_estimated: bool = False


class PolledGroup(CallbackGroup):
    """A callback group the executor never runs: its subscriptions are polled instead."""

    def can_execute(self, entity) -> bool:
        return False

    def beginning_execution(self, entity) -> bool:
        return False

    def ending_execution(self, entity) -> None:
        pass


def received_ns(info) -> int:
    """Return the rmw receive time (ns) from rclpy's message info, else now."""
    received = info.get('received_timestamp') if isinstance(info, dict) else None
    return received if received else time.time_ns()


def _read_trajectory(msg, joints, now: float):
    """Read a reference (CDR bytes or a message): our CDR reader, never rclpy's."""
    if not isinstance(msg, (bytes, bytearray, memoryview)):
        return joint_trajectory_to_arrays(msg, joints, now=now)
    sample = joint_trajectory_cdr_to_arrays(msg, joints, now=now)
    if sample is None:  # another encapsulation: refused before rclpy prints on stderr
        return Rejection('malformed', encapsulation_problem(bytes(msg), 'JointTrajectory'))
    return sample


def _message_names(raw: bytes):
    """Return the joint names of a raw JointState, or None if it has none readable."""
    try:
        parsed = parse_joint_state_cdr(raw)
        return None if parsed is None else parsed[2]  # None: its own reading says why
    except Exception:  # noqa: B902 - the sample's own reading reports why
        return None


class IngestThread:
    """
    The thread that takes what is queued on polled raw subscriptions.

    ``streams`` pairs each subscription with its handler ``handle(raw, received_ns)``;
    every INGEST_PERIOD_S it takes at most DRAIN_LIMIT messages per stream. An exception in
    a handler is reported by ``on_error(topic)`` and the thread goes on, unless it is
    stopping or ``alive()`` says the node is gone.
    """

    def __init__(self, streams, alive: Callable[[], bool], on_error: Callable[[str], None]):
        self._streams = streams
        self._alive = alive
        self._on_error = on_error
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name='rkgnn_ingest', daemon=True)
        self._thread.start()

    def stop(self) -> bool:
        """Stop and join the thread; return False if it did not stop in time."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(JOIN_TIMEOUT_S)
        return not self._thread.is_alive()

    def _run(self) -> None:
        while not self._stop.wait(INGEST_PERIOD_S):
            for sub, handle in self._streams:
                try:
                    for raw, info in _drain(sub):
                        handle(raw, received_ns(info))
                except Exception:  # noqa: B902 - the thread must survive
                    if self._stop.is_set() or not self._alive():
                        return
                    self._on_error(sub.topic_name)


def _drain(sub):
    """Yield the ``(message, info)`` pairs already queued on ``sub``, at most DRAIN_LIMIT."""
    for _ in range(DRAIN_LIMIT):
        try:
            with sub.handle:
                taken = sub.handle.take_message(sub.msg_type, sub.raw)
        except InvalidHandle:  # destroyed at shutdown
            return
        if taken is None:
            return
        yield taken


class Ingestion:
    """
    The joint streams in: conversion, buffering, the newest samples, drop accounting.

    Parameters
    ----------
    config : Config
        The parameters (:class:`~rkgnn_ros.identification.parameters.Config`); replaced by
        :meth:`reconfigure`.
    log : callable
        ``log(level, text)``, level 'info' or 'warning' (the node queues them for its
        executor).
    alive : callable, optional
        Returns False once the node shuts down: errors then are not counted.
    on_state : callable, optional
        Called when a prediction is due on an accepted state (``prediction.on_state``).
    clock : callable
        Monotonic seconds (staleness, log throttling).

    Attributes
    ----------
    drops : DropAccount
        The node's drop accounting: every part reports its drops here.

    """

    def __init__(self, config, log: Callable[[str, str], None],
                 alive: Callable[[], bool] = lambda: True,
                 on_state: Optional[Callable[[], None]] = None,
                 clock: Callable[[], float] = time.monotonic):
        self._config = config
        self._log = log
        self._alive = alive
        self._on_state = on_state or (lambda: None)
        self._clock = clock
        # held while a stream message is handled, and while the joints, the buffer or the
        # settings they depend on change
        self.lock = threading.RLock()
        self._joints: Optional[Tuple[str, ...]] = None
        self._buffer: Optional[StreamBuffer] = None
        # per stream: what no arm could produce is dropped before the buffer
        self._plausible = {stream: PlausibilityFilter(()) for stream in ('state', 'command')}
        self.drops = DropAccount(log, lambda: self._buffer, alive, clock)
        self._received: Dict[str, float] = {}
        self._last_state_prediction = -math.inf
        self.latest_state: Optional[StateSample] = None
        self.latest_command: Optional[np.ndarray] = None  # θd (n,)
        self.sources = Sources(config)
        #: ('state' | 'command', stamp, θ or θd (n,)) per accepted sample, for the self-check
        self.feed: deque = deque(maxlen=FEED_LIMIT)
        self._thread: Optional[IngestThread] = None
        if config['joints']:
            self.set_joints(config['joints'], 'the joints parameter')

    # ------------------------------------------------------------------ reading

    @property
    def joints(self) -> Optional[Tuple[str, ...]]:
        """Return the joint names (None until known)."""
        return self._joints

    @property
    def buffer(self) -> Optional[StreamBuffer]:
        """Return the stream buffer, None until the joints are known."""
        return self._buffer

    def view(self):
        """
        Return ``(config, joints, buffer, received)``, consistent with each other.

        The config's settings carry the case in effect (``case: auto`` follows the streams).
        """
        with self.lock:
            config, case = self._config, self.sources.case
            if case is not None and case != config.settings.case:
                config = replace(config, settings=replace(config.settings, case=case))
            return config, self._joints, self._buffer, dict(self._received)

    def seconds(self) -> float:
        """Return the ingestion clock's time (s): what the times in ``view()[3]`` are on."""
        return self._clock()

    @property
    def velocity_estimated(self) -> bool:
        """Return whether the search's data get θ̇ from θ (``Sources.buffered_estimated``)."""
        return self.sources.buffered_estimated

    def capture(self) -> Optional[Capture]:
        """Return a capture of the buffered streams (None until the joints are known)."""
        buffer = self._buffer
        return None if buffer is None else buffer.capture()

    def reference(self) -> Optional[PlannedReference]:
        """Return the newest planned trajectory (immutable), or None."""
        buffer = self._buffer
        return None if buffer is None else buffer.reference()

    def samples_buffered(self) -> int:
        """Return the number of buffered joint_states samples."""
        buffer = self._buffer
        return buffer.stats()['state_samples'] if buffer is not None else 0

    # ------------------------------------------------------------------ configuration

    def reconfigure(self, config, rebuild: bool = False, joints_changed: bool = False) -> None:
        """
        Take new parameters; with ``rebuild`` make a new buffer (its data are dropped).

        With ``joints_changed`` the joints come from the ``joints`` parameter (empty: from
        the next joint_states message).
        """
        with self.lock:
            self._config = config
            before = self.sources.case
            self.sources.reconfigure(config)
            rebuild = rebuild or self.sources.case != before
            if joints_changed:
                self.set_joints(config['joints'] or None, 'the joints parameter')
            elif rebuild:
                self.set_joints(self._joints, 'a parameter change')

    def set_joints(self, joints, source: str) -> None:
        """Adopt ``joints`` (None: learn them from joint_states) and rebuild the buffer."""
        with self.lock:
            cfg = self._config
            joints = tuple(joints) if joints else None
            buffer = None
            if joints is not None:
                case = self.sources.case
                buffer = StreamBuffer(joints, cfg['model_step'], cfg['window'],
                                      cfg['gap_threshold'], need_tau=case == 'torque',
                                      need_desired=case != 'torque',
                                      max_rate_hz=cfg['max_rate_hz'])
            self._plausible = {stream: PlausibilityFilter(joints or ())
                               for stream in ('state', 'command')}
            with self.drops.lock:
                self.drops.retire(self._buffer)
                changed = joints != self._joints
                self._joints = joints
                self._buffer = buffer
            self.latest_state = None
            self.latest_command = None
            self._received = {}
        if changed:
            if joints is None:
                self._log('info', 'joints: taken from the next joint_states message')
            else:
                self._log('info', f'joints from {source}: {list(joints)}')

    def clear(self) -> None:
        """Forget every buffered sample and the reference (``~/reset``); counters stay."""
        buffer = self._buffer
        with self.lock:
            for plausible in self._plausible.values():
                plausible.reset()
        if buffer is not None:
            buffer.clear()

    # ------------------------------------------------------------------ messages

    def handle_state(self, raw: bytes, received: int = 0) -> None:
        """Take one joint_states message (CDR bytes) received at ``received`` ns."""
        try:
            with self.lock:
                self._handle_state(raw, received or time.time_ns())
        except Exception:  # noqa: B902 - bad input is counted, never raised
            self.drops.internal_error('joint_states')

    def handle_command(self, raw: bytes, received: int = 0) -> None:
        """Take one joint_commands message (CDR bytes)."""
        try:
            with self.lock:
                self._handle_command(raw)
        except Exception:  # noqa: B902 - bad input is counted, never raised
            self.drops.internal_error('joint_commands')

    def handle_reference(self, msg, now: float) -> None:
        """
        Take one reference_trajectory message (a zero stamp means ``now``, in s).

        ``msg`` is its CDR bytes (the node's subscription is raw: the size budgets are
        checked before anything is built from the points) or a JointTrajectory.
        """
        try:
            sample = self._parsed('reference_trajectory', 'reference',
                                  lambda joints: _read_trajectory(msg, joints, now))
            if sample is None:
                return
            result = self._buffer.add_reference(sample.t0, sample.times, sample.positions,
                                                sample.velocities)
            if not result.accepted:
                self.drops.log_drop('reference_trajectory', result.reason,
                                    'rejected by the buffer')
        except Exception:  # noqa: B902 - bad input is counted, never raised
            self.drops.internal_error('reference_trajectory')

    def _parsed(self, topic: str, stream: str, read):
        """Return ``read(joints)``, or None if the joints are not known or it is refused."""
        if self._joints is None:
            self.drops.reject(topic, stream, 'no_joints',
                              'joints not known yet (waiting for joint_states)')
            return None
        sample = read(self._joints)
        return None if self.drops.refused(topic, stream, sample) else sample

    def _buffered(self, topic: str, result, stamp: float) -> bool:
        """Return whether the buffer took a sample; warn of a clock jump, log a refusal."""
        if result.clock_jump:
            self._warn_jump(topic, stamp)
        if not result.accepted:
            self.drops.log_drop(topic, result.reason,
                                f'stamp {stamp:.6f} s rejected by the buffer')
        return bool(result.accepted)

    def _handle_state(self, raw: bytes, received: int) -> None:
        cfg = self._config
        sources = self.sources
        need_tau = cfg.case == 'torque'  # a set case 1: effort or nothing
        joints = self._joints
        if joints is None:
            names = _message_names(raw) or ()
            sample = read_joint_state(raw, names, need_tau)
            if sample.ok and len(names) > MAX_JOINTS:
                sample = Rejection('over_budget', f'{len(names)} joints to learn, more than '
                                                  f'{MAX_JOINTS}: set the joints parameter')
            if self.drops.refused('joint_states', 'state', sample):
                return
            self._decide_case(sample.effort is not None)
            self.set_joints(names, 'the first joint_states message')
            joints = self._joints
        sample = read_joint_state(raw, joints, need_tau)
        if self.drops.refused('joint_states', 'state', sample):
            return
        self._decide_case(sample.effort is not None)
        effort = sample.effort if sources.case == 'torque' else None
        if sources.case == 'torque' and effort is None:
            self.drops.reject('joint_states', 'state', 'missing_effort',
                              f'effort is empty or NaN (case torque, {sources.case_reason})')
            return
        passed, dropped = self._plausible['state'].offer(
            (sample, effort, received), sample.stamp, sample.position, sample.velocity, effort)
        for _, reason, why in dropped:
            self.drops.reject('joint_states', 'state', reason, f'{why}: no arm does that')
        for item in passed:
            self._take_state(*item)

    def _take_state(self, sample, effort, received: int) -> None:
        """Buffer a plausible joint_states sample; keep it as the newest state."""
        cfg, sources, joints = self._config, self.sources, self._joints
        theta_dot, estimated = sources.velocity(sample.stamp, sample.position,
                                                sample.velocity)
        result = self._buffer.add_state(
            sample.stamp, sample.position,
            np.zeros(len(joints)) if theta_dot is None else theta_dot, effort)
        if not self._buffered('joint_states', result, sample.stamp):
            return
        now = self._clock()
        self._received['state'] = now
        self.feed.append(('state', sample.stamp, sample.position))
        self._command_from_plan(sample.stamp, now)
        if theta_dot is None or not sources.history_ready:
            return  # θ̇ not known well enough yet to start a prediction from
        self.latest_state = StateSample(sample.sec_nanosec, sample.stamp, sample.position,
                                        theta_dot, effort, received, estimated)
        if cfg['prediction.on_state'] and now - self._last_state_prediction >= cfg['model_step']:
            self._last_state_prediction = now
            self._on_state()

    def _warn_jump(self, topic: str, stamp: float) -> None:
        self.drops.warn_throttled((topic, 'clock_jump'),
                                  f'{topic}: the clock jumped (the stream moved to stamp '
                                  f'{stamp:.3f} s): buffered data cleared, identification '
                                  'continues on the new timeline')

    def clock_reset(self, seconds: float) -> None:
        """
        Clear the buffer: the node's clock jumped back by ``seconds`` (``/clock`` reset).

        Counted as ``clock_jump``; what is buffered belongs to the old timeline.
        """
        with self.lock:
            buffer = self._buffer
            if buffer is None:
                return
            buffer.clock_reset()
            self.latest_state = None
            self.latest_command = None
        self.drops.warn_throttled(('clock', 'clock_jump'),
                                  f'the node clock jumped back by {seconds:.3f} s: buffered data '
                                  'cleared, identification continues on the new timeline')

    def _decide_case(self, effort: bool) -> None:
        """Let ``case: auto`` follow the streams; a switch rebuilds the buffer and says so."""
        case = self.sources.observe_effort(effort, self._clock())
        if case is None:
            return
        self._log('info', f'case auto: {case} ({self.sources.case_reason}); the search runs '
                          f'case {case} from the next data')
        if self._joints is not None:
            self.set_joints(self._joints, f'the switch to case {case}')

    def _command_from_plan(self, stamp: float, now: float) -> None:
        """Without joint_commands, take θd, θ̇d of the newest plan at a state's stamp."""
        if not self.sources.commands_from_plan(now):
            return
        plan = self._buffer.reference()
        if plan is None or not plan.t0 + plan.times[0] <= stamp <= plan.end:
            return
        theta_d, theta_d_dot = plan.at([stamp])
        if self._buffer.add_command(stamp, theta_d[0], theta_d_dot[0]).accepted:
            self.latest_command = theta_d[0]
            self._received['command'] = now
            self.feed.append(('command', stamp, theta_d[0]))

    def _handle_command(self, raw: bytes) -> None:
        sample = self._parsed('joint_commands', 'command',
                              lambda joints: read_joint_state(raw, joints, False))
        if sample is None:
            return
        if sample.velocity is None:
            self.drops.reject('joint_commands', 'command', 'missing_velocity',
                              'velocity (θ̇d) is empty or NaN')
            return
        passed, dropped = self._plausible['command'].offer(
            sample, sample.stamp, sample.position, sample.velocity)
        for _, reason, why in dropped:
            self.drops.reject('joint_commands', 'command', reason,
                              f'{why}: no servo is asked that')
        for item in passed:
            self._take_command(item)

    def _take_command(self, sample) -> None:
        """Buffer a plausible joint_commands sample; keep it as the newest command."""
        result = self._buffer.add_command(sample.stamp, sample.position, sample.velocity)
        if not self._buffered('joint_commands', result, sample.stamp):
            return
        self.latest_command = sample.position
        now = self._clock()
        self._received['command'] = now
        self.sources.command_received(now)
        self.feed.append(('command', sample.stamp, sample.position))

    # ------------------------------------------------------------------ the ingest thread

    def start(self, state_sub, command_sub) -> None:
        """Start the ingest thread on the two raw subscriptions (in a :class:`PolledGroup`)."""
        self._thread = IngestThread(((state_sub, self.handle_state),
                                     (command_sub, self.handle_command)),
                                    self._alive, self.drops.internal_error)

    def stop(self) -> bool:
        """Stop and join the ingest thread; return False if it did not stop in time."""
        return self._thread is None or self._thread.stop()

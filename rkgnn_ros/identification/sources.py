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
What the arm's driver publishes, and what the identifier makes of it.

Drivers differ: effort or none, a velocity or none (or one differenced from noisy
encoders), a ``joint_commands`` topic or only the plan. :class:`Sources` holds the three
decisions the ingestion (:mod:`.ingest`) takes per message, so that every driver gives
predictions:

Case (``case: auto``)
    Effort in joint_states (n finite values) -> 'torque'; else ``kp`` and ``kd`` given ->
    'pd_gains'; else 'unknown'. The first message decides at once. Afterwards a switch
    needs :data:`AUTO_SWITCH_S` seconds (node clock) and :data:`AUTO_SWITCH_MESSAGES`
    messages in which every message said the other thing: a few messages without effort (a
    driver's glitch) restart nothing; a driver that stops publishing effort for good
    switches a second later. A switch
    rebuilds the buffer (its layout depends on the case) and restarts the search. A set
    case is kept whatever the streams do (messages it cannot use are dropped and counted).
Velocity
    The search's data get θ̇ from θ, by the lag-free centred derivative
    (:mod:`rkgnn_ros.core.fitting.online`), unless ``velocity.estimate: missing`` and the
    driver has a velocity: a differenced velocity's noise (√2 σθ / dt) would otherwise
    reach the fits (on the paper's arm with 1e-4 rad of encoder noise and a gravity
    compensating servo, case 3's start predicted 2 s ahead at 1.96 % of the range with the
    differenced velocity, 0.1 % with the derivative; 2.04 / 1.98 % on exact data). The
    state a prediction starts from keeps the driver's velocity when it has one (finite for
    every joint), unless 'always'; else θ̇ is estimated by
    :func:`~rkgnn_ros.core.differentiate.causal_slope` (order 2 over the last
    :data:`~rkgnn_ros.core.differentiate.CAUSAL_WINDOW` samples, on their stamps: at 100 Hz
    about 4 ms of delay and 7 % more gain at 1 Hz, exact for quadratic motion). The history
    restarts at a gap (``gap_threshold``); until it holds :data:`MIN_HISTORY` samples no
    prediction starts from the state.
Commands
    ``joint_commands`` when it delivered within ``stale_timeout``; else the plan on
    ``reference_trajectory`` sampled at each state's stamp (θd, θ̇d of the newest plan,
    linear between its points), which is what the servo was following.

:func:`read_joint_state` reads a message whose velocity or effort may be missing.
"""

from collections import deque
from typing import Dict, Optional, Tuple

import numpy as np
from rkgnn_ros.core.differentiate import CAUSAL_ORDER, causal_slope, CAUSAL_WINDOW
from rkgnn_ros.identification.parameters import auto_case
from rkgnn_ros.wire.cdr import encapsulation_problem
from rkgnn_ros.wire.conversions import IF_PRESENT, joint_state_cdr_to_arrays, Rejection

__all__ = ['AUTO_SWITCH_MESSAGES', 'AUTO_SWITCH_S', 'MIN_HISTORY', 'Sources',
           'read_joint_state']

AUTO_SWITCH_S = 1.0  # s of contrary messages before case 'auto' switches ...
AUTO_SWITCH_MESSAGES = 10  # ... and at least this many of them
MIN_HISTORY = CAUSAL_ORDER + 2  # θ samples before an estimated θ̇ starts a prediction


class Sources:
    """
    The case, the velocity and the commands as the driver's streams allow them.

    Not thread-safe: the ingestion calls it under its lock.

    Parameters
    ----------
    config : Config
        The parameters; replaced by :meth:`reconfigure`.

    """

    def __init__(self, config):
        self._config = config
        self.case: Optional[str] = None      # the case in effect (None: 'auto', undecided)
        self.case_reason = ''
        self._contrary_since: Optional[float] = None
        self._contrary = 0
        self._history: deque = deque(maxlen=CAUSAL_WINDOW)   # (t, θ (n,)) of the newest
        self.velocity_estimated = False
        self._last_command: Optional[float] = None  # node clock of the last joint_commands
        self._first_state: Optional[float] = None   # ... and of the first state
        self.commands = 'none yet'
        self.reconfigure(config)

    def reconfigure(self, config) -> None:
        """Take new parameters; a set case takes effect at once, 'auto' decides anew."""
        self._config = config
        wanted = config.case
        if wanted != 'auto':
            self.case, self.case_reason = wanted, 'set by the case parameter'
        elif self.case_reason == 'set by the case parameter':
            self.case, self.case_reason = None, ''
        self._contrary_since, self._contrary = None, 0
        self._history.clear()

    @property
    def auto(self) -> bool:
        """Return whether the case follows the streams."""
        return self._config.case == 'auto'

    def observe_effort(self, effort: bool, now: float) -> Optional[str]:
        """
        Return the case to switch to after a state with or without ``effort`` (None: keep).

        Only with ``case: auto``; see the module docstring for the hysteresis.
        """
        if not self.auto:
            return None
        wanted = auto_case(effort, self._config.values)
        if wanted == self.case:
            self._contrary_since, self._contrary = None, 0
            return None
        if self.case is not None:
            if self._contrary_since is None:
                self._contrary_since = now
            self._contrary += 1
            if (now - self._contrary_since < AUTO_SWITCH_S
                    or self._contrary < AUTO_SWITCH_MESSAGES):
                return None
        self._contrary_since, self._contrary = None, 0
        self.case = wanted
        self.case_reason = ('effort in joint_states' if effort else
                            'no effort in joint_states, ' + (
                                'kp and kd given' if wanted == 'pd_gains'
                                else 'no gains given'))
        return wanted

    def velocity(self, t: float, theta: np.ndarray,
                 measured: Optional[np.ndarray]) -> Tuple[Optional[np.ndarray], bool]:
        """
        Return ``(θ̇, estimated)`` for a state at stamp ``t``.

        θ̇ is None when it must be estimated and fewer than two samples are known yet.
        """
        history = self._history
        if history and not 0.0 < t - history[-1][0] <= self._config['gap_threshold']:
            history.clear()
        history.append((t, theta))
        estimate = measured is None or self._config['velocity.estimate'] == 'always'
        self.velocity_estimated = estimate
        if not estimate:
            return measured, False
        if len(history) < 2:
            return None, True
        times = np.array([s for s, _ in history])
        values = np.array([v for _, v in history])
        return causal_slope(times, values, CAUSAL_ORDER), True

    @property
    def buffered_estimated(self) -> bool:
        """Return whether the search's data get θ̇ from θ (see the module docstring)."""
        return self.velocity_estimated or self._config['velocity.estimate'] != 'missing'

    @property
    def history_ready(self) -> bool:
        """Return whether an estimated θ̇ may start a prediction."""
        return not self.velocity_estimated or len(self._history) >= MIN_HISTORY

    def command_received(self, now: float) -> None:
        """Record a joint_commands sample at node clock ``now``."""
        self._last_command = now
        self.commands = 'joint_commands'

    def commands_from_plan(self, now: float) -> bool:
        """
        Return whether the plan stands in for joint_commands (silent for stale_timeout).

        Silent since the first state, too: a topic that starts a little after joint_states
        does not find its samples taken already.
        """
        if self._first_state is None:
            self._first_state = now
        last = self._first_state if self._last_command is None else self._last_command
        silent = now - last > self._config['stale_timeout']
        if silent:
            self.commands = 'reference_trajectory (no joint_commands)'
        return silent

    def describe(self) -> Dict[str, str]:
        """Return the diagnostics entries: case, velocity source, command source."""
        if self.case is None:
            case = 'auto: waiting for joint_states'
        else:
            case = f"{'auto -> ' if self.auto else ''}{self.case} ({self.case_reason})"
        if self.velocity_estimated:
            velocity = ('estimated from position (causal order-2 fit over the last '
                        f'{CAUSAL_WINDOW} samples for the start state, centred for the search)')
        else:
            velocity = 'joint_states' + (' (the search: centred derivative of position)'
                                         if self.buffered_estimated else '')
        return {'case_in_effect': case, 'velocity_source': velocity,
                'commands_source': self.commands}


def _read(raw: bytes, joints, need_velocity: bool, need_effort: bool):
    """
    Read a raw JointState (CDR bytes): our reader, never rclpy's deserializer.

    Plain CDR our reader refuses and bytes of another encapsulation are ``'malformed'``:
    rclpy's deserializer would print a line on stderr for each malformed message.
    """
    sample = joint_state_cdr_to_arrays(raw, joints, need_velocity, need_effort)
    if sample is not None:
        return sample
    problem = encapsulation_problem(raw, 'JointState')
    return Rejection('malformed', problem or f'{len(raw)} bytes of CDR that do not form a '
                                             'JointState')


def read_joint_state(raw: bytes, joints, need_effort: bool):
    """
    Read a raw JointState whose velocity and effort may be missing (empty or NaN).

    A missing field comes back as None; inf in a field it has is 'non_finite'; with
    ``need_effort`` a missing effort is 'missing_effort'. One pass over the bytes, usual
    message or not (commands carry no effort: at 1 kHz a second pass cost a third of
    their handling).
    """
    sample = _read(raw, joints, IF_PRESENT, IF_PRESENT)
    if sample.ok and need_effort and sample.effort is None:
        return Rejection('missing_effort', 'effort is empty or NaN (case torque)')
    return sample

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
The feed-forward input of a servo with an effort interface: what it takes, what it refuses.

A servo takes a feed-forward as a trajectory with efforts (a JointTrajectory: joint names,
a start stamp, points with ``time_from_start`` and ``effort``) and adds it to its own
torque at its own time (:class:`~rkgnn_ros.core.sim.servo.FeedforwardTrack`). A wrong
effort goes straight into the drive, so :class:`FeedforwardReceiver` applies only a
trajectory that is whole and sound, and otherwise runs the servo alone:

- the joints are mapped by name; an unknown, missing or repeated joint refuses it;
- every point needs one effort per joint, finite and within the drive's limit; times
  strictly increasing, at least two points;
- a trajectory whose last point is already in the past is stale;
- a refused trajectory also drops the one being applied: a source that sends garbage is
  not followed on its older word;
- an empty trajectory (no points) stops the feed-forward, as an empty trajectory stops
  joint_trajectory_controller; it is what the identifier sends when its gate closes;
- when the time passes the last point of the applied trajectory the servo runs alone
  (the track gives zero there) and the expiry is reported once.

Every refusal and every fall-back is counted per reason (:data:`REASONS`) and returned as
an :class:`Event` with a message that says why, for the node to log. Times are absolute
seconds on the servo's clock (a zero start stamp means "now"); :meth:`FeedforwardReceiver.track`
hands the applied trajectory to a simulation whose time starts at some origin.
"""

import math
from typing import Dict, NamedTuple, Optional, Sequence

import numpy as np

from .servo import FeedforwardTrack

#: Why the servo runs without a feed-forward: refusals, then the two normal ends.
REASONS = ('over_budget', 'bad_shape', 'unknown_joint', 'missing_joint', 'duplicate_joint',
           'no_effort', 'non_finite', 'over_limit', 'non_increasing_time', 'stale', 'not_started',
           'clock_jump', 'stopped', 'expired')


class Event(NamedTuple):
    """What happened to the feed-forward input: applied, or a reason and why."""

    applied: bool
    reason: str = ''
    message: str = ''


class FeedforwardReceiver:
    """
    The feed-forward a servo applies, and the count of everything it would not.

    Parameters
    ----------
    joint_names : sequence of str
        The servo's joints, in its column order.
    tau_limit : array_like, shape (n,) or scalar, optional
        The drives' limits (N m); an effort beyond them refuses the trajectory. None or
        ``inf``: no limit.

    """

    def __init__(self, joint_names: Sequence[str], tau_limit=None):
        self.joint_names = tuple(joint_names)
        self._index = {name: i for i, name in enumerate(self.joint_names)}
        n = len(self.joint_names)
        limit = np.inf if tau_limit is None else tau_limit
        self.tau_limit = np.broadcast_to(np.asarray(limit, dtype=float), (n,)).copy()
        self.counts: Dict[str, int] = dict.fromkeys(REASONS, 0)
        self.applied = 0
        self._times: Optional[np.ndarray] = None  # (K,) absolute s
        self._effort: Optional[np.ndarray] = None  # (K, n) N m, servo column order
        self._track: Optional[FeedforwardTrack] = None
        self._track_origin: Optional[float] = None

    @property
    def active(self) -> bool:
        """Return whether a feed-forward trajectory is held (it may not have begun yet)."""
        return self._times is not None

    @property
    def end(self) -> Optional[float]:
        """Return the absolute time (s) of the applied trajectory's last point, or None."""
        return None if self._times is None else float(self._times[-1])

    def offer(self, now: float, start: Optional[float], names: Sequence[str],
              times: Sequence[float], efforts: Sequence[Sequence[float]]) -> Event:
        """
        Take one feed-forward trajectory; return whether it is applied, or why not.

        Parameters
        ----------
        now : float
            The servo's time (s).
        start : float or None
            Absolute time (s) of ``time_from_start`` 0 (the header stamp); None or 0: now.
        names : sequence of str
            The message's joint names.
        times : sequence of float, length K
            ``time_from_start`` of each point (s).
        efforts : sequence of K sequences
            The points' efforts, in the message's joint order.

        """
        if len(times) == 0 and len(efforts) == 0:
            return self._refuse('stopped', 'an empty trajectory: the feed-forward stops')
        names = [str(name) for name in names]
        for name in names:
            if name not in self._index:
                return self._refuse('unknown_joint', f'unknown joint {name!r} (the servo has '
                                                     f'{list(self.joint_names)})')
        if len(set(names)) != len(names):
            return self._refuse('duplicate_joint', f'a joint is named twice in {names}')
        missing = [name for name in self.joint_names if name not in names]
        if missing:
            return self._refuse('missing_joint', f'no effort for joint(s) {missing}')
        if len(times) != len(efforts) or len(times) < 2:
            return self._refuse('bad_shape', f'{len(times)} times and {len(efforts)} points; '
                                             'at least 2 points are needed')
        try:
            if isinstance(efforts, np.ndarray) and efforts.ndim == 2:
                sizes = np.full(len(efforts), efforts.shape[1])
            else:
                sizes = np.fromiter(map(len, efforts), dtype=np.int64, count=len(efforts))
        except TypeError as exc:
            return self._refuse('bad_shape', f'a point without an effort list ({exc})')
        wrong = np.flatnonzero(sizes != len(names))
        if wrong.size:
            k = int(wrong[0])
            if sizes[k] == 0:
                return self._refuse('no_effort', f'point {k} has no effort')
            return self._refuse('bad_shape', f'point {k} has {sizes[k]} efforts for '
                                             f'{len(names)} joints')
        try:
            order = [names.index(name) for name in self.joint_names]
            effort = np.array(efforts, dtype=float).reshape(len(efforts), len(names))[:, order]
            t = np.asarray(times, dtype=float)
            start = float(now if not start else start)
        except (TypeError, ValueError) as exc:
            return self._refuse('bad_shape', f'not numeric ({exc})')
        if not (np.all(np.isfinite(effort)) and np.all(np.isfinite(t))
                and math.isfinite(start)):
            joints = sorted({self.joint_names[j]
                             for j in np.nonzero(~np.isfinite(effort))[1].tolist()})
            what = f'effort for joint(s) {joints}' if joints else 'time'
            return self._refuse('non_finite', f'NaN or inf {what}')
        over = np.abs(effort) > self.tau_limit
        if np.any(over):
            k, j = (int(v[0]) for v in np.nonzero(over))
            return self._refuse('over_limit', f'effort {effort[k, j]:.6g} N m for joint '
                                              f'{self.joint_names[j]!r} beyond its limit '
                                              f'{self.tau_limit[j]:.6g} N m')
        if np.any(np.diff(t) <= 0.0):
            return self._refuse('non_increasing_time',
                                'time_from_start must increase strictly from point to point')
        absolute = start + t
        if absolute[-1] <= now:
            return self._refuse('stale', f'its last point is {now - absolute[-1]:.3g} s in '
                                         'the past')
        self._times, self._effort = absolute, effort
        self._track = self._track_origin = None
        self.applied += 1
        return Event(True)

    def refuse(self, reason: str, message: str) -> Event:
        """Count a refusal decided by the caller (e.g. ``'not_started'``); run alone."""
        return self._refuse(reason, message)

    def expire(self, now: float) -> Optional[Event]:
        """Return the expiry event once the time ``now`` (s) passes the last point, else None."""
        if self._times is None or now <= self._times[-1]:
            return None
        return self._refuse('expired', 'its last point has passed')

    def track(self, origin: float) -> Optional[FeedforwardTrack]:
        """
        Return the applied trajectory on a time axis starting at ``origin`` (s), or None.

        The track is rebuilt only when the trajectory or the origin changes.
        """
        if self._times is None:
            return None
        if self._track is None or self._track_origin != origin:
            self._track = FeedforwardTrack(self._times - origin, self._effort)
            self._track_origin = origin
        return self._track

    def _refuse(self, reason: str, message: str) -> Event:
        self.counts[reason] = self.counts.get(reason, 0) + 1
        self._times = self._effort = self._track = self._track_origin = None
        return Event(False, reason, message)

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
A capture of a :class:`~rkgnn_ros.streams.buffer.StreamBuffer`, and what is read from it.

The buffer hands out copies, never itself: :class:`Capture` (the streams' arrays, copied
under the buffer's lock) resamples them into :class:`Snapshot` segments and pairs them for
a controller fit, in whatever thread takes its time over it; :class:`PlannedReference` is
the newest reference trajectory, immutable. Time base and pairing are those of
:mod:`rkgnn_ros.streams.buffer`.

Resampling
    θ, θ̇, τ are interpolated linearly between the state samples at each grid time
    ``k * model_step`` (τ is then held by the model over ``[t[k], t[k+1])`` as ``Dataset``
    states). Only the newest ``window`` seconds (before the newest state) are used;
    segments shorter than ``min_samples`` grid points are left out. With pairing, the
    grid times are paired like the states (θd, θ̇d interpolated at them), and only
    covered grid times make up segments.
Reference
    Interpolated linearly; outside its span the first / last position is held at zero
    velocity (the controller holds a point at rest).
"""

import math
from typing import Dict, List, Optional, Tuple

import numpy as np
from rkgnn_ros.core.data import Dataset

__all__ = ['Capture', 'PlannedReference', 'Snapshot']

_EPS = 1e-9  # s: slack for tolerance comparisons of stamps rounded in float64


class Snapshot(list):
    """
    A list of :class:`Dataset` segments, oldest first, with their shared time base.

    Attributes
    ----------
    time_origin : float
        Absolute time (s) of ``Dataset.t == 0``.
    epoch : int
        Incremented at every clear (clock jump or :meth:`StreamBuffer.clear`): datasets of
        different epochs do not share a timeline.

    """

    def __init__(self, segments=(), time_origin: float = 0.0, epoch: int = 0):
        super().__init__(segments)
        self.time_origin = time_origin
        self.epoch = epoch


def _interp_rows(x: np.ndarray, xp: np.ndarray, fp: np.ndarray,
                 gap: float = math.inf) -> np.ndarray:
    """
    Interpolate rows ``fp`` (M, W) given at sorted ``xp`` (M,) to ``x`` (K,): (K, W).

    Linear inside intervals at most ``gap`` long; the nearest sample inside longer ones;
    the end values held outside ``[xp[0], xp[-1]]``.
    """
    if xp.size == 1:
        return np.repeat(fp[:1], x.size, axis=0)
    lo = np.clip(np.searchsorted(xp, x, side='right') - 1, 0, xp.size - 2)
    span = xp[lo + 1] - xp[lo]  # > 0: stored stamps are strictly increasing
    w = np.clip((x - xp[lo]) / span, 0.0, 1.0)
    out = fp[lo] * (1.0 - w)[:, None] + fp[lo + 1] * w[:, None]
    gapped = span > gap + _EPS
    if gapped.any():
        nearest = np.where(w < 0.5, lo, lo + 1)
        out[gapped] = fp[nearest[gapped]]
    return out


def _hermite_rows(x: np.ndarray, xp: np.ndarray, p: np.ndarray,
                  v: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """
    Return the cubic Hermite interpolant and its derivative at ``x`` (K,): two (K, W).

    The cubic runs through positions ``p`` with velocities ``v`` (M, W) at sorted ``xp``
    (M >= 2). Outside ``[xp[0], xp[-1]]`` the end position is held at zero velocity.
    """
    lo = np.clip(np.searchsorted(xp, x, side='right') - 1, 0, xp.size - 2)
    h = (xp[lo + 1] - xp[lo])[:, None]
    u = np.clip((x - xp[lo]) / h[:, 0], 0.0, 1.0)[:, None]
    u2, u3 = u * u, u * u * u
    p0, p1, v0, v1 = p[lo], p[lo + 1], v[lo], v[lo + 1]
    pos = ((2.0 * u3 - 3.0 * u2 + 1.0) * p0 + (u3 - 2.0 * u2 + u) * h * v0
           + (3.0 * u2 - 2.0 * u3) * p1 + (u3 - u2) * h * v1)
    vel = ((6.0 * u2 - 6.0 * u) * (p0 - p1) / h + (3.0 * u2 - 4.0 * u + 1.0) * v0
           + (3.0 * u2 - 2.0 * u) * v1)
    vel[(x < xp[0]) | (x > xp[-1])] = 0.0
    return pos, vel


def covered_by(x: np.ndarray, xp: np.ndarray, gap: float, tol: float) -> np.ndarray:
    """Return which times ``x`` the sorted command stamps ``xp`` cover (see pairing)."""
    m = xp.size
    if m == 0:
        return np.zeros(x.shape, dtype=bool)
    idx = np.searchsorted(xp, x, side='right')  # xp[idx-1] <= x < xp[idx]
    lo = np.clip(idx - 1, 0, m - 1)
    hi = np.clip(idx, 0, m - 1)
    inside = (idx > 0) & (idx < m) & (xp[hi] - xp[lo] <= gap + _EPS)
    near = np.minimum(np.abs(x - xp[lo]), np.abs(xp[hi] - x)) <= tol + _EPS
    return inside | near


def _runs(mask: np.ndarray) -> List[Tuple[int, int]]:
    """Return ``[start, stop)`` index pairs of the True runs in a boolean array."""
    edges = np.flatnonzero(np.diff(np.concatenate(([0], mask.astype(np.int8), [0]))))
    return list(zip(edges[::2].tolist(), edges[1::2].tolist()))


class PlannedReference:
    """
    One planned reference, immutable: θd, θ̇d at ``t0 + times``.

    What :meth:`StreamBuffer.reference` hands out: readers keep it as long as they like,
    whatever the buffer does meanwhile.
    """

    def __init__(self, t0: float, times: np.ndarray, positions: np.ndarray,
                 velocities: np.ndarray, cubic: bool = True):
        self.t0, self.times, self.positions, self.velocities = t0, times, positions, velocities
        self.cubic = bool(cubic)  # False: the velocities were estimated (positions only)
        for array in (times, positions, velocities):
            array.flags.writeable = False

    @classmethod
    def checked(cls, t0, times, positions, velocities, n: int, max_abs_value: float,
                max_points: int = 10_000):
        """
        Return ``(reference, None)`` from raw arrays, or ``(None, drop reason)``.

        ``times`` (K,) from ``t0``, ``positions`` (K, n) θd, ``velocities`` (K, n) θ̇d or
        None to estimate them from the positions (``np.gradient``; zero for one point).
        Reasons: 'over_budget' (more than ``max_points`` points, not copied), 'bad_shape',
        'bad_stamp', 'non_finite', 'out_of_range' (beyond ``max_abs_value``),
        'non_increasing_time'.
        """
        try:
            if np.size(times) > max_points:
                return None, 'over_budget'
        except Exception:  # noqa: B902 - whatever it is, it is not a reference
            return None, 'bad_shape'
        try:
            t0 = float(t0)
            times = np.array(times, dtype=float).reshape(-1)
            positions = np.array(positions, dtype=float)
            if velocities is not None:
                velocities = np.array(velocities, dtype=float)
        except Exception:  # noqa: B902 - whatever it is, it is not a reference
            return None, 'bad_shape'
        k = times.size
        if k == 0 or positions.shape != (k, n) or (
                velocities is not None and velocities.shape != (k, n)):
            return None, 'bad_shape'
        values = [positions] if velocities is None else [positions, velocities]
        if not (math.isfinite(t0) and np.isfinite(times).all()):
            return None, 'bad_stamp'
        if not all(np.isfinite(v).all() for v in values):
            return None, 'non_finite'
        if any(np.abs(v).max() > max_abs_value for v in values):
            return None, 'out_of_range'
        if k > 1 and not np.all(np.diff(times) > 0.0):
            return None, 'non_increasing_time'
        cubic = velocities is not None
        if velocities is None:
            velocities = np.gradient(positions, times, axis=0) if k > 1 else \
                np.zeros_like(positions)
            if not np.isfinite(velocities).all():
                return None, 'non_finite'
        return cls(t0, times, positions, velocities, cubic), None

    @property
    def end(self) -> float:
        """Return the absolute time (s) of the last point."""
        return self.t0 + float(self.times[-1])

    def at(self, t) -> Tuple[np.ndarray, np.ndarray]:
        """
        Return (θd, θ̇d), each (M, n), at absolute times ``t`` (M,).

        Inside the reference, as joint_trajectory_controller samples a trajectory: the cubic
        (Hermite) through each interval's end positions and velocities when the plan gave
        velocities (θ̇d its derivative), linear when it gave positions only (θ̇d then the
        estimated velocities, interpolated). Before its first point the first position and
        after its last point the last position is held, with zero velocity. Linear
        interpolation of a 20 ms plan misses a sine's θd by h²/8·θ̈d (1e-4 rad at 0.5 Hz,
        the size of the whole 2 s-ahead error of a good model); the cubic by h⁴/384·θd⁗.
        """
        s = np.atleast_1d(np.asarray(t, dtype=float)) - self.t0
        if self.cubic and self.times.size > 1:
            return _hermite_rows(s, self.times, self.positions, self.velocities)
        theta_d = _interp_rows(s, self.times, self.positions)
        theta_d_dot = _interp_rows(s, self.times, self.velocities)
        theta_d_dot[(s < self.times[0]) | (s > self.times[-1])] = 0.0
        return theta_d, theta_d_dot


class Capture:
    """
    A consistent copy of a buffer's streams, read without any lock ever after.

    What :meth:`StreamBuffer.capture` returns: the arrays are copies taken under the
    buffer's lock, so resampling them (:meth:`segments`) or pairing them for a controller
    fit (:meth:`controller_samples`) can take its time in another thread while samples
    keep arriving. ``failures`` counts the segments :meth:`segments` could not build.
    """

    def __init__(self, buffer, states, commands, origin, epoch):
        self.joints = buffer.joints
        self.model_step, self.window = buffer.model_step, buffer.window
        self.gap_threshold, self.pair_tolerance = buffer.gap_threshold, buffer.pair_tolerance
        self.need_tau, self.need_desired = buffer.need_tau, buffer.need_desired
        self._n = len(buffer.joints)
        self._ts, self._vs = states    # (K,), (K, 2n or 3n)
        self._tc, self._vc = commands  # (L,), (L, 2n)
        self.time_origin = 0.0 if origin is None else origin
        self.epoch = epoch
        self.failures = 0

    def segments(self, min_samples: int = 2, pair_commands: bool = False) -> Snapshot:
        """
        Return the newest ``window`` seconds as uniformly resampled segments.

        Segments have at least ``max(2, min_samples)`` points at ``model_step``. With
        ``pair_commands`` the segments carry θd, θ̇d (paired as with ``need_desired``, so
        only covered grid times make up segments) even when ``need_desired`` is False.
        """
        pair = self.need_desired or bool(pair_commands)
        segments, failures = self._resample(max(2, int(min_samples)), pair)
        self.failures += failures
        return Snapshot(segments, self.time_origin, self.epoch)

    def controller_samples(self) -> Optional[Dict[str, np.ndarray]]:
        """
        Return the states of the window paired with commands, for a controller fit.

        Only with ``need_tau`` (case 'torque', where the applied torque is measured): the
        state samples of the newest ``window`` seconds that the command stream covers (see
        pairing), with θd, θ̇d interpolated at their stamps, whether or not ``need_desired``.
        Keys ``theta``, ``theta_dot``, ``tau``, ``theta_d``, ``theta_d_dot``, each (K, n);
        None when τ is not stored or no state is covered.
        """
        ts, vs, tc, vc = self._ts, self._vs, self._tc, self._vc
        if not self.need_tau or not ts.size or not tc.size:
            return None
        keep = (ts >= ts[-1] - self.window) & covered_by(
            ts, tc, self.gap_threshold, self.pair_tolerance)
        if not keep.any():
            return None
        n = self._n
        ts, vs = ts[keep], vs[keep]
        desired = _interp_rows(ts, tc, vc, self.gap_threshold)
        return {'theta': vs[:, :n], 'theta_dot': vs[:, n:2 * n], 'tau': vs[:, 2 * n:],
                'theta_d': desired[:, :n], 'theta_d_dot': desired[:, n:]}

    def _resample(self, min_samples, pair):
        n, h = self._n, self.model_step
        ts, vs, tc, vc = self._ts, self._vs, self._tc, self._vc
        if ts.size < 2:
            return [], 0
        t_start = ts[-1] - self.window
        first = max(int(np.searchsorted(ts, t_start, side='right')) - 1, 0)
        ts, vs = ts[first:], vs[first:]
        segments: List[Dataset] = []
        failures = 0
        breaks = np.flatnonzero(np.diff(ts) > self.gap_threshold + _EPS) + 1
        for a, b in zip(np.concatenate(([0], breaks)), np.concatenate((breaks, [ts.size]))):
            if b - a < 2:
                continue
            k0 = math.ceil(max(ts[a], t_start) / h - 1e-9)
            k1 = math.floor(ts[b - 1] / h + 1e-9)
            if k1 - k0 + 1 < min_samples:
                continue
            grid = np.arange(k0, k1 + 1) * h
            if pair:
                runs = _runs(covered_by(grid, tc, self.gap_threshold, self.pair_tolerance))
            else:
                runs = [(0, grid.size)]
            for r0, r1 in runs:
                if r1 - r0 < min_samples:
                    continue
                t = grid[r0:r1]
                state = _interp_rows(t, ts[a:b], vs[a:b])
                fields = {'theta': state[:, :n], 'theta_dot': state[:, n:2 * n]}
                if self.need_tau:
                    fields['tau'] = state[:, 2 * n:]
                if pair:
                    desired = _interp_rows(t, tc, vc, self.gap_threshold)
                    fields['theta_d'] = desired[:, :n]
                    fields['theta_d_dot'] = desired[:, n:]
                try:
                    segments.append(Dataset(t=t, joint_names=self.joints, **fields))
                except ValueError:  # defensive: validation above should make this unreachable
                    failures += 1
        return segments, failures

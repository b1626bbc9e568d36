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
The rows a chain is scored on, and its score: the residual of the best inertial parameters.

A candidate chain is scored thousands of times, so its rows are few and chosen once:

- :func:`state_rows` (the search): ``count`` instants drawn from the data, θ, θ̇ and θ̈
  from θ through one Gaussian of σ and its derivatives, τ through the same Gaussian. Y is
  evaluated once per row, but Y(h * θ) is not h * Y(θ): on motion below 1 Hz and σ = 0.02 s
  the rows are off by about 1e-2 of the torque, enough to hide the lightest bodies;
- :func:`block_rows` (the refinement): :mod:`.rigid_data`'s parallel filtering, exact
  whatever the motion, on short blocks of consecutive rows at random places: Y at every
  sample of a block and its margins, filtered by the same Gaussian as τ.

:class:`ChainScore` is the variable projection: for a chain's :class:`~..rigid.kernels.Tree`
the weighted rows A (each joint's over its RMS torque, every column scaled to unit norm),
β = argmin ‖A β − y‖ (normal equations with a ridge of :data:`RIDGE` of the mean diagonal,
which drops the columns no torque depends on), and the residual A β − y over ‖y‖: its
squared norm is the share of the weighted torque the chain leaves unexplained.
Case 3's rows (``servo=True``, :meth:`ChainRows.with_unknown_gains`) carry the servo's
errors filtered as τ and the gains as extra columns, unknowns the projection solves for
beside the parameters (they do not depend on the chain).
:meth:`ChainScore.jacobian` is Kaufman's: P⊥ (∂A/∂x) β, (∂A/∂x) β by forward differences
of the rows' torques at β (:meth:`ChainRows.torques`: one inverse dynamics per coordinate,
not a regressor, and no solve).
"""

import math
from typing import Callable, NamedTuple, Optional, Sequence

import numpy as np

from .rigid_data import (choose_sigma, DERIVATIVE_SIGMA, error_integral,
                         second_derivative_kernel)
from ..data import Dataset
from ..differentiate import gaussian_kernels
from ..rigid import kernels
from ..rigid.kernels import N_INERTIAL, N_JOINT, Tree

__all__ = ['ChainRows', 'ChainScore', 'RIDGE', 'block_rows', 'state_rows', 'torque_weights']

#: Ridge of the normal equations, a share of their mean diagonal (columns at unit norm).
RIDGE = 1e-10


def _convolve(x: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    return np.stack([np.convolve(x[:, j], kernel, 'valid') for j in range(x.shape[1])], 1)


class _Group(NamedTuple):
    """Blocks of one sampling interval: ``count`` blocks of ``length`` states, filter H."""

    first: int
    count: int
    length: int
    smoothing: np.ndarray   # (k, length): the kept rows of one block from its states


class ChainRows:
    """
    States at which Y is evaluated, and the torques the rows are fitted to.

    ``q``, ``qd``, ``qdd`` (S, n): the states; ``tau`` (R, n): the rows' torques. Without
    groups R = S (a row per state); with them each group's blocks are filtered to rows.
    ``servo`` (R, n, 3): the servo's errors θd − θ, θ̇d − θ̇ and ∫(θd − θ) dt from the
    segment's start, filtered as τ (case 3's rows carry them); ``segment`` (R,): the segment
    each row comes from; ``extra`` (R n, E): columns of unknowns that do not depend on the
    chain, fitted beside the parameters (:meth:`with_unknown_gains`).
    """

    def __init__(self, q, qd, qdd, tau, groups: Sequence[_Group] = (), servo=None,
                 extra=None, segment=None):
        self.q, self.qd, self.qdd = (np.ascontiguousarray(v, dtype=float) for v in (q, qd, qdd))
        self.tau = np.asarray(tau, dtype=float)
        self.groups = tuple(groups)
        self.n = self.q.shape[1]
        self.columns = np.arange((N_INERTIAL + N_JOINT) * self.n)
        self.servo = None if servo is None else np.asarray(servo, dtype=float)
        self.extra = None if extra is None else np.asarray(extra, dtype=float)
        self.segment = (np.zeros(self.tau.shape[0], dtype=np.int64) if segment is None
                        else np.asarray(segment, dtype=np.int64))

    def with_unknown_gains(self, integral: bool = False) -> 'ChainRows':
        """
        Return the rows of case 3: a PD servo of unknown gains, their mean Kp the unit.

        Y π = Kp e + Kd ė on every joint is homogeneous in (π, Kp, Kd); with
        Kp_1 = n − Σ_{j>1} Kp_j (the mean Kp is 1) it is Y π − Σ_{j>1} Kp_j (e_j − e_1)
        − Σ_j Kd_j ė_j = n e_1: the target holds joint 1's rows, the extra columns the
        other gains' (:meth:`gains` reads them back). ``integral``: a PID servo, + Ki ∫e on
        every joint, ∫e from each segment's start: a column of Ki per joint, and per joint a
        constant for every segment after the first (Ki times the integral at the segment's
        start; the first segment's is the arm's offset, a column of Y).
        """
        if self.servo is None:
            raise ValueError('these rows carry no servo errors')
        rows, n = self.n_rows, self.n
        e, ed = self.servo[:, :, 0], self.servo[:, :, 1]
        columns = []
        for j in range(1, n):
            c = np.zeros((rows, n))
            c[:, j] = e[:, j]
            c[:, 0] = -e[:, 0]
            columns.append(c.reshape(-1))
        for j in range(n):
            c = np.zeros((rows, n))
            c[:, j] = ed[:, j]
            columns.append(c.reshape(-1))
        if integral:
            if self.servo.shape[2] < 3:
                raise ValueError('these rows carry no integral of the servo errors')
            for j in range(n):
                c = np.zeros((rows, n))
                c[:, j] = self.servo[:, j, 2]
                columns.append(c.reshape(-1))
            for seg in np.unique(self.segment)[1:]:
                for j in range(n):
                    c = np.zeros((rows, n))
                    c[self.segment == seg, j] = 1.0
                    columns.append(c.reshape(-1))
        target = np.zeros((rows, n))
        target[:, 0] = n * e[:, 0]
        return ChainRows(self.q, self.qd, self.qdd, target, self.groups, self.servo,
                         -np.stack(columns, axis=1), self.segment)

    def gains(self, extra) -> tuple:
        """Return (Kp, Kd) (n,), mean Kp 1, of the extra columns' coefficients ``extra``."""
        n = self.n
        extra = np.asarray(extra, dtype=float)
        kp = np.concatenate([[n - float(np.sum(extra[:n - 1]))], extra[:n - 1]])
        return kp, extra[n - 1:2 * n - 1].copy()

    def scaled(self, factor: float) -> 'ChainRows':
        """Return these rows with their target (τ, or case 3's n e_1) times ``factor``."""
        return ChainRows(self.q, self.qd, self.qdd, self.tau * factor, self.groups, self.servo,
                         self.extra, self.segment)

    def integral_gains(self, extra) -> np.ndarray:
        """Return Ki (n,), in the mean Kp's unit (zeros where the rows carry no integral)."""
        n = self.n
        if self.extra is None or self.extra.shape[1] < 3 * n - 1:    # PD: 2 n - 1 columns
            return np.zeros(n)
        return np.asarray(extra, dtype=float)[2 * n - 1:3 * n - 1].copy()

    @property
    def n_rows(self) -> int:
        """Return the number of rows R (each n joint equations)."""
        return self.tau.shape[0]

    def design(self, tree: Tree) -> np.ndarray:
        """Return Y's rows for the chain of ``tree``, shape (R n, P), joint-major."""
        y = kernels.regressor_rows(tree.parent, tree.col, tree.rot, tree.pos, tree.axis,
                                   tree.gravity, tree.coulomb_velocity, self.q, self.qd,
                                   self.qdd, self.columns)
        if not self.groups:
            return y
        width = self.n * self.columns.size
        parts = []
        for g in self.groups:
            block = y[g.first * self.n:(g.first + g.count * g.length) * self.n]
            block = block.reshape(g.count, g.length, width)
            parts.append(np.einsum('kl,blc->bkc', g.smoothing, block)
                         .reshape(-1, self.columns.size))
        return np.concatenate(parts)

    def torques(self, tree: Tree, parameters) -> np.ndarray:
        """Return Y's rows times ``parameters`` (P,), shape (R n,): one RNEA per state."""
        tau = kernels.inverse_dynamics(tree.parent, tree.col, tree.rot, tree.pos, tree.axis,
                                       tree.gravity, tree.coulomb_velocity,
                                       np.ascontiguousarray(parameters, dtype=float),
                                       self.q, self.qd, self.qdd)
        if not self.groups:
            return tau.reshape(-1)
        parts = []
        for g in self.groups:
            block = tau[g.first:g.first + g.count * g.length].reshape(g.count, g.length, self.n)
            parts.append(np.einsum('kl,blj->bkj', g.smoothing, block).reshape(-1))
        return np.concatenate(parts)


def torque_weights(segments: Sequence[Dataset]) -> np.ndarray:
    """Return 1 / RMS torque per joint over the segments (1 where a joint has none)."""
    tau = np.concatenate([seg.tau for seg in segments])
    rms = np.sqrt(np.mean(tau * tau, axis=0))
    return np.where(np.isfinite(rms) & (rms > 0.0), 1.0 / np.where(rms > 0.0, rms, 1.0), 1.0)


def _sigma(segments, sigma):
    return choose_sigma(segments) if sigma is None else float(sigma)


def _servo_errors(seg: Dataset) -> np.ndarray:
    """Return θd − θ, θ̇d − θ̇ and ∫(θd − θ) dt from the start of ``seg``, shape (N, n, 3)."""
    e = seg.theta_d - seg.theta
    return np.stack([e, seg.theta_d_dot - seg.theta_dot, error_integral(e, seg.dt)], axis=2)


def _torque(seg: Dataset) -> np.ndarray:
    return seg.tau if seg.tau is not None else np.zeros_like(seg.theta)


def state_rows(segments: Sequence[Dataset], count: int, rng: np.random.Generator,
               sigma: Optional[float] = None, measured_velocity: bool = False,
               servo: bool = False) -> Optional[ChainRows]:
    """
    Return ``count`` rows at random instants, states and torques filtered by one Gaussian.

    ``sigma`` (s): the Gaussian's (default :func:`~.rigid_data.choose_sigma`); θ̇ and θ̈
    from the measured θ̇ with ``measured_velocity``, else from θ; ``servo``: the servo's
    errors too, filtered as τ (the segments need θd and θ̇d). None when the segments hold
    fewer instants than ``count``.
    """
    sigma = _sigma(segments, sigma)
    parts = []
    for index, seg in enumerate(segments):
        s = max(sigma, seg.dt)
        h, d1 = gaussian_kernels(seg.dt, s)
        if seg.n_samples <= h.size:
            continue
        if measured_velocity:
            rates = [_convolve(seg.theta_dot, h), _convolve(seg.theta_dot, d1)]
        else:
            rates = [_convolve(seg.theta, d1),
                     _convolve(seg.theta, second_derivative_kernel(seg.dt, s))]
        errors = (np.stack([_convolve(x, h) for x in np.moveaxis(_servo_errors(seg), 2, 0)],
                           axis=2) if servo else np.zeros((0,)))
        q = _convolve(seg.theta, h)
        parts.append([q] + rates + [_convolve(_torque(seg), h), errors,
                                    np.full(q.shape[0], index, dtype=np.int64)])
    if not parts:
        return None
    q, qd, qdd, tau, which = (np.concatenate([p[k] for p in parts]) for k in (0, 1, 2, 3, 5))
    if q.shape[0] < count:
        return None
    index = np.sort(rng.choice(q.shape[0], size=int(count), replace=False))
    errors = np.concatenate([p[4] for p in parts])[index] if servo else None
    return ChainRows(q[index], qd[index], qdd[index], tau[index], servo=errors,
                     segment=which[index])


def block_rows(segments: Sequence[Dataset], blocks: int, per_block: int,
               rng: np.random.Generator, sigma: Optional[float] = None,
               measured_velocity: bool = False, servo: bool = False) -> Optional[ChainRows]:
    """
    Return exact filtered rows (module docstring) on about ``blocks`` random blocks.

    Each block gives ``per_block`` rows :data:`~.rigid_data.STRIDE_SIGMA` σ apart, as
    :func:`~.rigid_data.filtered_rows` keeps them; blocks are shared among the segments by
    length and never overlap; ``servo``: the servo's errors too, filtered as τ. None when
    no segment is long enough for one block.
    """
    sigma = _sigma(segments, sigma)
    prepared = []
    for index, seg in enumerate(segments):
        dt = seg.dt
        s1 = max(DERIVATIVE_SIGMA, dt)
        s = max(sigma, math.sqrt(2.0) * s1)
        _, d1 = gaussian_kernels(dt, s1)
        h, _ = gaussian_kernels(dt, math.sqrt(s * s - s1 * s1))
        m1, m2 = d1.size // 2, h.size // 2
        stride = max(1, int(round(0.5 * s / dt)))
        length = (per_block - 1) * stride + 2 * m2 + 1
        if seg.n_samples < 2 * m1 + length:
            continue
        inner = slice(m1, seg.n_samples - m1)
        if measured_velocity:
            qd, qdd = seg.theta_dot[inner], _convolve(seg.theta_dot, d1)
        else:
            qd = _convolve(seg.theta, d1)
            qdd = _convolve(seg.theta, second_derivative_kernel(dt, s1))
        signals = [_torque(seg)[inner]]
        if servo:
            errors = _servo_errors(seg)[inner]
            signals += [errors[:, :, 0], errors[:, :, 1], errors[:, :, 2]]
        prepared.append((dt, seg.theta[inner], qd, qdd, signals, h, stride, length, index))
    if not prepared:
        return None
    total = sum(p[1].shape[0] for p in prepared)
    by_dt = {}
    for dt, q, qd, qdd, tau, h, stride, length, index in prepared:
        room = q.shape[0] // length
        wanted = max(1, int(round(blocks * q.shape[0] / total)))
        # non-overlapping blocks: random slots of a grid of whole blocks, then shifted
        slots = np.sort(rng.choice(room, size=min(room, wanted), replace=False))
        spare = q.shape[0] - room * length
        starts = slots * length + np.sort(rng.integers(0, spare + 1, slots.size))
        key = (round(dt, 12), length, stride)
        entry = by_dt.setdefault(key, {'h': h, 'states': [], 'tau': [], 'segment': []})
        for start in starts:
            part = slice(start, start + length)
            entry['states'].append((q[part], qd[part], qdd[part]))
            entry['segment'].append(index)
            entry['tau'].append(np.stack([_convolve(x[part], h)[::stride][:per_block]
                                          for x in tau], axis=2))
    states, taus, groups, which = [], [], [], []
    for (_, length, stride), entry in by_dt.items():
        h = entry['h']
        m2 = h.size // 2
        filt = np.zeros((per_block, length))
        for k in range(per_block):
            filt[k, k * stride:k * stride + 2 * m2 + 1] = h[::-1]
        first = sum(len(s[0]) for s in states)
        groups.append(_Group(first, len(entry['states']), length, filt))
        states += entry['states']
        taus += entry['tau']
        which += [np.full(per_block, index, dtype=np.int64) for index in entry['segment']]
    q, qd, qdd = (np.concatenate([s[k] for s in states]) for k in range(3))
    signals = np.concatenate(taus)
    return ChainRows(q, qd, qdd, signals[:, :, 0], groups,
                     signals[:, :, 1:] if servo else None, segment=np.concatenate(which))


class ChainScore:
    """
    The variable projection of a chain on rows (module docstring).

    Parameters
    ----------
    rows : ChainRows
        Where the chain is evaluated.
    weights : ndarray, shape (n,)
        Each joint's row weight (1 / its RMS torque).

    """

    def __init__(self, rows: ChainRows, weights):
        self.rows = rows
        self.weights = np.asarray(weights, dtype=float).reshape(-1)
        self._w = np.tile(self.weights, rows.n_rows)
        self.target = (rows.tau * self.weights).reshape(-1)
        self.norm = max(float(np.linalg.norm(self.target)), 1e-300)
        self.evaluations = 0

    def _solve(self, tree: Tree):
        """Return (A scaled, column scales, Cholesky factor, β, residual) of a chain."""
        import scipy.linalg
        self.evaluations += 1
        a = self.rows.design(tree)
        if self.rows.extra is not None:
            a = np.hstack([a, self.rows.extra])
        a = a * self._w[:, None]
        scale = np.sqrt(np.sum(a * a, axis=0))
        scale[~(scale > 0.0)] = 1.0
        a /= scale
        normal = a.T @ a
        normal[np.diag_indices_from(normal)] += RIDGE * np.trace(normal) / normal.shape[0]
        factor = scipy.linalg.cho_factor(normal, check_finite=False)
        beta = scipy.linalg.cho_solve(factor, a.T @ self.target, check_finite=False)
        return a, scale, factor, beta, (a @ beta - self.target) / self.norm

    def residual(self, tree: Tree) -> np.ndarray:
        """Return the chain's relative residual, shape (R n,), at its best parameters."""
        if not _finite_tree(tree):
            return np.full(self.target.size, 1.0 / math.sqrt(self.target.size))
        return self._solve(tree)[4]

    def cost(self, tree: Tree) -> float:
        """Return the unexplained share of the weighted torque, ‖r‖² (0 ... 1)."""
        r = self.residual(tree)
        return float(r @ r)

    def parameters(self, tree: Tree) -> np.ndarray:
        """Return the chain's least-squares parameters, shape (P,) (no consistency)."""
        _, scale, _, beta, _ = self._solve(tree)
        return (beta / scale)[:self.rows.columns.size]

    def extra(self, tree: Tree) -> np.ndarray:
        """Return the least-squares coefficients of the rows' extra columns, shape (E,)."""
        _, scale, _, beta, _ = self._solve(tree)
        return (beta / scale)[self.rows.columns.size:]

    def jacobian(self, tree_of: Callable[[np.ndarray], Tree], x: np.ndarray,
                 step: float = 1e-6):
        """
        Return (residual (R n,), Kaufman's Jacobian (R n, N)) at ``x`` of ``tree_of(x)``.

        Forward differences of the rows with step ``step`` in x's units.
        """
        import scipy.linalg
        x = np.asarray(x, dtype=float)
        a, scale, factor, beta, r = self._solve(tree_of(x))
        jac = np.empty((r.size, x.size))
        parameters = (beta / scale)[:self.rows.columns.size]   # the extra columns stay
        here = self.rows.torques(tree_of(x), parameters)
        for k in range(x.size):
            moved = x.copy()
            moved[k] += step
            jac[:, k] = (self.rows.torques(tree_of(moved), parameters) - here) * self._w / step
        # P⊥ (∂A β): what the parameters themselves cannot follow
        jac -= a @ scipy.linalg.cho_solve(factor, a.T @ jac, check_finite=False)
        return r, jac / self.norm


def _finite_tree(tree: Tree) -> bool:
    return bool(np.all(np.isfinite(tree.rot)) and np.all(np.isfinite(tree.pos))
                and np.all(np.isfinite(tree.gravity)))

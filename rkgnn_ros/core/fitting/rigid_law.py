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
A servo's gravity compensation on the arm's own gravity regressor.

A servo that compensates gravity adds Ĝ(θ) = Y_g(θ) ρ̂: the gravity of some set of masses
and first moments on the same kinematics (its own nominal model). With the robot
description known, that is the whole family: :class:`GravityFeatures` are the independent
columns of G's regressor (a dozen or so for a 6- or 7-joint arm, where products of
trigonometric features number 3^n), a different feature row per joint, one weight vector
ρ shared by all joints. :func:`fit_gravity_law` fits the law
τ = Kp e + Kd ė [+ Ki ∫e] + c + Y_g(θ or θd) ρ by one least squares over all joints (each
joint's rows divided by its RMS torque), with the filter and the saturation rule of
:func:`~.controller.fit_controller`; it returns a
:class:`~.controller_laws.ControllerLaw` whose ``theta_weights`` repeat ρ on every row.
"""

from typing import Optional, Sequence, Union

import numpy as np

from .controller import _filtered_segments, _segments
from .controller_laws import ControllerLaw, DEFAULT_FILTER_SIGMA, THETA_INPUTS
from ..data import Dataset
from ..rigid.kernels import N_INERTIAL
from ..rigid.structure import RigidStructure

__all__ = ['GravityFeatures', 'fit_gravity_law']


class GravityFeatures:
    """
    The independent columns of an arm's gravity regressor: φ(θ) of shape (..., n, F).

    ``per_joint``: joint i's torque is φ(θ)[i] · W[i] (a law's ``theta_weights`` W
    (n, F) repeat one ρ).
    """

    per_joint = True

    #: Random configurations the independent columns are chosen on, per column.
    STATES_PER_COLUMN = 4

    def __init__(self, structure: RigidStructure, seed: int = 0):
        import scipy.linalg
        self.structure = structure
        n = structure.n_joints
        inertial = np.array([N_INERTIAL * b + k for b in range(n) for k in range(4)])
        rng = np.random.default_rng(seed)
        count = max(20, self.STATES_PER_COLUMN * inertial.size)
        theta, _, _ = structure.random_states(count, rng)
        zeros = np.zeros_like(theta)
        rows = structure.rows(theta, zeros, zeros, inertial)
        scale = np.sqrt(np.mean(rows * rows, axis=0))
        used = scale > 1e-12 * max(float(scale.max()), 1e-300)
        if not np.any(used):
            self.columns = np.zeros(0, dtype=np.int64)
            return
        _, r, pivots = scipy.linalg.qr(rows[:, used] / scale[used], mode='economic',
                                       pivoting=True)
        diag = np.abs(np.diag(r))
        rank = int(np.sum(diag > 1e-8 * diag[0]))
        #: the full-parameter columns kept (mass and first moments only)
        self.columns = np.sort(inertial[used][pivots[:rank]])

    @property
    def size(self) -> int:
        """Return the number of features F."""
        return int(self.columns.size)

    def __call__(self, theta) -> np.ndarray:
        """Return φ(θ): ``theta`` (..., n) -> (..., n, F)."""
        theta = np.asarray(theta, dtype=float)
        n = self.structure.n_joints
        if theta.shape[-1] != n:
            raise ValueError(f'theta must have {n} columns, got {theta.shape}')
        flat = theta.reshape(-1, n)
        zeros = np.zeros_like(flat)
        rows = self.structure.rows(flat, zeros, zeros, self.columns)
        return rows.reshape(theta.shape[:-1] + (n, self.size))

    def full(self, weights) -> np.ndarray:
        """Return the full parameter vector whose gravity is φ(θ) ρ for ``weights`` ρ (F,)."""
        out = np.zeros(self.structure.n_parameters)
        out[self.columns] = np.asarray(weights, dtype=float).reshape(-1)
        return out

    def same_as(self, other) -> bool:
        """Return whether ``other`` is the same features (same structure and columns)."""
        return (isinstance(other, GravityFeatures) and other.structure is self.structure
                and np.array_equal(other.columns, self.columns))


def _filter(x: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    flat = x.reshape(x.shape[0], -1)
    out = np.stack([np.convolve(flat[:, j], kernel, 'valid') for j in range(flat.shape[1])], 1)
    return out.reshape((out.shape[0],) + x.shape[1:])


def _fit_one(segments, features: GravityFeatures, theta_input: str, integral: bool,
             sigma: float, min_samples: int) -> Optional[ControllerLaw]:
    sigma, h, h_prime, m, limit, used = _filtered_segments(segments, sigma)
    if not used:
        return None
    n = segments[0].n_joints
    window = np.ones(2 * m + 1)
    blocks = []
    for k, (seg, s) in enumerate(used):
        e = seg.theta_d - seg.theta
        theta_dot = _filter(seg.theta, h_prime)
        block = {'e': _filter(e, h), 'e_dot': _filter(seg.theta_d_dot, h) - theta_dot,
                 'tau': _filter(seg.tau, h),
                 'phi': (_filter(features(seg.theta if theta_input == 'measured'
                                          else seg.theta_d), h) if features.size
                         else np.zeros((seg.n_samples - 2 * m, n, 0))),
                 'blocked': np.stack([np.convolve(s[:, j].astype(float), window, 'valid') > 0
                                      for j in range(n)], 1)}
        if integral:
            z = np.zeros_like(e)
            z[1:] = np.cumsum(0.5 * (e[1:] + e[:-1]), axis=0) * seg.dt
            block['z'], block['z_end'] = _filter(z, h), z[-1]
        blocks.append(block)
    total = sum(b['e'].shape[0] for b in blocks)
    if total < max(int(min_samples), 3):
        return None
    n_seg = len(blocks) if integral else 1
    n_f = features.size
    per_joint = 3 + (1 if integral else 0) + (n_seg - 1)
    # columns: per joint [Kp, Kd, (Ki), c (one per segment with an integral)], then ρ
    width = n * per_joint + n_f
    rows, target, which = [], [], []
    tau_all = np.concatenate([b['tau'] for b in blocks])
    rms = np.sqrt(np.mean(tau_all ** 2, axis=0))
    rms = np.where(rms > 0.0, rms, 1.0)
    for k, b in enumerate(blocks):
        count = b['e'].shape[0]
        for j in range(n):
            keep = ~b['blocked'][:, j]
            a = np.zeros((count, width))
            o = j * per_joint
            a[:, o], a[:, o + 1] = b['e'][:, j], b['e_dot'][:, j]
            c = o + 2
            if integral:
                a[:, c] = b['z'][:, j]
                c += 1
            a[:, c + (k if integral else 0)] = 1.0
            a[:, n * per_joint:] = b['phi'][:, j, :]
            rows.append(a[keep] / rms[j])
            target.append(b['tau'][keep, j] / rms[j])
            which.append(np.full(int(keep.sum()), j))
    a = np.vstack(rows)
    y = np.concatenate(target)
    if a.shape[0] < max(int(min_samples), 3):
        return None
    scale = np.sqrt(np.mean(a * a, axis=0))
    gains = np.concatenate([[j * per_joint, j * per_joint + 1] for j in range(n)])
    if np.any(scale[gains] == 0.0):
        return None              # an error that never varied: the gains are not identifiable
    scale[scale == 0.0] = 1.0
    coef, _, _, sv = np.linalg.lstsq(a / scale, y, rcond=1e-10)
    if sv[-1] < 1e-10 * sv[0]:
        core = np.linalg.svd(a[:, gains] / scale[gains], compute_uv=False)
        if core[-1] < 1e-8 * core[0]:
            return None
    coef = coef / scale
    residual = y - a @ coef
    which = np.concatenate(which)
    ratio = np.array([np.sqrt(np.mean(residual[which == j] ** 2)) if np.any(which == j)
                      else np.inf for j in range(n)])
    kp, kd, ki, bias = (np.zeros(n) for _ in range(4))
    for j in range(n):
        o = j * per_joint
        kp[j], kd[j] = coef[o], coef[o + 1]
        c = o + 2
        if integral:
            ki[j] = coef[c]
            c += 1
        bias[j] = coef[c + (n_seg - 1 if integral else 0)]      # the newest segment's constant
    rho = coef[n * per_joint:]
    integral_term = ki * blocks[-1]['z_end'] if integral else np.zeros(n)
    samples = int(sum(seg.n_samples for seg, _ in used))
    return ControllerLaw(kp=kp, kd=kd, ki=ki, bias=bias, integral_term=integral_term,
                         feedforward=np.zeros(n), theta_weights=np.tile(rho, (n, 1)),
                         theta_input=theta_input, features=features, fit_ratio=ratio,
                         samples=samples, tau_limit=limit, filter_sigma=float(sigma))


def fit_gravity_law(data: Union[Dataset, Sequence[Dataset]], features: GravityFeatures,
                    theta_input: str = 'auto', integral: bool = False,
                    filter_sigma: float = DEFAULT_FILTER_SIGMA,
                    min_samples: int = 50) -> Optional[ControllerLaw]:
    """
    Fit τ = Kp e + Kd ė [+ Ki ∫e] + c + Y_g ρ on measured torque and commands.

    As :func:`~.controller.fit_controller` with ``features`` of a robot description: one
    ρ for all joints. ``theta_input`` 'auto' fits both places of the θ-terms (θ, θd) and
    keeps the smaller residual. None with too few samples or an error that never varied.
    """
    segments = _segments(data)
    if theta_input not in THETA_INPUTS + ('auto',):
        raise ValueError(f"theta_input must be 'auto' or one of {THETA_INPUTS}, "
                         f'got {theta_input!r}')
    inputs = THETA_INPUTS if theta_input == 'auto' else (theta_input,)
    best = None
    for where in inputs:
        law = _fit_one(segments, features, where, integral, filter_sigma, min_samples)
        if law is not None and (best is None
                                or np.mean(law.fit_ratio) < np.mean(best.fit_ratio)):
            best = law
    return best

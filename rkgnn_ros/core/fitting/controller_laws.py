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
The laws of an arm's own controller: what a fitted servo law is and how it acts.

:class:`PDLaw` is the pure PD τ = Kp e + Kd ė + c; :class:`ControllerLaw` the general law
a real servo runs (integral, constant, θ-terms such as a gravity compensation, velocity
feed-forward), its θ-terms on a basis: the arm model's own RBF units
(:class:`RBFFeatures`, so that they fold into the model exactly) or the global
:class:`TrigFeatures`. Fitting them from measured torque is
:mod:`rkgnn_ros.core.fitting.controller`; the records here only hold and evaluate them.
"""

from dataclasses import dataclass, field, replace
import math
from typing import Optional

import numpy as np

from .policy import KD_AGREEMENT_S, KI_AGREEMENT_PER_S
from ..model.model import RKGNNModel
from ..servo_law import pd_torque

__all__ = ['ControllerLaw', 'DEFAULT_FILTER_SIGMA', 'gains_agree', 'PDLaw', 'RBFFeatures',
           'THETA_INPUTS', 'TrigFeatures']

#: Default standard deviation (s) of the Gaussian filter of :func:`fit_controller`: it
#: passes the motion of an arm (gain 0.98 at 1 Hz, 0.64 at 5 Hz) and removes the noise of
#: differenced encoders (at 100 Hz, 1e-4 rad of θ noise leaves 7e-4 rad/s on h′ * θ).
DEFAULT_FILTER_SIGMA = 0.03

#: Where the θ-dependent terms of :class:`ControllerLaw` are evaluated.
THETA_INPUTS = ('measured', 'desired')


def gains_agree(kp, kd, kp_other, kd_other, rtol: float) -> bool:
    """
    Return whether the gains ``kp_other``, ``kd_other`` are ``kp``, ``kd`` within ``rtol``.

    Kp within ``rtol * |Kp|``; Kd within ``rtol * (|Kd| + KD_AGREEMENT_S * |Kp|)``
    (:data:`~.policy.KD_AGREEMENT_S`, 0.1 s): a small derivative gain is noisy relative to
    itself but matters little against Kp. Per joint, every joint must agree.
    """
    kp_ok = np.abs(kp_other - kp) <= rtol * np.abs(kp)
    kd_ok = np.abs(kd_other - kd) <= rtol * (np.abs(kd) + KD_AGREEMENT_S * np.abs(kp))
    return bool(np.all(kp_ok) and np.all(kd_ok))


@dataclass(frozen=True)
class PDLaw:
    """
    A fitted joint-space PD law τ = Kp e + Kd ė + c (diagonal gains).

    Attributes
    ----------
    kp, kd, bias : ndarray, shape (n,)
        Gains and constant torque per joint.
    fit_ratio : ndarray, shape (n,)
        RMS residual / RMS torque per joint (0 is a perfect fit).
    samples : int
        Samples the fit used.

    """

    kp: np.ndarray
    kd: np.ndarray
    bias: np.ndarray
    fit_ratio: np.ndarray
    samples: int

    def torque(self, theta, theta_dot, theta_d, theta_d_dot) -> np.ndarray:
        """Return the law's torque for states and commands of shape (..., n)."""
        e = np.asarray(theta_d) - np.asarray(theta)
        e_dot = np.asarray(theta_d_dot) - np.asarray(theta_dot)
        return pd_torque(self.kp, self.kd, e, e_dot) + self.bias

    def usable(self, max_fit_ratio: float = 0.2, min_gain: float = 1e-6) -> bool:
        """Return whether the law explains the torque of every joint and Kp > 0."""
        return bool(np.all(self.fit_ratio <= max_fit_ratio) and np.all(self.kp > min_gain)
                    and np.all(self.kd >= 0.0))

    def shift(self) -> np.ndarray:
        """Return c / Kp, the offset that folds the constant into θd (shape (n,))."""
        return self.bias / self.kp

    def close_to(self, other: Optional['PDLaw'], rtol: float = 0.1) -> bool:
        """
        Return whether ``other`` has the same gains within ``rtol``.

        As :func:`gains_agree` says (the paper's Kd of 0.19 is noisy relative to itself but
        matters little against Kp).
        """
        if other is None or other.kp.shape != self.kp.shape:
            return False
        return gains_agree(self.kp, self.kd, other.kp, other.kd, rtol)

    def to_dict(self) -> dict:
        """Return plain lists (for a model's ``info``)."""
        return {'kp': self.kp.tolist(), 'kd': self.kd.tolist(), 'bias': self.bias.tolist(),
                'fit_ratio': self.fit_ratio.tolist(), 'samples': self.samples}


class RBFFeatures:
    """
    The θ-features of an arm model with Gaussian RBF units: φ_l(θ) = exp(−|θ − c_l|² / s_l²).

    A controller term W φ(θ) on these features is a term the model's gravity output can
    hold exactly (its constant is handled as a command shift, see :func:`closed_loop`).

    Parameters
    ----------
    centres : array_like, shape (K, n)
        Unit centres (rad).
    inv_width2 : array_like, shape (K,)
        1 / s_l².

    """

    def __init__(self, centres, inv_width2):
        self.centres = np.array(centres, dtype=float, ndmin=2)
        self.inv_width2 = np.array(inv_width2, dtype=float).reshape(-1)
        if self.inv_width2.size != self.centres.shape[0]:
            raise ValueError(f'{self.centres.shape[0]} centres but {self.inv_width2.size} '
                             'widths')

    @classmethod
    def from_model(cls, model: RKGNNModel) -> 'RBFFeatures':
        """Return the θ-features of ``model`` (its decoded centres and widths)."""
        if model.spec.basis != 'rbf':
            raise ValueError(f"the model's basis is {model.spec.basis!r}: RBF units come from "
                             "a network of the 'rbf' basis")
        features = model.spec.decode(model.genome[None], model.scales).features[0]   # (K, n + 1)
        n = model.n_joints
        return cls(features[:, :n], features[:, n])

    @property
    def size(self) -> int:
        """Return the number of features F."""
        return self.inv_width2.size

    def __call__(self, theta) -> np.ndarray:
        """Return φ(θ): ``theta`` shape (..., n) -> (..., F)."""
        theta = np.asarray(theta, dtype=float)
        d2 = np.sum(np.square(theta[..., None, :] - self.centres), axis=-1)
        return np.exp(-d2 * self.inv_width2)

    def same_as(self, other: 'RBFFeatures') -> bool:
        """Return whether ``other`` has the same units (to rounding)."""
        return (isinstance(other, RBFFeatures) and other.centres.shape == self.centres.shape
                and np.allclose(other.centres, self.centres, rtol=1e-12, atol=1e-12)
                and np.allclose(other.inv_width2, self.inv_width2, rtol=1e-12, atol=0.0))


class TrigFeatures:
    """
    A global θ-basis for the terms a servo adds: products of (1, cos θ_k, sin θ_k).

    The potential energy of any serial arm of revolute joints is a polynomial of degree at
    most 1 in each (cos θ_k, sin θ_k), and so is its gravity vector G = ∂U/∂θ: a gravity
    compensation Ĝ(θ) is exactly a linear combination of these products. Every product of
    at most ``max_factors`` non-constant factors is a feature (the constant is left out: the
    law has its own): 3^n − 1 features when ``max_factors >= n`` (26 for 3 joints).

    Parameters
    ----------
    n_joints : int
        Number of joints n.
    max_factors : int
        Most joints one product involves (limits the count for 6 or 7 joints).

    """

    def __init__(self, n_joints: int, max_factors: int = 3):
        if int(n_joints) < 1 or int(max_factors) < 1:
            raise ValueError('n_joints and max_factors must be >= 1')
        self.n_joints = int(n_joints)
        self.max_factors = int(max_factors)
        terms = [()]
        for k in range(self.n_joints):
            terms = terms + [t + ((k, kind),) for t in terms if len(t) < self.max_factors
                             for kind in (0, 1)]
        #: each feature: tuple of (joint, 0 = cos | 1 = sin)
        self.terms = [t for t in terms if t]
        # the features as one gather and product: column 2 k + kind of [cos θ_0, sin θ_0,
        # cos θ_1, ..., 1], the last (1) padding the shorter products
        width = max((len(t) for t in self.terms), default=1)
        self._index = np.full((len(self.terms), width), 2 * self.n_joints, dtype=np.intp)
        for f, term in enumerate(self.terms):
            for j, (joint, kind) in enumerate(term):
                self._index[f, j] = 2 * joint + kind

    @property
    def size(self) -> int:
        """Return the number of features F."""
        return len(self.terms)

    def __call__(self, theta) -> np.ndarray:
        """Return the features: ``theta`` shape (..., n) -> (..., F)."""
        theta = np.asarray(theta, dtype=float)
        if theta.shape[-1] != self.n_joints:
            raise ValueError(f'theta must have {self.n_joints} columns, got {theta.shape}')
        trig = np.empty(theta.shape[:-1] + (2 * self.n_joints + 1,))
        trig[..., 0:-1:2] = np.cos(theta)
        trig[..., 1:-1:2] = np.sin(theta)
        trig[..., -1] = 1.0
        return trig[..., self._index].prod(axis=-1)


@dataclass(frozen=True)
class ControllerLaw:
    """
    A fitted servo law, τ = Kp e + Kd ė + Ki ∫e + c + W φ(θ or θd) + K_v θ̇d (diagonal).

    Attributes
    ----------
    kp, kd, ki : ndarray, shape (n,)
        Gains (``ki`` zeros when no integral was fitted).
    bias : ndarray, shape (n,)
        Constant torque c; with an integral term, the integral's value at the start of the
        fitted data is part of it.
    integral_term : ndarray, shape (n,)
        Ki ∫e from the start to the end of the fitted data: c + integral_term is the
        constant the integral contributes now (held over a prediction).
    feedforward : ndarray, shape (n,)
        K_v, the gain on θ̇d (zeros unless fitted).
    theta_weights : ndarray, shape (n, F)
        W, per joint, on ``features`` (F = 0 without).
    theta_input : {'measured', 'desired'}
        Whether φ is evaluated at θ or at θd.
    features : callable or None
        The θ-basis, ``features(θ) -> (..., F)`` (:class:`TrigFeatures`,
        :class:`RBFFeatures`), or ``(..., n, F)``, a row per joint, when it has
        ``per_joint`` set (:class:`~.rigid_law.GravityFeatures`).
    fit_ratio : ndarray, shape (n,)
        RMS residual / RMS torque per joint, on the filtered data.
    samples : int
        Samples the fit used.
    tau_limit : ndarray, shape (n,)
        Saturation level seen in the data (``inf``: none).
    filter_sigma : float
        The filter the law was fitted with (s).

    """

    kp: np.ndarray
    kd: np.ndarray
    ki: np.ndarray
    bias: np.ndarray
    integral_term: np.ndarray
    feedforward: np.ndarray
    theta_weights: np.ndarray
    theta_input: str
    features: Optional[RBFFeatures]
    fit_ratio: np.ndarray
    samples: int
    tau_limit: np.ndarray = field(default=None)
    filter_sigma: float = DEFAULT_FILTER_SIGMA

    def __post_init__(self):
        if self.tau_limit is None:
            object.__setattr__(self, 'tau_limit', np.full(self.kp.shape, np.inf))

    @property
    def n_joints(self) -> int:
        """Return the number of joints n."""
        return self.kp.size

    def describe(self) -> str:
        """Return the law's form, e.g. 'PID + θ-terms (measured)'."""
        # an integral gain below 0.1 % of Kp (1/s) is a fitted zero
        kind = 'PID' if np.any(np.abs(self.ki) > 1e-3 * np.abs(self.kp)) else 'PD'
        if self.theta_weights.size:
            kind += f' + θ-terms ({self.theta_input})'
        if np.any(self.feedforward != 0.0):
            kind += ' + velocity feed-forward'
        return kind

    def _theta_terms(self, theta, theta_d) -> np.ndarray:
        at = np.asarray(theta if self.theta_input == 'measured' else theta_d, dtype=float)
        if not self.theta_weights.size:
            return np.zeros(at.shape)
        if getattr(self.features, 'per_joint', False):   # φ (..., n, F): a row per joint
            return np.einsum('...if,if->...i', self.features(at), self.theta_weights)
        return np.einsum('...f,if->...i', self.features(at), self.theta_weights)

    def torque(self, theta, theta_dot, theta_d, theta_d_dot, integral_term=None) -> np.ndarray:
        """
        Return the law's torque, shape (..., n), saturated at ``tau_limit``.

        ``integral_term`` (..., n) is Ki ∫e since the start of the fitted data; default
        the held value :attr:`integral_term`. So the law is a controller for
        :func:`rkgnn_ros.core.sim.simulate.simulate`.
        """
        theta_d = np.asarray(theta_d, dtype=float)
        theta_d_dot = np.asarray(theta_d_dot, dtype=float)
        held = self.integral_term if integral_term is None else integral_term
        tau = (pd_torque(self.kp, self.kd, theta_d - theta, theta_d_dot - theta_dot)
               + self.bias + held + self.feedforward * theta_d_dot
               + self._theta_terms(theta, theta_d))
        return np.clip(tau, -self.tau_limit, self.tau_limit)

    __call__ = torque

    def shift(self, theta_d=None, theta_d_dot=None, integral_term=None) -> np.ndarray:
        """
        Return what the law adds to θd when its command-only terms are folded in (…, n).

        Kp (θd' − θ) = Kp (θd − θ) + c + I + K_v θ̇d [+ W φ(θd)]: θd' = θd + this. Needs
        ``theta_d`` when φ is on θd and ``theta_d_dot`` when K_v is fitted.
        """
        offset = self.bias + (self.integral_term if integral_term is None else integral_term)
        if np.any(self.feedforward != 0.0):
            if theta_d_dot is None:
                raise ValueError('this law has a velocity feed-forward: give theta_d_dot')
            offset = offset + self.feedforward * np.asarray(theta_d_dot, dtype=float)
        if self.theta_input == 'desired' and self.theta_weights.size:
            if theta_d is None:
                raise ValueError('this law has θ-terms on θd: give theta_d')
            offset = offset + self._theta_terms(None, theta_d)
        return offset / self.kp

    def usable(self, max_fit_ratio: float = 0.2, min_gain: float = 1e-6) -> bool:
        """Return whether the law explains every joint's torque, Kp > 0 and Kd >= 0."""
        return bool(np.all(self.fit_ratio <= max_fit_ratio) and np.all(self.kp > min_gain)
                    and np.all(self.kd >= 0.0))

    def close_to(self, other: Optional['ControllerLaw'], rtol: float = 0.1) -> bool:
        """Return whether ``other`` has the same gains within ``rtol`` (see :class:`PDLaw`)."""
        if other is None or other.kp.shape != self.kp.shape:
            return False
        scale_i = np.abs(self.ki) + KI_AGREEMENT_PER_S * np.abs(self.kp)
        return bool(PDLaw.close_to(self, other, rtol)
                    and np.all(np.abs(other.ki - self.ki) <= rtol * scale_i))

    def advance_integral(self, theta, theta_d, dt: float) -> 'ControllerLaw':
        """Return the law with Ki ∫e extended over new samples (K, n) at interval ``dt``."""
        e = np.asarray(theta_d, dtype=float) - np.asarray(theta, dtype=float)
        return replace(self, integral_term=self.integral_term + self.ki * np.sum(e, 0) * dt)

    def to_dict(self) -> dict:
        """Return plain values (for a model's ``info`` and logs)."""
        return {'form': self.describe(), 'kp': self.kp.tolist(), 'kd': self.kd.tolist(),
                'ki': self.ki.tolist(), 'bias': self.bias.tolist(),
                'integral_term': self.integral_term.tolist(),
                'feedforward': self.feedforward.tolist(),
                'theta_input': self.theta_input,
                'theta_features': int(self.theta_weights.shape[1]),
                'fit_ratio': self.fit_ratio.tolist(), 'samples': self.samples,
                'tau_limit': [None if not math.isfinite(v) else v for v in self.tau_limit],
                'filter_sigma': self.filter_sigma}

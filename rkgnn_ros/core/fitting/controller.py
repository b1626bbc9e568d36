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
The arm's own controller, estimated from measured torque: τ ≈ Kp (θd − θ) + Kd (θ̇d − θ̇) + c.

In case 1 the applied torque is measured, so a model of the arm alone predicts the future
only if the future torque is known. When the arm is servoed to a commanded trajectory, the
torque it will apply is the controller's answer to the state it will reach: fitting the
controller's law from the buffered torque and command streams lets the case-1 model be
rolled out in closed loop along the planned reference, exactly like case 2 with gains that
were measured instead of given.

The law is fitted per joint by linear least squares on [e, ė, 1] (a diagonal PD plus a
constant torque), and accepted only when it explains the torque well (``fit_ratio``: RMS
residual over RMS torque). The constant is folded into the desired position,
θd' = θd + c / Kp, so the closed-loop model is a plain case-2 model.
"""

from dataclasses import dataclass, replace
from typing import Optional

import numpy as np

from .identify import RKGNNModel

__all__ = ['PDLaw', 'fit_pd_law', 'closed_loop_model', 'open_loop_model']


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
        return self.kp * e + self.kd * e_dot + self.bias

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

        Kd is compared with ``rtol * (|Kd| + 0.1 s * |Kp|)``: a small derivative gain (the
        paper's 0.19) is noisy relative to itself but matters little against Kp.
        """
        if other is None or other.kp.shape != self.kp.shape:
            return False
        kp_ok = np.abs(other.kp - self.kp) <= rtol * np.abs(self.kp)
        kd_ok = np.abs(other.kd - self.kd) <= rtol * (np.abs(self.kd) + 0.1 * np.abs(self.kp))
        return bool(np.all(kp_ok) and np.all(kd_ok))

    def to_dict(self) -> dict:
        """Return plain lists (for a model's ``info``)."""
        return {'kp': self.kp.tolist(), 'kd': self.kd.tolist(), 'bias': self.bias.tolist(),
                'fit_ratio': self.fit_ratio.tolist(), 'samples': self.samples}


def fit_pd_law(theta, theta_dot, tau, theta_d, theta_d_dot,
               min_samples: int = 20) -> Optional[PDLaw]:
    """
    Fit τ_i = kp_i e_i + kd_i ė_i + c_i per joint by least squares.

    Parameters
    ----------
    theta, theta_dot, tau, theta_d, theta_d_dot : array_like, shape (K, n)
        Paired samples: measured state, applied torque, commanded state.
    min_samples : int
        Fewer finite samples than this give None.

    Returns
    -------
    PDLaw or None
        None when there are too few samples or a joint's regressors are degenerate (the
        error never varied, so the gains are not identifiable).

    """
    inputs = (theta, theta_dot, tau, theta_d, theta_d_dot)
    arrays = [np.asarray(a, dtype=float) for a in inputs]
    shape = arrays[0].shape
    if len(shape) != 2 or any(a.shape != shape for a in arrays):
        raise ValueError(f'all inputs must have the same shape (K, n), got '
                         f'{[a.shape for a in arrays]}')
    theta, theta_dot, tau, theta_d, theta_d_dot = arrays
    finite = np.all([np.isfinite(a).all(axis=1) for a in arrays], axis=0)
    if int(finite.sum()) < max(int(min_samples), 3):
        return None
    e = (theta_d - theta)[finite]
    e_dot = (theta_d_dot - theta_dot)[finite]
    tau = tau[finite]
    n = shape[1]
    kp, kd, bias, ratio = (np.empty(n) for _ in range(4))
    for i in range(n):
        a = np.column_stack([e[:, i], e_dot[:, i], np.ones(e.shape[0])])
        scale = np.sqrt(np.mean(a * a, axis=0))
        scale[scale == 0.0] = 1.0
        coef, _, rank, sv = np.linalg.lstsq(a / scale, tau[:, i], rcond=None)
        if rank < 3 or sv[-1] < 1e-8 * sv[0]:
            return None
        coef = coef / scale
        residual = tau[:, i] - a @ coef
        rms_tau = np.sqrt(np.mean(tau[:, i] ** 2))
        kp[i], kd[i], bias[i] = coef
        ratio[i] = np.sqrt(np.mean(residual ** 2)) / rms_tau if rms_tau > 0 else np.inf
    return PDLaw(kp, kd, bias, ratio, int(finite.sum()))


def closed_loop_model(model: RKGNNModel, law: PDLaw) -> RKGNNModel:
    """
    Return the case-1 ``model`` closed with the fitted ``law``, as a case-2 model.

    Its inputs are the commanded θd + ``law.shift()`` and θ̇d. The genome is shared: a
    case-1 and a case-2 network have the same layout.
    """
    if model.case != 'torque':
        raise ValueError(f"closed_loop_model needs a case 'torque' model, got {model.case!r}")
    if law.kp.shape != (model.n_joints,):
        raise ValueError(f'the law is for {law.kp.size} joints, the model has '
                         f'{model.n_joints}')
    spec = replace(model.spec, case='pd_gains')
    return RKGNNModel(spec, model.scales, model.genome, joint_names=model.joint_names,
                      kp=law.kp, kd=law.kd, dt=model.dt, substeps=model.substeps,
                      info=dict(model.info, closed_loop='fitted PD law'))


def open_loop_model(model: RKGNNModel, info=None) -> RKGNNModel:
    """
    Return the arm model of a closed-loop (case-2) ``model`` as a case-1 model.

    The inverse of :func:`closed_loop_model`: same genome, torque as the input. ``info``
    replaces the model's info when given.
    """
    if model.case != 'pd_gains':
        raise ValueError(f"open_loop_model needs a case 'pd_gains' model, got {model.case!r}")
    spec = replace(model.spec, case='torque')
    return RKGNNModel(spec, model.scales, model.genome, joint_names=model.joint_names,
                      dt=model.dt, substeps=model.substeps,
                      info=dict(model.info if info is None else info))

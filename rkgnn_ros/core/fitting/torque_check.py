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
The held-out torque check: a model's inverse dynamics against the torque it is judged by.

On validation samples (data the fit did not use) a model's torque at the measured state,
M(θ) θ̈ + V + G + F, is compared with the torque: measured (case 1, and case 3 when the
samples carry it), the known PD law (case 2), or the identified controller's torque times
the torque scale (case 3 otherwise). θ̈ is the lag-free Savitzky–Golay derivative of θ̇
(:func:`~rkgnn_ros.core.differentiate.centred_derivative`); half a window at each end of a
segment, where that derivative is one-sided and noisier, is left out. The error is per
joint, RMSE / std of that joint's torque (:func:`torque_error`). The feed-forward's gate
(:mod:`rkgnn_ros.core.control.gate`) and the loops the fitting keeps
(:mod:`.trig_loop`) judge a model by it.
"""

import math
from typing import Optional, Sequence, Tuple

import numpy as np

from ..data import Dataset
from ..differentiate import centred_derivative, CENTRED_ORDER, CENTRED_WINDOW
from ..servo_law import pd_torque

__all__ = ['model_case', 'paired_torques', 'STD_FLOOR', 'torque_error',
           'torque_scale_from_effort']

#: A joint's torque std is floored at this fraction of the largest joint's.
STD_FLOOR = 0.01


def model_case(model) -> Tuple[str, Optional[np.ndarray], Optional[np.ndarray]]:
    """
    Return a model's identification case and known gains: ``(case, kp, kd)``.

    An :class:`~rkgnn_ros.core.fitting.identify.RKGNNModel` says them as ``case``, ``kp``,
    ``kd``, a fitted :class:`~rkgnn_ros.core.fitting.linear.LinearDynamics` as ``case_``,
    ``kp_``, ``kd_``; a model with neither (the simulated arm) is taken as case 1.
    """
    case = getattr(model, 'case', None) or getattr(model, 'case_', None) or 'torque'
    gains = []
    for name in ('kp', 'kd'):
        value = getattr(model, name, None)
        gains.append(getattr(model, name + '_', None) if value is None else value)
    return case, gains[0], gains[1]


def _trimmed(data: Dataset) -> Tuple[slice, np.ndarray]:
    """Return the rows kept and θ̈ (rows, n) of one segment; an empty slice if too short."""
    if data.n_samples < CENTRED_ORDER + 2:
        return slice(0, 0), np.empty((0, data.n_joints))
    acc = centred_derivative(data.theta_dot, data.dt)
    half = CENTRED_WINDOW // 2
    keep = slice(half, data.n_samples - half) if data.n_samples > 4 * half else slice(None)
    return keep, acc[keep]


def paired_torques(model, validation: Sequence[Dataset],
                   torque_scale: float = 1.0) -> Tuple[np.ndarray, np.ndarray]:
    """
    Return the model's torque and the reference torque on validation samples.

    Parameters
    ----------
    model : object
        The model (``inverse_dynamics``; its case and gains as :func:`model_case` reads
        them, ``controller_torque`` in case 3). A model without a case (e.g. the simulated
        arm) is judged as in case 1, against the measured torque.
    validation : sequence of Dataset
        Held-out segments.
    torque_scale : float
        N m per model unit (1 in cases 1 and 2).

    Returns
    -------
    predicted, reference : ndarray, shape (S, n)
        ``torque_scale`` × M θ̈ + V + G + F at the measured states, and the torque it is
        judged against (see the module docstring), over the kept samples.

    Raises
    ------
    ValueError
        If the samples lack what the case needs (torque, or the desired trajectory).

    """
    case, kp, kd = model_case(model)
    predicted, reference = [], []
    for data in validation:
        keep, acc = _trimmed(data)
        if acc.shape[0] == 0:
            continue
        theta, theta_dot = data.theta[keep], data.theta_dot[keep]
        with np.errstate(all='ignore'):
            tau_hat = torque_scale * np.asarray(
                model.inverse_dynamics(theta, theta_dot, acc), dtype=float)
        if case == 'torque' or (case == 'unknown' and data.tau is not None):
            if data.tau is None:
                raise ValueError('case 1: the validation samples carry no measured torque')
            tau = data.tau[keep]
        else:
            if data.theta_d is None or data.theta_d_dot is None:
                raise ValueError(f'case {case!r}: the validation samples carry no '
                                 'desired trajectory')
            theta_d, theta_d_dot = data.theta_d[keep], data.theta_d_dot[keep]
            if case == 'pd_gains':
                tau = pd_torque(kp, kd, theta_d - theta, theta_d_dot - theta_dot)
            else:
                with np.errstate(all='ignore'):
                    tau = torque_scale * np.asarray(
                        model.controller_torque(theta, theta_dot, theta_d, theta_d_dot),
                        dtype=float)
        predicted.append(tau_hat)
        reference.append(tau)
    n = model.n_joints
    if not predicted:
        return np.empty((0, n)), np.empty((0, n))
    return np.vstack(predicted), np.vstack(reference)


def torque_error(predicted: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """
    Return the torque error per joint, RMSE / std of the reference torque, shape (n,).

    Each joint's std is floored at :data:`STD_FLOOR` of the largest joint's (and at 1e-12).
    Non-finite predictions give ``inf`` for their joint.
    """
    predicted = np.asarray(predicted, dtype=float)
    reference = np.asarray(reference, dtype=float)
    with np.errstate(all='ignore'):
        rmse = np.sqrt(np.mean(np.square(predicted - reference), axis=0))
    rmse = np.where(np.isfinite(rmse), rmse, np.inf)
    std = np.std(reference, axis=0)
    floor = max(STD_FLOOR * float(np.max(std)), 1e-12)
    return rmse / np.maximum(std, floor)


def torque_scale_from_effort(model, datasets: Sequence[Dataset]) -> float:
    """
    Return the N m per model unit that best maps a case-3 model to measured effort.

    The least-squares scale s of s · (M θ̈ + V + G + F) ≈ τ over the samples (θ̈ as in the
    gate). Raises ValueError if no sample carries effort or the scale is not positive and
    finite (the model does not explain the effort at all).
    """
    predicted, measured = [], []
    for data in datasets:
        if data.tau is None:
            continue
        keep, acc = _trimmed(data)
        if acc.shape[0] == 0:
            continue
        with np.errstate(all='ignore'):
            predicted.append(np.asarray(model.inverse_dynamics(
                data.theta[keep], data.theta_dot[keep], acc), dtype=float))
        measured.append(data.tau[keep])
    if not predicted:
        raise ValueError('no samples with measured effort to fix the torque scale from')
    p, m = np.concatenate(predicted).ravel(), np.concatenate(measured).ravel()
    with np.errstate(all='ignore'):
        scale = float(np.dot(p, m) / np.dot(p, p))
    if not (math.isfinite(scale) and scale > 0.0):
        raise ValueError(f'the model does not explain the measured effort (scale {scale})')
    return scale

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
After a change of a described arm: the residual that shows it, and the payload that made it.

:func:`newest_residual` is the model in use's residual on the newest filtered samples
(:func:`.rigid_fit.residual`), what :class:`.change.ChangeDetector` judges.
:func:`fit_last_body` re-identifies only the last moving body's ten parameters from the
first seconds after a change, every other parameter held at the model before it: a payload
or a tool changes nothing else, and ten parameters are determined by a second or two of
ordinary motion where the whole arm's are not. The least squares is pulled towards the
body before the change (a ridge of :data:`~.policy.BODY_RIDGE` per row, relative to each column's
scale) so that what little motion there is cannot swing the poorly excited inertia, and
the change of its inertia is pulled harder (:data:`~.policy.POINT_MASS_RIDGE`) towards that
of a point mass with the change's mass and first moment (:func:`point_mass_inertia`,
:data:`~.policy.POINT_MASS_PASSES` passes): a payload is seldom much more, and the inertia's
freedom would cost the first moment's precision, which the closed loop's prediction needs
most (its error over a wrist's Kp is a standing offset). A body that comes out unrealizable
is moved just inside. :func:`payload_of` says the
difference as vendors' payload tools do: mass (kg), centre of mass in the last link's
frame (m), inertia about it (kg m²).
"""

import math
from typing import Optional, Sequence

import numpy as np

from . import rigid_fit
from .controller_laws import ControllerLaw
from .policy import BODY_RIDGE, POINT_MASS_PASSES, POINT_MASS_RIDGE
from .rigid_data import filtered_rows
from ..data import Dataset
from ..rigid import consistency
from ..rigid.kernels import N_INERTIAL

__all__ = ['fit_last_body', 'newest_residual', 'payload_of', 'point_mass_inertia', 'since']


def since(segments: Sequence[Dataset], origin: float, start: float):
    """Return the parts of ``segments`` from stamp time ``start`` (s) on (``origin``: t = 0)."""
    out = []
    for seg in segments:
        first = int(np.searchsorted(seg.t + origin, start))
        if seg.n_samples - first >= 2:
            out.append(seg if first == 0 else seg.slice(first, seg.n_samples))
    return out


def _rows(structure, segments, sigma, law):
    features = law.features if law is not None and law.theta_weights.size else None
    return filtered_rows(segments, structure.regressor, sigma, False, features)


def newest_residual(arm, law: Optional[ControllerLaw], segments: Sequence[Dataset],
                    sigma: float):
    """Return ``(residual (K, n), times (K,))`` of the model on ``segments``, or None."""
    rows = _rows(arm.structure, segments, sigma, law)
    if rows is None or rows.n_samples < 1 or (law is None and rows.tau is None) or \
            (law is not None and rows.error is None):
        return None
    out, _ = rigid_fit.residual(arm, law, rows)
    return out, rows.time


def fit_last_body(before, law: Optional[ControllerLaw], segments: Sequence[Dataset],
                  sigma: float, start: float = -math.inf):
    """
    Return the arm ``before`` with its last body refitted on ``segments`` (module docstring).

    ``law`` None: on the measured torque (case 1); else on the servo's torque by that law
    (the closed loop's equation). Only the rows from ``start`` (s, the segments' time) on
    are fitted: the samples before it are the filter's support. None when too few rows.
    """
    structure = before.structure
    rows = _rows(structure, segments, sigma, law)
    if rows is not None and start > -math.inf:
        rows = rows.take(rows.time >= start)
    if rows is None or rows.n_samples < 10:
        return None
    target = rows.tau if law is None else rigid_fit.servo_torque(law, rows)
    if target is None:
        return None
    n = structure.n_joints
    last = n - 1                                  # bodies are in parent order: the tip
    cols = np.arange(N_INERTIAL * last, N_INERTIAL * (last + 1))
    rest = np.setdiff1d(np.arange(structure.n_parameters), cols)
    y = rows.regressor.reshape(-1, structure.n_parameters)
    weights = np.tile(1.0 / np.maximum(np.sqrt(np.mean(target ** 2, axis=0)), 1e-9),
                      rows.n_samples)
    a = y[:, cols] * weights[:, None]
    b = (target.reshape(-1) - y[:, rest] @ before.parameters[rest]) * weights
    if law is not None and np.any(law.ki != 0.0):   # each joint's integral constant
        return None
    scale = np.sqrt(np.mean(a * a, axis=0))
    scale = np.where(scale > 0.0, scale, 1.0)
    old = before.parameters[cols]
    weight = np.full(cols.size, BODY_RIDGE)
    prior = np.zeros(cols.size)       # the change of the body the ridge pulls towards
    for _ in range(1 + POINT_MASS_PASSES):
        ridge = np.sqrt(weight * a.shape[0])
        lhs = np.vstack([a / scale, np.diag(ridge)])
        rhs = np.concatenate([b - a @ old, ridge * prior * scale])
        step, *_ = np.linalg.lstsq(lhs, rhs, rcond=1e-10)
        change = step / scale
        if not abs(change[0]) > 1e-9:
            break
        prior[4:] = point_mass_inertia(change[0], change[1:4])
        weight[4:] = POINT_MASS_RIDGE
    body = old + change
    if not consistency.realizable(body[None], 1e-9)[0]:
        body = consistency.parameters(consistency.coordinates(body[None]))[0]
    parameters = before.parameters.copy()
    parameters[cols] = body
    return rigid_fit.RigidArm(structure, parameters, dict(before.info))


def point_mass_inertia(mass: float, first_moment) -> np.ndarray:
    """
    Return a point mass's inertia about the frame's origin (kg m², xx yy zz xy xz yz).

    ``mass`` (kg) at ``first_moment`` / ``mass`` (``first_moment`` in kg m): m (|c|² I − c cᵀ),
    in the order of the inertial parameters' inertia (a negative mass: one taken away).
    """
    h = np.asarray(first_moment, dtype=float)
    inertia = (float(h @ h) * np.eye(3) - np.outer(h, h)) / float(mass)
    return np.array([inertia[0, 0], inertia[1, 1], inertia[2, 2], inertia[0, 1],
                     inertia[0, 2], inertia[1, 2]])


def payload_of(before, after) -> dict:
    """Return the last body's change: mass (kg), com (m), inertia about it (kg m², 6)."""
    n = before.structure.n_joints
    cols = slice(N_INERTIAL * (n - 1), N_INERTIAL * n)
    delta = after.parameters[cols] - before.parameters[cols]
    mass = float(delta[0])
    heavy = abs(mass) > 1e-9
    com = delta[1:4] / mass if heavy else np.zeros(3)
    inertia = delta[4:] - (point_mass_inertia(mass, delta[1:4]) if heavy else 0.0)
    joint = before.structure.joint_names[int(before.structure.tree.col[n - 1])]
    return {'mass': mass, 'com': com.tolist(), 'inertia': [float(v) for v in inertia],
            'frame': _child_link(before.structure.urdf, joint)}


def _child_link(urdf: str, joint: str) -> str:
    """Return the child link of ``joint`` in ``urdf`` (its frame is the joint's)."""
    import xml.etree.ElementTree as ElementTree
    for element in ElementTree.fromstring(urdf).findall('joint'):
        child = element.find('child')
        if element.get('name') == joint and child is not None:
            return str(child.get('link'))
    return joint

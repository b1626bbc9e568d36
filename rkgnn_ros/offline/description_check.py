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
A robot description checked against the data: ``identify_bag --robot-description X --learn-chain``.

A description's kinematics can be wrong (an old URDF, an axis flipped or tilted by a
mounting, a link's length). The chain learned from the same recording does without them.
Both rigid bodies are fitted on the same training part (case torque) and scored on the same
held-out part (:func:`~rkgnn_ros.core.fitting.validation.split_validation`), so their
torque errors compare; the learned axes are compared with the description's up to the
symmetries that give equal dynamics (:func:`~rkgnn_ros.core.rigid.chain.axis_errors`).

The description *fits the data* when its held-out torque error (RMSE / std, worst joint) is
at most :data:`SLACK` times the learned chain's plus :data:`MARGIN`; otherwise the check
names the joint it explains worst and the axes that differ most. The model written stays
the description's: the check informs, it does not replace.
"""

import math
from typing import Optional, Sequence

import numpy as np

from rkgnn_ros.core.data import Dataset
from rkgnn_ros.core.fitting.rigid_fit import fit_torque
from rkgnn_ros.core.fitting.validation import MIN_SEGMENT_SAMPLES, split_validation
from rkgnn_ros.core.rigid.chain import axis_errors, chain_of

__all__ = ['check_description', 'MARGIN', 'SLACK']

#: [ratio] The description fits the data while its held-out torque error is at most this many
#: times the learned chain's ...
SLACK = 1.5
#: [RMSE / std] ... plus this (two fits on a few seconds differ by about this much alone).
MARGIN = 0.01


def check_description(description, learned, segments: Sequence[Dataset],
                      validation_fraction: float, min_samples: int = 50) -> Optional[dict]:
    """
    Return the check of ``description`` against ``learned`` on ``segments`` (with τ).

    Both are :class:`~rkgnn_ros.core.rigid.structure.RigidStructure` of the same joints.
    The dict: ``fits_data`` (bool), ``text`` (one line), ``description_error`` and
    ``learned_error`` (held-out torque RMSE / std, worst joint), their per-joint lists,
    ``axis_deg`` (the angle of each of the description's axes to the learned one, degrees,
    after the best alignment; None when the description's moving joints are not one serial
    chain), ``axis_deg_max``, ``gravity_deg`` (the error of the first axis's tilt to
    gravity). None when either fit has too few samples or no held-out part.
    """
    segments = [seg for seg in segments if seg.tau is not None]
    train, validation, _ = split_validation(segments, validation_fraction, MIN_SEGMENT_SAMPLES)
    if not train or not validation:
        return None
    given = fit_torque(description, train, validation, min_samples=min_samples)
    found = fit_torque(learned, train, validation, min_samples=min_samples)
    if given is None or found is None or not (
            math.isfinite(given.error) and math.isfinite(found.error)):
        return None
    try:
        axes = axis_errors(learned.chain, chain_of(description))
    except ValueError:          # not one serial chain: the torques still compare
        axes = None
    names = list(description.joint_names)
    fits = given.error <= SLACK * found.error + MARGIN
    worst = int(np.argmax(given.errors - found.errors))
    text = (f'the robot description explains the held-out torque with {given.error:.2%} '
            f'error (worst joint), the chain learned from the data with {found.error:.2%}')
    if axes is not None:
        k = int(np.argmax(axes['aligned_deg']))
        text += (f'; their axes differ by at most {axes["aligned_deg_max"]:.1f} deg '
                 f'({names[k]})')
    text += (': the description fits the data' if fits else
             f': the description does not fit the data (worst on {names[worst]}, '
             f'{given.errors[worst]:.2%} against {found.errors[worst]:.2%})')
    return {'fits_data': bool(fits), 'text': text,
            'description_error': given.error, 'learned_error': found.error,
            'description_errors': given.errors.tolist(), 'learned_errors': found.errors.tolist(),
            'axis_deg': None if axes is None else axes['aligned_deg'],
            'axis_deg_max': None if axes is None else axes['aligned_deg_max'],
            'gravity_deg': None if axes is None else axes['gravity_deg'],
            'joints': names}

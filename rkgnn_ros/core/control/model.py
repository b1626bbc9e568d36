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
The model a feed-forward is computed from: one function, so it can change in one place.

A feed-forward needs M, V, G and F right along plans the model never saw. The RBF model
the online search evolves holds only near its training path (``bench/control.py``: on
held-out plans its torque error is of the order of the torque itself), while the
equation-error fit of :class:`~rkgnn_ros.core.fitting.linear.LinearDynamics` on the tied
trigonometric basis of a planar arm (issue 11) is global: every configuration of a planar
revolute chain is in its span, and it is fitted in closed form in a fraction of a second.
So :func:`feedforward_model` fits that model to the data the identifier buffered; the gate
(:mod:`~rkgnn_ros.core.control.gate`) judges it like any other model. When the global basis
becomes the identifier's own model, this function returns that model instead.

Cases: 1 (``'torque'``, measured torque) and 2 (``'pd_gains'``, the torque of the known
PD law). Case 3 has no torque scale (see the gate), and this function refuses it.

The fit does not certify M positive definite over the whole joint range
(``certify=False``): a feed-forward uses only the inverse dynamics along the plan, the
model still raises M to its floor wherever it falls short, and on the bench's arms the
certified fit made no cuts and gave the same tracking to the last digit, at 1.9-3.5 times
the fit's time (one A/B run on a loaded machine) -- time the identifier's feed-forward
thread takes from the node's other threads.
"""

from typing import Optional, Sequence

import numpy as np

from ..data import Dataset
from ..fitting.linear import LinearDynamics
from ..model.trig import TrigBasis

#: Identification cases whose data fix the torque in N m.
FEEDFORWARD_CASES = ('torque', 'pd_gains')


def feedforward_model(train: Sequence[Dataset], case: str, kp=None, kd=None,
                      structure=None) -> LinearDynamics:
    """
    Return the model for the feed-forward, fitted on ``train``.

    Parameters
    ----------
    train : sequence of Dataset
        Gap-free segments, oldest first (held-out samples excluded by the caller).
    case : {'torque', 'pd_gains'}
        What gives the torque: the measured effort, or the known PD law.
    kp, kd : array_like, shape (n,), optional
        The known gains (case ``'pd_gains'``).
    structure : RigidStructure, optional
        A robot description's: its rigid body is the model (global on any arm, physically
        consistent), fitted in closed form (:mod:`rkgnn_ros.core.fitting.rigid_fit`).

    Returns
    -------
    LinearDynamics or RigidArm
        Fitted on the tied planar trigonometric basis, or the rigid body (any model with
        ``inverse_dynamics``, ``simulate`` and ``n_joints`` would do for the callers).

    Raises
    ------
    ValueError
        For case 3 or data that lack what the case needs.

    """
    if case not in FEEDFORWARD_CASES:
        raise ValueError(f'no feed-forward model in case {case!r}: the torque scale is not '
                         'identifiable without measured torque or known gains')
    segments = list(train)
    if not segments:
        raise ValueError('no training data')
    if structure is not None:
        from ..fitting.rigid_fit import fit_closed, fit_torque
        if case == 'torque':
            fit = fit_torque(structure, segments)
        else:
            fit = fit_closed(structure, segments, kp=np.asarray(kp, dtype=float),
                             kd=np.asarray(kd, dtype=float))
        if fit is None:
            raise ValueError('too few data for the rigid-body fit')
        arm = fit.arm
        if case == 'pd_gains':
            arm.kp, arm.kd = np.asarray(kp, dtype=float), np.asarray(kd, dtype=float)
        return arm
    basis = TrigBasis(segments[0].n_joints, planar=True, tied=True)
    gains: Optional[tuple] = (kp, kd) if case == 'pd_gains' else (None, None)
    return LinearDynamics(basis, certify=False).fit(segments, case, *gains)

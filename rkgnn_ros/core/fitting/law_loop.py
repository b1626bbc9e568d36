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
A global arm model closed with a fitted servo law: what every such loop shares.

A loop rolls the arm out under the law τ = Kp (θd − θ) + Kd (θ̇d − θ̇) + ... from one
state over a plan. The law's command-only terms (constant, integral held, θ-terms on θd,
velocity feed-forward) fold into a shifted θd (:meth:`ControllerLaw.shift`); its θ-terms
on the measured θ are evaluated in the loop's compiled rollout when the loop knows their
basis (``_terms_compiled``), else along the previous pass; an integral term grows along
the previous pass (Picard iteration, :data:`PASSES` rollouts) unless the subclass's kernel
integrates it as a state (``_integral_compiled``: then ``_once`` also takes ``raw``, the
unshifted θd, and the integral grows from its start value inside the rollout). A subclass
gives ``_once(x0, t, θd', θ̇d)`` (one compiled rollout of the PD loop with the compiled
θ-terms) and ``_set_law_terms()`` (what of the law its kernel takes).
"""

import copy
import math
from typing import Optional

import numpy as np

from .controller_laws import ControllerLaw
from ..integration.inputs import stage_inputs
from ..integration.rkg import choose_substeps

__all__ = ['LawLoop', 'MAX_SUBSTEPS', 'PASSES', 'SAFETY', 'SUBSTEPS_REUSE_RAD']

#: Rollouts of :meth:`LawLoop.simulate` when the law has an integral or θ-terms on θ that
#: the kernel does not evaluate.
PASSES = 3

#: Most RKG steps per sampling interval (a stiffer loop is rolled out with this many).
MAX_SUBSTEPS = 64

#: Share of RKG's stability limit a rollout's step uses at its start state's stiffness: the
#: step's own error stays far below any model's, with room for the stiffness to grow along
#: the rollout.
SAFETY = 0.7

#: A start within this (rad, every joint) of the last keeps its number of RKG steps.
SUBSTEPS_REUSE_RAD = 0.05


class LawLoop:
    """Base of an arm closed with a :class:`ControllerLaw` (module docstring)."""

    law: ControllerLaw
    _terms_compiled: bool = False
    _integral_compiled: bool = False

    def __init__(self, arm, law: ControllerLaw, substeps: Optional[int] = None):
        if not np.all(law.kp > 0.0):
            raise ValueError(f'the law needs Kp > 0 on every joint, got {law.kp.tolist()}')
        if law.n_joints != arm.n_joints:
            raise ValueError(f'the law is for {law.n_joints} joints, the arm has '
                             f'{arm.n_joints}')
        self.arm, self.law = arm, law
        self.substeps = None if substeps is None else max(1, int(substeps))
        #: held-out torque error of the arm (worst joint, RMSE / std; set by the fit)
        self.torque_error = math.inf

    def _set_law_terms(self) -> None:
        raise NotImplementedError

    def _stiffness_at(self, theta) -> float:
        """Return the largest |eigenvalue| (1/s) of the linearised closed loop at ``theta``."""
        raise NotImplementedError

    def _substeps_at(self, theta: np.ndarray, dt: float) -> int:
        """
        Return the RKG steps per ``dt`` that the stiffness at ``theta`` needs.

        At :data:`SAFETY` of RKG's stability limit, at most :data:`MAX_SUBSTEPS`; kept for
        starts within :data:`SUBSTEPS_REUSE_RAD` of the one it was computed at (M(θ)
        changes little over such a move, and :data:`SAFETY` covers it).
        """
        cached = getattr(self, '_substeps_cache', None)
        if cached is not None and cached[1] == dt and \
                np.max(np.abs(theta - cached[0])) <= SUBSTEPS_REUSE_RAD:
            return cached[2]
        try:
            stiffness = self._stiffness_at(theta)
        except np.linalg.LinAlgError:
            stiffness = math.inf
        substeps = (MAX_SUBSTEPS if not math.isfinite(stiffness)
                    else min(MAX_SUBSTEPS, choose_substeps(dt, stiffness, safety=SAFETY)))
        self._substeps_cache = (theta.copy(), dt, substeps)
        return substeps

    def _inputs(self, x0, t, theta_d, theta_d_dot):
        """Return n, the sampling interval, the RKG steps in it and the rollout's stage inputs."""
        n = self.n_joints
        dt = float(t[-1] - t[0]) / (t.size - 1)
        substeps = self.substeps
        if substeps is None:
            substeps = self._substeps_at(np.asarray(x0, dtype=float)[:n], dt)
        u = stage_inputs('pd_gains', t, substeps, theta_d=theta_d, theta_d_dot=theta_d_dot)
        return n, dt, substeps, u

    def _once(self, x0, t, theta_d, theta_d_dot) -> np.ndarray:
        raise NotImplementedError

    @property
    def n_joints(self) -> int:
        """Return the number of joints n."""
        return self.law.n_joints

    def with_law(self, law: ControllerLaw) -> 'LawLoop':
        """Return this loop with ``law`` (the same gains; e.g. its integral term moved on)."""
        if not (np.array_equal(law.kp, self.law.kp) and np.array_equal(law.kd, self.law.kd)):
            raise ValueError('with_law keeps the gains: fit a new loop for other gains')
        out = copy.copy(self)
        out.law = law
        out._set_law_terms()
        return out

    def simulate(self, x0, t, theta_d, theta_d_dot, integral_term=None,
                 passes: int = PASSES) -> np.ndarray:
        """
        Roll the closed loop out from ``x0`` (2n,) over the uniform times ``t`` (K,).

        ``theta_d``, ``theta_d_dot`` (K, n) are the commands at ``t``; ``integral_term``
        (n,) the law's integral term at the start (default the law's). Returns the states
        (K, 2n), NaN from a divergence on.
        """
        law = self.law
        t = np.asarray(t, dtype=float)
        theta_d = np.asarray(theta_d, dtype=float)
        theta_d_dot = np.asarray(theta_d_dot, dtype=float)
        n = theta_d.shape[1]
        start = law.integral_term if integral_term is None else np.asarray(integral_term)
        integral = np.broadcast_to(start, theta_d.shape)
        # θ-terms on the measured θ: in the kernel; on another basis, along the last pass
        on_theta = (law.theta_input == 'measured' and law.theta_weights.size > 0
                    and not self._terms_compiled)
        integrating = bool(np.any(law.ki != 0.0))
        in_kernel = integrating and self._integral_compiled
        passes = max(1, int(passes)) if (on_theta or (integrating and not in_kernel)) else 1
        along = theta_d
        states = None
        for _ in range(passes):
            shifted = theta_d + law.shift(theta_d, theta_d_dot, integral)
            if on_theta:
                shifted = shifted + law._theta_terms(along, None) / law.kp
            states = (self._once(x0, t, shifted, theta_d_dot, raw=theta_d) if in_kernel
                      else self._once(x0, t, shifted, theta_d_dot))
            if not np.all(np.isfinite(states)):
                break
            along = states[:, :n]
            if integrating and not in_kernel:
                e = theta_d - along
                grown = np.zeros_like(e)
                grown[1:] = np.cumsum(0.5 * (e[1:] + e[:-1]) * np.diff(t)[:, None], axis=0)
                integral = start + law.ki * grown
        return states

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
The rigid-body arm of a robot description closed with the servo's law, rolled out compiled.

The prediction of every case with a robot description: the identified
:class:`~.rigid_fit.RigidArm` (M by the composite rigid-body algorithm, V + G + F by
Newton-Euler, rotor inertia, friction and offset included) under the fitted or known
law, integrated by the Runge-Kutta-Gill stage update
(:func:`~rkgnn_ros.core.integration.rkg.gill_stage`) in one numba kernel. The law's
gravity compensation on the arm's own gravity regressor (tied weights ρ,
:class:`~.rigid_law.GravityFeatures`) is one more Newton-Euler pass at each stage; its
other terms are handled by :class:`~.law_loop.LawLoop`.

The number of RKG steps per sample interval follows the stiffness of the linearised closed
loop at the start state: the largest |eigenvalue| of [[0, I], [−M⁻¹Kp, −M⁻¹(Kd + fv +
fc / v_c)]] (the Coulomb term's slope at rest counts as damping), at
:data:`~.law_loop.SAFETY` of RKG's stability limit, at most
:data:`~.law_loop.MAX_SUBSTEPS`.
"""

from typing import Optional

from numba import njit
import numpy as np

from .controller_laws import ControllerLaw
from .law_loop import LawLoop, MAX_SUBSTEPS
from .rigid_fit import RigidArm
from .rigid_law import GravityFeatures
from ..integration.inputs import stage_inputs
from ..integration.rkg import gill_node, gill_stage
from ..rigid.kernels import _crba, _rnea, cholesky_solve, gravity_pass, N_INERTIAL
from ..servo_law import compiled_pd_torque

__all__ = ['MAX_SUBSTEPS', 'RigidLoop', 'precompile_rigid_loop']

#: A state component beyond this magnitude ends a rollout as diverged.
DIVERGED = 1e6


@njit(cache=True, nogil=True)
def _rates(x, u, ue, n, parent, col, trot, pos, axis, gravity, vc, pi, kp, kd, ki, law_pi,
           law_on, rot, w, v, wd, al, fn, ff, tmp, comp, mass, bias, grav, zeros, rate):
    """Write ẋ (3n,) of the closed loop into ``rate``; return False where M is not positive."""
    q = x[:n]
    qd = x[n:2 * n]
    _rnea(parent, col, trot, pos, axis, gravity, vc, pi, q, qd, zeros, True, rot, w, v, wd,
          al, fn, ff, tmp, bias)
    _crba(parent, col, rot, pos, axis, pi, comp, fn, ff, tmp, mass)
    if law_on:
        gravity_pass(parent, col, rot, pos, axis, gravity, law_pi, al, fn, ff, tmp, grav)
    for i in range(n):
        tau = compiled_pd_torque(kp[i], kd[i], u[i] - x[i], u[n + i] - x[n + i]) + x[2 * n + i]
        if law_on:
            tau += grav[i]
        rate[n + i] = tau - bias[i]
        rate[i] = x[n + i]
        rate[2 * n + i] = ki[i] * (ue[i] - x[i])
    return cholesky_solve(mass, rate[n:2 * n])


@njit(cache=True, nogil=True)
def _rollout(x0, u, ue, h, parent, col, trot, pos, axis, gravity, vc, pi, kp, kd, ki, law_pi,
             law_on, out):
    """
    Roll out over ``u`` (K-1, substeps, 3, 2n) into ``out`` (K, 2n); NaN after divergence.

    The state carries the growth of the integral term (N m, from 0 at the start): its rate
    is ``ki`` (θd − θ) with θd the first n columns of ``ue`` (the unshifted commands, shaped
    as ``u``), and it adds to the servo's torque.
    """
    n = kp.shape[0]
    nb = parent.shape[0]
    rot = np.empty((nb, 3, 3))
    w, v, wd, al = np.empty((nb, 3)), np.empty((nb, 3)), np.empty((nb, 3)), np.empty((nb, 3))
    fn, ff, tmp = np.empty((nb, 3)), np.empty((nb, 3)), np.empty((4, 3))
    comp = np.empty(N_INERTIAL * nb)
    mass = np.zeros((n, n))
    bias, grav, zeros = np.empty(n), np.empty(n), np.zeros(n)
    x, xs = np.zeros(3 * n), np.empty(3 * n)
    x[:2 * n] = x0
    rate, acc = np.empty(3 * n), np.zeros(3 * n)
    out[0] = x0
    for i in range(u.shape[0]):
        for s in range(u.shape[1]):
            xs[:] = x
            for stage in range(4):
                node = gill_node(stage)
                if not _rates(xs, u[i, s, node], ue[i, s, node], n, parent, col, trot, pos,
                              axis, gravity, vc, pi, kp, kd, ki, law_pi, law_on, rot, w, v,
                              wd, al, fn, ff, tmp, comp, mass, bias, grav, zeros, rate):
                    return
                gill_stage(stage, h, x, xs, rate, acc)
        for j in range(3 * n):
            if not abs(x[j]) <= DIVERGED:
                return
        out[i + 1] = x[:2 * n]


class RigidLoop(LawLoop):
    """
    A :class:`~.rigid_fit.RigidArm` closed with a :class:`ControllerLaw` (module docstring).

    Attributes
    ----------
    arm : RigidArm
        The arm.
    law : ControllerLaw
        The servo's law (Kp > 0 on every joint).
    substeps : int or None
        RKG steps per sampling interval; None: from the stiffness at each start.
    torque_error : float
        The fit's held-out error (worst joint; set by whoever fitted it).

    """

    def __init__(self, arm: RigidArm, law: ControllerLaw, substeps: Optional[int] = None):
        super().__init__(arm, law, substeps)
        tree = arm.structure.tree
        self._tree = tree
        self._pi = np.ascontiguousarray(arm.parameters, dtype=float)
        self._set_law_terms()

    def _set_law_terms(self) -> None:
        law = self.law
        self._kp = np.ascontiguousarray(law.kp, dtype=float)
        self._kd = np.ascontiguousarray(law.kd, dtype=float)
        self._law_pi = np.zeros(self.arm.structure.n_parameters)
        self._law_on = False
        self._terms_compiled = True
        self._integral_compiled = True
        if law.theta_input == 'measured' and law.theta_weights.size:
            weights = law.theta_weights
            tied = bool(np.all(weights == weights[:1]))
            if (isinstance(law.features, GravityFeatures) and tied
                    and law.features.structure is self.arm.structure):
                self._law_pi = law.features.full(weights[0])
                self._law_on = True
            else:
                self._terms_compiled = False     # by passes along the previous one

    def _once(self, x0, t, theta_d, theta_d_dot, raw=None) -> np.ndarray:
        n, dt, substeps, u = self._inputs(x0, t, theta_d, theta_d_dot)
        if raw is None:
            ue, ki = u, np.zeros(n)
        else:
            ue = stage_inputs('pd_gains', t, substeps, theta_d=raw, theta_d_dot=theta_d_dot)
            ki = np.ascontiguousarray(self.law.ki, dtype=float)
        out = np.full((t.size, 2 * n), np.nan)
        tree = self._tree
        _rollout(np.asarray(x0, dtype=float), np.ascontiguousarray(u), np.ascontiguousarray(ue),
                 dt / substeps, tree.parent, tree.col, tree.rot, tree.pos, tree.axis,
                 tree.gravity, float(tree.coulomb_velocity), self._pi, self._kp, self._kd, ki,
                 self._law_pi, self._law_on, out)
        return out

    def stiffness(self, theta) -> float:
        """Return the largest |eigenvalue| (1/s) of the linearised closed loop at ``theta``."""
        n = self.n_joints
        mass = self.arm.mass_matrix(np.asarray(theta, dtype=float)[None])[0]
        joint = self.arm.joint_terms()
        damping = (self.law.kd + joint[:, 1]
                   + joint[:, 2] / self.arm.structure.tree.coulomb_velocity)
        inverse = np.linalg.inv(mass)
        a = np.zeros((2 * n, 2 * n))
        a[:n, n:] = np.eye(n)
        a[n:, :n] = -inverse * self.law.kp
        a[n:, n:] = -inverse * damping
        return float(np.max(np.abs(np.linalg.eigvals(a))))

    def _stiffness_at(self, theta) -> float:
        return self.stiffness(theta)


def precompile_rigid_loop(structure) -> None:
    """Compile (or load from numba's cache) the rollout kernel, on ``structure``'s prior."""
    n = structure.n_joints
    tree = structure.tree
    out = np.full((3, 2 * n), np.nan)
    u = np.zeros((2, 1, 3, 2 * n))
    _rollout(np.zeros(2 * n), u, u, 0.01, tree.parent, tree.col, tree.rot, tree.pos,
             tree.axis, tree.gravity, float(tree.coulomb_velocity),
             np.ascontiguousarray(structure.prior), np.ones(n), np.ones(n), np.zeros(n),
             np.zeros(structure.n_parameters), True, out)

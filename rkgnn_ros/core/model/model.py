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
An identified RKGNN model: roll it out, read its terms, save and load it.

:class:`RKGNNModel` holds a network structure, the scales its genome is decoded with and
the genome. ``simulate`` / ``predict`` roll it out over a long horizon (the compiled kernel
of :mod:`.kernels`); ``mass_matrix``, ``velocity_terms``, ``gravity_terms``,
``friction_terms``, ``controller_torque`` expose the identified terms (the numpy network
of :mod:`.network`); ``inverse_dynamics`` is what computed-torque control needs; ``save`` /
``load`` use the versioned YAML format of :mod:`.files`. Fitting it is the business of
:mod:`..fitting`, which this module never imports.
"""

from typing import NamedTuple, Optional, Sequence

import numpy as np

from . import files
from .network import BatchedNetwork
from .scales import Scales
from .spec import NetworkSpec
from ..data import Dataset
from ..integration.inputs import stage_inputs


def _finite_vector(name, value, n):
    arr = np.asarray(value, dtype=float).reshape(-1)
    if arr.size != n:
        raise ValueError(f'{name} must have {n} values, got {arr.size}')
    if not np.all(np.isfinite(arr)):
        raise ValueError(f'{name} contains NaN or inf')
    return arr


class ModelRollout(NamedTuple):
    """How an :class:`RKGNNModel` is rolled out, and its info (see there)."""

    substeps: object = 4
    torque_interpolation: object = 'linear'
    info: object = None


class RKGNNModel:
    """
    An identified RKGNN model of an n-joint arm.

    Parameters
    ----------
    spec : NetworkSpec
        Network structure (fixes the case and the genome layout).
    scales : Scales
        Scales the genome is decoded with.
    genome : array_like, shape (N,)
        Normalised network parameters.
    joint_names : sequence of str, optional
        Names of the joints, in order.
    kp, kd : array_like, shape (n,), optional
        The known PD gains (case 'pd_gains').
    dt : float
        Sampling interval the model was identified at (prediction output step by default).
    substeps : int
        RKG steps per sampling interval.
    torque_interpolation : str
        Case 'torque': 'hold' or 'linear' between torque samples.
    info : dict, optional
        Free-form provenance (cost, generation, ...), saved with the model.

    """

    def __init__(self, spec: NetworkSpec, scales: Scales, genome, joint_names=None, kp=None,
                 kd=None, dt=0.01, **options):
        substeps, torque_interpolation, info = ModelRollout(**options)
        n = spec.n_joints
        self.spec = spec
        self.scales = scales
        if scales.theta_center.size != n:
            raise ValueError(f'scales are for {scales.theta_center.size} joints, '
                             f'the network has {n}')
        self.genome = _finite_vector('genome', genome, spec.genome_size)
        names = tuple(joint_names) if joint_names else tuple(f'joint{i + 1}' for i in range(n))
        if len(names) != n:
            raise ValueError(f'{len(names)} joint names for a {n}-joint model')
        if len(set(names)) != n:
            raise ValueError(f'duplicate joint names: {list(names)}')
        self.joint_names = names
        if spec.case == 'pd_gains':
            if kp is None or kd is None:
                raise ValueError("case 'pd_gains' needs kp and kd")
        self.kp = None if kp is None else _finite_vector('kp', kp, n)
        self.kd = None if kd is None else _finite_vector('kd', kd, n)
        if not (np.isfinite(dt) and dt > 0):
            raise ValueError(f'dt must be positive, got {dt}')
        self.dt = float(dt)
        if int(substeps) < 1:
            raise ValueError(f'substeps must be >= 1, got {substeps}')
        self.substeps = int(substeps)
        if torque_interpolation not in ('hold', 'linear'):
            raise ValueError(f"torque_interpolation must be 'hold' or 'linear', "
                             f'got {torque_interpolation!r}')
        self.torque_interpolation = torque_interpolation
        self.info = dict(info or {})
        self._params = spec.decode(self.genome[None], scales)
        self._constants = spec.constants(scales, self.kp, self.kd)
        self._net = BatchedNetwork(spec, self._params, scales, self.kp, self.kd)

    @property
    def n_joints(self) -> int:
        """Return the number of joints n."""
        return self.spec.n_joints

    @property
    def case(self) -> str:
        """Return the identification case: 'torque', 'pd_gains' or 'unknown'."""
        return self.spec.case

    def theta_features(self, theta) -> np.ndarray:
        """Return the network's θ-features φ(θ) (any basis): ``theta`` (S, n) -> (S, F)."""
        return self._net.features(np.atleast_2d(np.asarray(theta, dtype=float)))

    # ----- the identified terms (numpy; any leading batch of states)
    def _states(self, theta, theta_dot=None):
        theta = np.atleast_2d(np.asarray(theta, dtype=float))
        if theta.shape[-1] != self.n_joints:
            raise ValueError(f'theta must have {self.n_joints} columns, got {theta.shape}')
        if theta_dot is None:
            theta_dot = np.zeros_like(theta)
        theta_dot = np.broadcast_to(np.asarray(theta_dot, dtype=float), theta.shape)
        return np.hstack([theta, theta_dot])

    def _no_input(self):
        """Return a zero input u of the right size (τ in case 1, [θd, θ̇d] otherwise)."""
        return np.zeros(self.n_joints if self.case == 'torque' else 2 * self.n_joints)

    def _squeeze(self, value, theta):
        return value[0] if np.ndim(theta) == 1 else value

    def mass_matrix(self, theta):
        """M(θ): ``theta`` shape (n,) or (T, n) -> (n, n) or (T, n, n)."""
        x = self._states(theta)
        return self._squeeze(self._net.mass_matrix(x[:, :self.n_joints]), theta)

    def terms(self, theta, theta_dot, theta_d=None, theta_d_dot=None, tau=None):
        """Return M, V, G, F and the torque τ (of the case's controller model) at the states."""
        x = self._states(theta, theta_dot)
        n = self.n_joints
        if self.case == 'torque':
            u = np.zeros(n) if tau is None else np.asarray(tau, dtype=float)
        else:
            if theta_d is None or theta_d_dot is None:
                raise ValueError(f'case {self.case!r} needs theta_d and theta_d_dot')
            u = np.hstack([np.broadcast_to(theta_d, x[:, :n].shape),
                           np.broadcast_to(theta_d_dot, x[:, :n].shape)])
        out = self._net.terms(x, u)
        return {k: self._squeeze(np.asarray(v), theta) for k, v in out.items()}

    def velocity_terms(self, theta, theta_dot):
        """V(θ, θ̇) = B(θ)[θ̇θ̇] + C(θ)[θ̇²]."""
        x = self._states(theta, theta_dot)
        return self._squeeze(self._net.terms(x, self._no_input())['V'], theta)

    def gravity_terms(self, theta):
        """G(θ)."""
        x = self._states(theta)
        return self._squeeze(self._net.terms(x, self._no_input())['G'], theta)

    def friction_terms(self, theta_dot):
        """F(θ̇) (independent of θ)."""
        theta_dot = np.asarray(theta_dot, dtype=float)
        x = self._states(np.zeros_like(np.atleast_2d(theta_dot)), theta_dot)
        return self._squeeze(self._net.terms(x, self._no_input())['F'], theta_dot)

    def controller_torque(self, theta, theta_dot, theta_d, theta_d_dot):
        """τ of the identified (case 3) or known (case 2) controller."""
        if self.case == 'torque':
            raise ValueError("case 'torque' has no controller model: the torque is measured")
        return self.terms(theta, theta_dot, theta_d, theta_d_dot)['tau']

    def inverse_dynamics(self, theta, theta_dot, theta_ddot):
        """τ = M θ̈ + V + G + F: the torque a computed-torque controller applies."""
        t = self.terms(theta, theta_dot, np.zeros_like(theta), np.zeros_like(theta))
        m = np.asarray(t['M'])
        acc = np.asarray(theta_ddot, dtype=float)
        return np.einsum('...ij,...j->...i', m, acc) + t['V'] + t['G'] + t['F']

    def forward_dynamics(self, theta, theta_dot, tau=None, theta_d=None, theta_d_dot=None):
        """θ̈ of the model (torque given in case 1, desired trajectory otherwise)."""
        x = self._states(theta, theta_dot)
        n = self.n_joints
        if self.case == 'torque':
            u = np.asarray(tau, dtype=float)
        else:
            u = np.hstack([np.broadcast_to(theta_d, x[:, :n].shape),
                           np.broadcast_to(theta_d_dot, x[:, :n].shape)])
        if self.case == 'torque' and u.ndim == 2:
            rows = [self._net.rhs(x[i:i + 1], u[i]) for i in range(x.shape[0])]
            acc = np.vstack(rows)[:, n:]
        elif self.case != 'torque' and x.shape[0] > 1:
            acc = np.vstack([self._net.rhs(x[i:i + 1], u[i]) for i in range(x.shape[0])])[:, n:]
        else:
            acc = self._net.rhs(x, u)[:, n:]
        return self._squeeze(acc, theta)

    def implied_gains(self, step=1e-6):
        """
        Return the controller model's PD gains linearised at zero error: (kp, kd), shape (n,).

        Case 2 returns the known gains; case 3 the slope of the torque network at zero error
        (linear gains plus the RBF sub-networks' derivative), in the model's gauge (see
        network.py: in case 3 the absolute torque scale is not identifiable). Case 1: None.
        """
        if self.case == 'torque':
            return None
        if self.case == 'pd_gains':
            return self.kp.copy(), self.kd.copy()
        n = self.n_joints
        zeros = np.zeros((1, n))
        kp = np.empty(n)
        kd = np.empty(n)
        for i in range(n):
            e = np.zeros((1, n))
            e[0, i] = step
            hi = self.controller_torque(zeros, zeros, e, zeros)[0, i]
            lo = self.controller_torque(zeros, zeros, -e, zeros)[0, i]
            kp[i] = (hi - lo) / (2 * step)
            hi = self.controller_torque(zeros, zeros, zeros, e)[0, i]
            lo = self.controller_torque(zeros, zeros, zeros, -e)[0, i]
            kd[i] = (hi - lo) / (2 * step)
        return kp, kd

    # ----- rollouts (compiled kernel)
    def _rollout(self, x0, u_flat, h, substeps):
        from .kernels import rollout
        n = self.n_joints
        bound_center = np.concatenate([self.scales.theta_center, np.zeros(n)])
        bound_scale = 100.0 * np.concatenate([self.scales.theta_spread + 1.0,
                                              self.scales.velocity * 10.0 + 1.0])
        return rollout(np.ascontiguousarray(x0, dtype=float), np.ascontiguousarray(u_flat),
                       float(h), substeps, self._constants, self._params.take(0),
                       bound_center, bound_scale)

    def simulate(self, x0, t, tau=None, reference=None, theta_d=None, theta_d_dot=None,
                 substeps=None):
        """
        Roll the model out from state ``x0`` over the uniform times ``t``.

        Parameters
        ----------
        x0 : array_like, shape (2n,)
            Start state [θ, θ̇] at ``t[0]``.
        t : array_like, shape (N,)
            Uniform output times.
        tau : array_like, shape (N, n), optional
            Case 1: the torque samples (interpolated as ``torque_interpolation``).
        reference : object, optional
            Cases 2-3: anything with ``evaluate(times) -> (θd, θ̇d)`` (evaluated exactly).
        theta_d, theta_d_dot : array_like, shape (N, n), optional
            Cases 2-3: desired samples instead of ``reference``.
        substeps : int, optional
            RKG steps per interval; default keeps the model's step width.

        Returns
        -------
        ndarray, shape (N, 2n)
            Predicted states; rows after a divergence are NaN.

        """
        t = np.asarray(t, dtype=float)
        if t.ndim != 1 or t.size < 2 or not np.all(np.diff(t) > 0):
            raise ValueError('t must be increasing with at least 2 samples')
        dt = (t[-1] - t[0]) / (t.size - 1)
        if substeps is None:
            substeps = max(1, int(np.ceil(dt / (self.dt / self.substeps) - 1e-9)))
        x0 = _finite_vector('x0', x0, 2 * self.n_joints)
        u = stage_inputs(self.case, t, substeps, tau, theta_d, theta_d_dot, reference,
                         self.torque_interpolation)
        return self._rollout(x0, u, dt / substeps, substeps)

    def predict(self, data: Dataset, reference=None):
        """Open-loop rollout over a recorded segment from its first state, shape (N, 2n)."""
        return self.simulate(data.state[0], data.t, tau=data.tau, reference=reference,
                             theta_d=data.theta_d, theta_d_dot=data.theta_d_dot)

    # ----- persistence (the format is in files.py)
    def to_dict(self) -> dict:
        """Return the plain-data form written by :meth:`save`."""
        return files.model_to_dict(self)

    def to_yaml(self) -> str:
        """Return the YAML text of :meth:`to_dict`."""
        return files.model_to_yaml(self)

    @classmethod
    def from_dict(cls, d, joint_names: Optional[Sequence[str]] = None) -> 'RKGNNModel':
        """Build a model from :meth:`to_dict` output, validating everything (ValueError)."""
        return files.model_from_dict(cls, d, joint_names)

    @classmethod
    def from_yaml(cls, text, joint_names=None) -> 'RKGNNModel':
        """Parse YAML text (see :meth:`from_dict`)."""
        return files.model_from_yaml(cls, text, joint_names)

    def save(self, path) -> None:
        """Write the model atomically: temp file in the same folder, fsync, os.replace."""
        files.save_text_atomic(path, self.to_yaml())

    @classmethod
    def load(cls, path, joint_names=None) -> 'RKGNNModel':
        """Read a model written by :meth:`save` (ValueError if it is unusable)."""
        with open(path, 'r', encoding='utf-8') as f:
            text = f.read()
        return cls.from_yaml(text, joint_names)

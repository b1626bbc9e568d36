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
The function network N_f evaluated in numpy, batched over a population: the reference.

:class:`BatchedNetwork` computes M, V, G, F, the torque and ẋ = N_f(x, u) for every model
of a decoded population (:class:`.params.NetworkParams`) at once, in plain numpy. It is the
reference that the compiled kernels (:mod:`.kernels`) are held to, and what the identified
model (:class:`.model.RKGNNModel`) uses for its terms. The features come from the bases'
numpy implementations (:mod:`.basis`).
"""

import numpy as np

from .basis import registry
from .scales import Scales
from .spec import NetworkSpec
from ..servo_law import pd_torque


def _parts(spec):
    """Yield (basis, its slice of the features, its codes, its data width) in order."""
    codes = registry.table(spec)[-1]
    start = 0
    for basis in spec.bases:
        size = basis.size(spec)
        yield basis, slice(start, start + size), codes[start:start + size], basis.data_width(spec)
        start += size


def features(spec: NetworkSpec, params, theta):
    """
    Return the features of the bases of ``spec`` (numpy reference), shape (S, F).

    Parameters
    ----------
    spec : NetworkSpec
        Network structure.
    params : NetworkParams
        Decoded population (leading dimension P).
    theta : ndarray, shape (S, n)
        One state per model (S = P), or any number of states for one model (P = 1).

    """
    data = params.features
    return np.concatenate([basis.features(theta, codes, data[:, sl, :width])
                           for basis, sl, codes, width in _parts(spec)], axis=1)


def feature_gradients(spec: NetworkSpec, params, theta, phi):
    """Return ∂φ_f/∂θ_k of the bases of ``spec``, shape (S, F, n), given ``phi`` (S, F)."""
    data = params.features
    return np.concatenate([basis.gradients(theta, codes, data[:, sl, :width], phi[:, sl])
                           for basis, sl, codes, width in _parts(spec)], axis=1)


def pair_products(theta_dot):
    """[θ̇θ̇] of eq. (5): θ̇_j θ̇_k for j < k, shape (..., n(n-1)/2)."""
    n = theta_dot.shape[-1]
    j, k = np.triu_indices(n, 1)
    return theta_dot[..., j] * theta_dot[..., k]


class BatchedNetwork:
    """
    N_f for a whole population at once (numpy reference implementation).

    Parameters
    ----------
    spec : NetworkSpec
        Structure.
    params : NetworkParams
        Output of :meth:`NetworkSpec.decode` (leading dimension P).
    scales : Scales
        The scales used for decoding (needed for ε and for normalised minors).
    kp, kd : array_like, shape (n,), optional
        Known PD gains (case 'pd_gains').

    """

    def __init__(self, spec: NetworkSpec, params, scales: Scales, kp=None, kd=None):
        self.spec = spec
        self.p = params
        self.n = spec.n_joints
        self.slices = spec.output_slices()
        self.eps = spec.inertia_epsilon(scales)
        self.inertia_scale = scales.inertia
        n = self.n
        if spec.inertia == 'penalty':
            self.tri = np.triu_indices(n)
        else:
            self.tri = np.tril_indices(n)
        self.kp_known = None if kp is None else np.asarray(kp, dtype=float)
        self.kd_known = None if kd is None else np.asarray(kd, dtype=float)
        if spec.case == 'pd_gains' and (self.kp_known is None or self.kd_known is None):
            raise ValueError("case 'pd_gains' needs kp and kd")

    def features(self, theta):
        """Return the bases' features, ``theta`` (S, n) -> (S, F) (S = P, or any if P = 1)."""
        return features(self.spec, self.p, theta)

    def feature_gradients(self, theta, phi):
        """Return ∂φ_f/∂θ_k, shape (S, F, n), given the features ``phi`` (S, F)."""
        return feature_gradients(self.spec, self.p, theta, phi)

    def theta_outputs(self, theta):
        """θ outputs, ``theta`` shape (P, n) -> (P, n_out)."""
        p = self.p
        # one model (P = 1) broadcasts over any number of states, else one state per model
        phi = self.features(theta)                                      # (P, F)
        if p.weights.shape[0] == phi.shape[0]:
            # same summation order as the compiled kernel (BLAS matmul may use FMA)
            return np.einsum('pk,pok->po', phi, p.weights) + p.bias
        return np.matmul(p.weights, phi[:, :, None])[:, :, 0] + p.bias

    def mass_matrix(self, theta):
        """M(θ) for each individual, ``theta`` shape (P, n) -> (P, n, n)."""
        return self._assemble_mass(self.theta_outputs(theta))

    def mass_derivatives(self, theta):
        """∂M/∂θ_k for each individual: ``theta`` (P, n) -> (P, n (k), n, n)."""
        p = self.p
        n = self.n
        dphi = self.feature_gradients(theta, self.features(theta))     # (P, F, n)
        sl = self.slices['inertia']
        w = p.weights[:, sl, :]
        if w.shape[0] == theta.shape[0]:
            dtri = np.einsum('pok,pkn->pno', w, dphi)
        else:
            dtri = np.matmul(np.swapaxes(dphi, 1, 2), np.swapaxes(w[0], 0, 1)[None])
        pop = theta.shape[0]
        dmat = np.zeros((pop, n, n, n))
        dmat[:, :, self.tri[0], self.tri[1]] = dtri
        if self.spec.inertia == 'penalty':
            dmat[:, :, self.tri[1], self.tri[0]] = dtri
            return dmat
        lmat = np.zeros((pop, n, n))
        lmat[:, self.tri[0], self.tri[1]] = self.theta_outputs(theta)[:, sl]
        dl_lt = np.matmul(dmat, np.swapaxes(lmat, 1, 2)[:, None])
        return dl_lt + np.swapaxes(dl_lt, 2, 3)

    def _assemble_mass(self, out):
        n = self.n
        tri = out[:, self.slices['inertia']]
        mat = np.zeros((out.shape[0], n, n))
        mat[:, self.tri[0], self.tri[1]] = tri
        if self.spec.inertia == 'penalty':
            mat[:, self.tri[1], self.tri[0]] = tri
            return mat
        return mat @ np.swapaxes(mat, 1, 2) + np.diag(self.eps)

    def torque(self, x, u):
        """Joint torque τ for states ``x`` (P, 2n) and input ``u`` (see :meth:`rhs`)."""
        n = self.n
        case = self.spec.case
        if case == 'torque':
            return np.broadcast_to(u, (x.shape[0], n))
        err = u[..., :n] - x[:, :n]
        derr = u[..., n:] - x[:, n:]
        if case == 'pd_gains':
            return pd_torque(self.kp_known, self.kd_known, err, derr)
        p = self.p
        tau = pd_torque(p.kp, p.kd, err, derr)
        for e, centres, inv_width2, weights in (
                (err, p.p_centres, p.p_inv_width2, p.p_weights),
                (derr, p.d_centres, p.d_inv_width2, p.d_weights)):
            phi = np.exp(-np.square(e[:, :, None] - centres) * inv_width2)
            tau = tau + np.sum(weights * phi, axis=-1)
        return tau

    def terms(self, x, u):
        """Return M, V, G, F and τ at states ``x`` (P, 2n): a dict of arrays."""
        n = self.n
        theta, theta_dot = x[:, :n], x[:, n:]
        out = self.theta_outputs(theta)
        sl = self.slices
        pop = x.shape[0]
        if self.spec.velocity == 'christoffel':
            dmat = self.mass_derivatives(theta)  # dmat[p, k, i, j] = ∂M_ij / ∂θ_k
            v = (np.einsum('pk,pkij,pj->pi', theta_dot, dmat, theta_dot)
                 - 0.5 * np.einsum('pj,pijk,pk->pi', theta_dot, dmat, theta_dot))
        else:
            b = out[:, sl['coriolis']].reshape(pop, n, self.spec.n_pairs)
            c = out[:, sl['centrifugal']].reshape(pop, n, n)
            v = (np.einsum('pij,pj->pi', b, pair_products(theta_dot))
                 + np.einsum('pij,pj->pi', c, np.square(theta_dot)))
        f = (self.p.viscous * theta_dot
             + self.p.coulomb * np.tanh(theta_dot / self.spec.coulomb_velocity))
        return {'M': self._assemble_mass(out), 'V': v, 'G': out[:, sl['gravity']], 'F': f,
                'tau': self.torque(x, u)}

    def rhs(self, x, u):
        """
        ẋ = N_f(x, u).

        Parameters
        ----------
        x : ndarray, shape (P, 2n)
            States [θ, θ̇].
        u : ndarray
            Case 'torque': τ, shape (n,) or (P, n). Otherwise [θd, θ̇d], shape (2n,).

        Returns
        -------
        ndarray, shape (P, 2n)

        """
        t = self.terms(x, u)
        rhs = (t['tau'] - t['V'] - t['G'] - t['F'])[..., None]
        with np.errstate(all='ignore'):
            try:
                acc = np.linalg.solve(t['M'], rhs)[..., 0]
            except np.linalg.LinAlgError:
                acc = np.full(rhs.shape[:-1], np.nan)
                for i in range(x.shape[0]):
                    try:
                        acc[i] = np.linalg.solve(t['M'][i], rhs[i])[:, 0]
                    except np.linalg.LinAlgError:
                        pass
        return np.concatenate([x[:, self.n:], acc], axis=1)

    def min_minor(self, theta):
        """Smallest leading principal minor of the normalised M(θ), shape (P,)."""
        mat = self.mass_matrix(theta)
        norm = 1.0 / np.sqrt(self.inertia_scale)
        mat = mat * norm[:, None] * norm[None, :]
        minors = [np.linalg.det(mat[:, :k, :k]) for k in range(1, self.n + 1)]
        return np.min(np.stack(minors, axis=1), axis=1)

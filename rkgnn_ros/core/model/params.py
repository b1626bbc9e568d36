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
The decoded network as named records: what the compiled kernels and the numpy reference take.

:func:`decode` maps a population of normalised genomes to one :class:`NetworkParams` (every
array with a leading population axis P), in one place; :func:`constants` collects what the
kernels need besides the genome (:class:`NetworkConstants`: the case, the structure, the
feature table of the bases, the known gains). Both are ``NamedTuple`` records of arrays, which
numba passes whole, so no kernel takes dozens of positional arrays and none unpacks a
record by position. :func:`individual` takes one model's row of a population record inside
compiled code (private copies, so parallel threads never share a reference count).
"""

from typing import NamedTuple

from numba import njit
import numpy as np

from .basis import registry
from .basis.rbf import LOG_WIDTH_LIMIT

CASE_IDS = {'torque': 0, 'pd_gains': 1, 'unknown': 2}


class NetworkParams(NamedTuple):
    """
    Physical parameters of a population of networks (leading axis P; one model: P = 1).

    Attributes
    ----------
    features : ndarray, shape (P, F, D)
        The bases' decoded parameters per feature (RBF: centre (n) and 1/width²).
    weights : ndarray, shape (P, n_out, F)
        Weights of the features in each θ output.
    bias : ndarray, shape (P, n_out)
        Constant of each θ output (zero without ``bias``).
    viscous, coulomb : ndarray, shape (P, n)
        Friction coefficients.
    p_centres, p_inv_width2, p_weights, d_centres, d_inv_width2, d_weights : ndarray
        The case-3 P and D RBF sub-networks, shape (P, n, Kt) (Kt = 0 otherwise).
    kp, kd : ndarray, shape (P, n)
        Linear gains of the torque network (zero when absent).

    """

    features: np.ndarray
    weights: np.ndarray
    bias: np.ndarray
    viscous: np.ndarray
    coulomb: np.ndarray
    p_centres: np.ndarray
    p_inv_width2: np.ndarray
    p_weights: np.ndarray
    d_centres: np.ndarray
    d_inv_width2: np.ndarray
    d_weights: np.ndarray
    kp: np.ndarray
    kd: np.ndarray

    def take(self, rows) -> 'NetworkParams':
        """Return the models ``rows`` (an index array or slice), contiguous."""
        return NetworkParams(*(np.ascontiguousarray(a[rows]) for a in self))

    def repeat(self, count) -> 'NetworkParams':
        """Return every model repeated ``count`` times in a row (one row per state)."""
        return NetworkParams(*(np.repeat(a, count, axis=0) for a in self))


class NetworkConstants(NamedTuple):
    """
    What the compiled kernels need besides the genome, for one structure, scales and gains.

    Attributes
    ----------
    case_id : int
        0 torque, 1 PD gains known, 2 unknown controller.
    chol : bool
        M = L Lᵀ + diag(eps) from the inertia outputs (else they are M's upper triangle).
    christ : bool
        V from the Christoffel symbols of M (else the learned B and C outputs).
    bases : ndarray of int64, shape (B,)
        Kind codes of the bases (:mod:`.basis.registry`).
    starts : ndarray of int64, shape (B + 1,)
        Where each basis's features start; the last entry is F.
    kinds : ndarray of int64, shape (F,)
        Kind code of every feature.
    codes : ndarray of int64, shape (F, n)
        Fixed integer table of the features.
    work_rows, work_cols : int
        Shape of the bases' work table.
    inlined : bool
        Only the basis that the kernels inline (:func:`.basis.registry.inlined_only`).
    kp_known, kd_known : ndarray, shape (n,)
        Known PD gains (case 2; zeros otherwise).
    eps : ndarray, shape (n,)
        The Cholesky floor ε.
    inv_sqrt_ms : ndarray, shape (n,)
        1/sqrt(inertia scale), which normalises M for the leading-minor penalty.
    coulomb_velocity : float
        v_c of the smoothed Coulomb friction.

    """

    case_id: int
    chol: bool
    christ: bool
    bases: np.ndarray
    starts: np.ndarray
    kinds: np.ndarray
    codes: np.ndarray
    work_rows: int
    work_cols: int
    inlined: bool
    kp_known: np.ndarray
    kd_known: np.ndarray
    eps: np.ndarray
    inv_sqrt_ms: np.ndarray
    coulomb_velocity: float


def decode(spec, genomes, scales) -> NetworkParams:
    """
    Map normalised genomes to physical network parameters.

    Parameters
    ----------
    spec : NetworkSpec
        Network structure.
    genomes : ndarray, shape (P, N) or (N,)
        Normalised genomes.
    scales : Scales
        Physical scales of the data.

    Returns
    -------
    NetworkParams
        C-contiguous arrays with leading dimension P.

    """
    genomes = np.asarray(genomes, dtype=float)
    if genomes.ndim == 1:
        genomes = genomes[None, :]
    if genomes.ndim != 2 or genomes.shape[1] != spec.genome_size:
        raise ValueError(f'genomes must have shape (P, {spec.genome_size}), '
                         f'got {genomes.shape}')
    n, kt = spec.n_joints, int(spec.torque_units)
    pop = genomes.shape[0]
    s = scales
    blk = {b.name: genomes[:, b.start:b.stop].reshape((pop,) + b.shape)
           for b in spec.blocks()}
    out_scale = spec.output_scales(s)
    bases = spec.bases
    width = max([b.data_width(spec) for b in bases] + [1])
    features = np.zeros((pop, spec.n_features, width))
    start = 0
    for basis in bases:
        data = basis.decode(spec, blk, s)
        features[:, start:start + data.shape[1], :data.shape[2]] = data
        start += data.shape[1]
    weights = out_scale[None, :, None] * blk['theta_weights']
    bias = (out_scale * blk['theta_bias'] if spec.bias else np.zeros((pop, out_scale.size)))
    if spec.friction:
        # friction dissipates: both coefficients are |g| (never negative damping)
        viscous = 0.1 * s.torque / s.velocity * np.abs(blk['friction'][:, 0])
        coulomb = 0.1 * s.torque * np.abs(blk['friction'][:, 1])
    else:
        viscous = coulomb = np.zeros((pop, n))
    torque_nets = {}
    for name, scale_in in (('p', s.error), ('d', s.error_rate)):
        if spec.case == 'unknown' and kt > 0:
            net = blk[f'{name}_net']
            torque_nets[name] = (scale_in[:, None] * net[:, 0],
                                 np.exp(-2.0 * np.clip(net[:, 1], -LOG_WIDTH_LIMIT,
                                                       LOG_WIDTH_LIMIT)) / scale_in[:, None] ** 2,
                                 s.torque[:, None] * net[:, 2])
        else:
            torque_nets[name] = (np.zeros((pop, n, 0)),) * 3
    if spec.case == 'unknown' and spec.torque_linear:
        kp = s.torque / s.error * blk['pd_linear'][:, 0]
        kd = s.torque / s.error_rate * blk['pd_linear'][:, 1]
    else:
        kp = kd = np.zeros((pop, n))
    c = np.ascontiguousarray
    return NetworkParams(
        features=c(features), weights=c(weights), bias=c(bias), viscous=c(viscous),
        coulomb=c(coulomb), p_centres=c(torque_nets['p'][0]),
        p_inv_width2=c(torque_nets['p'][1]), p_weights=c(torque_nets['p'][2]),
        d_centres=c(torque_nets['d'][0]), d_inv_width2=c(torque_nets['d'][1]),
        d_weights=c(torque_nets['d'][2]), kp=c(kp), kd=c(kd))


def constants(spec, scales, kp=None, kd=None) -> NetworkConstants:
    """
    Return the kernels' genome-independent inputs for a structure, its scales and gains.

    Parameters
    ----------
    spec : NetworkSpec
        Network structure.
    scales : Scales
        The scales the genomes are decoded with.
    kp, kd : array_like, shape (n,), optional
        Known PD gains (case 'pd_gains'; zeros otherwise).

    """
    n = spec.n_joints
    bases, starts, kinds, codes = registry.table(spec)
    rows, cols = registry.work_shape(spec)

    def gains(value):
        if value is None:
            return np.zeros(n)
        return np.ascontiguousarray(np.asarray(value, dtype=float).reshape(-1))

    return NetworkConstants(
        case_id=CASE_IDS[spec.case], chol=spec.inertia == 'cholesky',
        christ=spec.velocity == 'christoffel', bases=bases, starts=starts, kinds=kinds,
        codes=codes,
        work_rows=int(rows), work_cols=int(cols), inlined=registry.inlined_only(spec),
        kp_known=gains(kp), kd_known=gains(kd),
        eps=np.ascontiguousarray(spec.inertia_epsilon(scales)),
        inv_sqrt_ms=np.ascontiguousarray(1.0 / np.sqrt(scales.inertia)),
        coulomb_velocity=float(spec.coulomb_velocity))


@njit(cache=True, nogil=True)
def individual(params, p):
    """Return model ``p`` of a population record as a record of private copies."""
    return NetworkParams(
        params.features[p].copy(), params.weights[p].copy(), params.bias[p].copy(),
        params.viscous[p].copy(), params.coulomb[p].copy(), params.p_centres[p].copy(),
        params.p_inv_width2[p].copy(), params.p_weights[p].copy(), params.d_centres[p].copy(),
        params.d_inv_width2[p].copy(), params.d_weights[p].copy(), params.kp[p].copy(),
        params.kd[p].copy())

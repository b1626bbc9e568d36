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
The function network N_f of the paper, its genome layout and a batched numpy evaluation.

N_f maps the state x = [θ, θ̇] (and the input u) to ẋ = [θ̇, θ̈] with

    θ̈ = M(θ)⁻¹ (τ - V(θ, θ̇) - G(θ) - F(θ̇)),   V = B(θ)[θ̇θ̇] + C(θ)[θ̇²].

Every θ-dependent term (the upper triangle of M, B, C, G) is the output of shape-adaptive
Gaussian RBF units over θ (eqs. 7-8): ``phi_l = exp(-|θ - c_l|² / s_l²)``. The units are
shared by all those outputs, which is what gives the paper's genome size: with 3 units and
3 joints, 3 × (3 centre + 1 width + 27 weights) = 93, plus viscous and Coulomb friction per
joint = 99 elements (cases 1 and 2). The torque network of case 3 adds, per joint, a P and a
D RBF sub-network of scalar input (θd - θ and θ̇d - θ̇) with 3 units of (centre, width,
weight): 3 × 2 × 3 × 3 = 54, so 153 elements.

Options beyond the paper (all off in ``NetworkSpec.paper``): a constant term per output
(``bias``: an RBF unit of infinite width; without it M vanishes far from the centres),
M = L Lᵀ + εI with L's lower triangle as the RBF outputs (``inertia='cholesky'``: symmetric
positive definite by construction, as in DeLaN) and linear P and D gains beside the RBF
torque sub-networks (``torque_linear``).

The genome is normalised: every element is of order one and is mapped to physical units by
the :class:`Scales` of the data (RMS torque, velocity, acceleration, spread of θ), so that
one mutation spread suits every element and the search does not depend on units.

Case 3 has a gauge freedom: scaling M, V, G, F and the torque network by one factor leaves
the motion unchanged, so without torque the absolute scale is not identifiable. The torque
scale is then fixed to 1 N m (``Scales.from_datasets``); identified gains are relative.
"""

from dataclasses import asdict, dataclass
from typing import Dict, List, Sequence, Tuple

import numpy as np

CASES = ('torque', 'pd_gains', 'unknown')
INERTIA_MODES = ('penalty', 'cholesky')
VELOCITY_MODES = ('learned', 'christoffel')


@dataclass(frozen=True)
class Scales:
    """
    Physical scales that map the normalised genome to physical units, one value per joint.

    Attributes
    ----------
    theta_center, theta_spread : ndarray, shape (n,)
        Mean and standard deviation of θ (rad): where RBF centres start and how far apart.
    velocity, acceleration : ndarray, shape (n,)
        RMS of θ̇ (rad/s) and of θ̈ (rad/s²).
    torque : ndarray, shape (n,)
        RMS of τ (N m); 1 in case 3, where it is not identifiable.
    error, error_rate : ndarray, shape (n,)
        RMS of θd - θ and of θ̇d - θ̇ (inputs of the torque network).

    """

    theta_center: np.ndarray
    theta_spread: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray
    torque: np.ndarray
    error: np.ndarray
    error_rate: np.ndarray

    def __post_init__(self):
        n = None
        for name, value in asdict(self).items():
            arr = np.asarray(value, dtype=float).reshape(-1)
            if n is None:
                n = arr.size
            if arr.size != n or not np.all(np.isfinite(arr)):
                raise ValueError(f'Scales.{name} must be {n} finite values, got {value!r}')
            if name != 'theta_center' and np.any(arr <= 0.0):
                raise ValueError(f'Scales.{name} must be positive, got {arr.tolist()}')
            object.__setattr__(self, name, arr)

    @property
    def inertia(self) -> np.ndarray:
        """Inertia scale per joint, torque / acceleration (kg m²), shape (n,)."""
        return self.torque / self.acceleration

    @classmethod
    def from_datasets(cls, datasets, case, kp=None, kd=None) -> 'Scales':
        """Measure the scales on a list of :class:`~rkgnn_ros.core.data.Dataset`."""
        if case == 'torque' and any(d.tau is None for d in datasets):
            raise ValueError("case 'torque' needs measured torque (Dataset.tau)")
        if case in ('pd_gains', 'unknown') and any(
                d.theta_d is None or d.theta_d_dot is None for d in datasets):
            raise ValueError(f'case {case!r} needs the desired trajectory '
                             '(Dataset.theta_d, theta_d_dot)')
        theta = np.vstack([d.theta for d in datasets])
        theta_dot = np.vstack([d.theta_dot for d in datasets])
        acc = np.vstack([np.gradient(d.theta_dot, d.dt, axis=0) for d in datasets])
        n = theta.shape[1]
        floor = 1e-3

        def rms(a, low=floor):
            return np.maximum(np.sqrt(np.mean(np.square(a), axis=0)), low)

        if case in ('pd_gains', 'unknown'):
            err = np.vstack([d.theta_d - d.theta for d in datasets])
            derr = np.vstack([d.theta_d_dot - d.theta_dot for d in datasets])
        else:
            err = derr = np.ones((1, n))
        if case == 'torque':
            torque = rms(np.vstack([d.tau for d in datasets]))
        elif case == 'pd_gains':
            torque = rms(err * np.asarray(kp, dtype=float) + derr * np.asarray(kd, dtype=float))
        else:
            torque = np.ones(n)
        return cls(theta_center=theta.mean(axis=0),
                   theta_spread=np.maximum(theta.std(axis=0), 0.05),
                   velocity=rms(theta_dot, 0.05), acceleration=rms(acc, 0.5),
                   torque=torque, error=rms(err), error_rate=rms(derr))

    def to_dict(self) -> Dict[str, list]:
        """Plain lists, for YAML."""
        return {k: np.asarray(v).tolist() for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d) -> 'Scales':
        """Inverse of :meth:`to_dict`; raises ValueError on missing or bad entries."""
        names = ('theta_center', 'theta_spread', 'velocity', 'acceleration', 'torque',
                 'error', 'error_rate')
        missing = [k for k in names if k not in d]
        if missing:
            raise ValueError(f'scales: missing {missing}')
        return cls(**{k: d[k] for k in names})


@dataclass(frozen=True)
class Block:
    """One named slice of the genome: ``genome[..., start:stop]`` reshaped to ``shape``."""

    name: str
    shape: Tuple[int, ...]
    start: int

    @property
    def size(self) -> int:
        """Return the number of genome elements."""
        return int(np.prod(self.shape))

    @property
    def stop(self) -> int:
        """End of the slice."""
        return self.start + self.size


@dataclass(frozen=True)
class NetworkSpec:
    """
    Structure of the function network N_f (everything that fixes the genome layout).

    Parameters
    ----------
    n_joints : int
        Number of joints n.
    case : str
        'torque' (case 1: measured torque), 'pd_gains' (case 2: known PD gains) or
        'unknown' (case 3: a torque network learns the controller).
    theta_units : int
        Gaussian RBF units over θ, shared by M, B, C and G (paper: 3).
    torque_units : int
        RBF units of each per-joint P and D sub-network (case 3; paper: 3).
    inertia : str
        'penalty' (the paper: upper triangle of M, penalised when a leading principal minor
        is negative) or 'cholesky' (M = L Lᵀ + εI, positive definite by construction).
    bias : bool
        Add a constant to every θ-dependent output.
    friction : bool
        Viscous and Coulomb friction per joint (F = f_v θ̇ + f_c tanh(θ̇ / v_c)).
    torque_linear : bool
        Linear P and D gains beside the RBF torque sub-networks (case 3).
    velocity : str
        'learned' (the paper: B and C are RBF outputs of their own) or 'christoffel'
        (V = Ṁθ̇ - ½ ∂(θ̇ᵀMθ̇)/∂θ from the Christoffel symbols of the identified M, as for any
        rigid-body arm: the model is then energy-consistent, so M positive definite and
        dissipative friction make it passive and stable under PD control).
    coulomb_velocity : float
        v_c of the smoothed Coulomb friction (rad/s).
    inertia_floor : float
        ε of M = L Lᵀ + diag(ε) as a fraction of the inertia scale ('cholesky'). A floor
        keeps identified models from growing needlessly stiff (a tiny eigenvalue of M makes
        the closed loop's fastest mode exceed what the RKG step can integrate).

    """

    n_joints: int
    case: str = 'torque'
    theta_units: int = 3
    torque_units: int = 3
    inertia: str = 'penalty'
    bias: bool = False
    friction: bool = True
    torque_linear: bool = False
    velocity: str = 'learned'
    coulomb_velocity: float = 0.05
    inertia_floor: float = 1e-3

    def __post_init__(self):
        if not isinstance(self.n_joints, (int, np.integer)) or self.n_joints < 1:
            raise ValueError(f'n_joints must be an integer >= 1, got {self.n_joints!r}')
        if self.case not in CASES:
            raise ValueError(f'case must be one of {CASES}, got {self.case!r}')
        if self.inertia not in INERTIA_MODES:
            raise ValueError(f'inertia must be one of {INERTIA_MODES}, got {self.inertia!r}')
        if self.velocity not in VELOCITY_MODES:
            raise ValueError(f'velocity must be one of {VELOCITY_MODES}, got {self.velocity!r}')
        if int(self.theta_units) < 0 or int(self.torque_units) < 0:
            raise ValueError('theta_units and torque_units must be >= 0')
        if self.theta_units == 0 and not self.bias:
            raise ValueError('theta_units = 0 needs bias = true (M would be zero)')
        if self.case == 'unknown' and self.torque_units == 0 and not self.torque_linear:
            raise ValueError("case 'unknown' needs torque_units > 0 or torque_linear = true")
        if not (np.isfinite(self.inertia_floor) and 0.0 < self.inertia_floor < 1.0):
            raise ValueError(f'inertia_floor must be in (0, 1), got {self.inertia_floor}')
        if not (np.isfinite(self.coulomb_velocity) and self.coulomb_velocity > 0):
            raise ValueError(f'coulomb_velocity must be > 0, got {self.coulomb_velocity}')

    @classmethod
    def paper(cls, n_joints=3, case='torque') -> 'NetworkSpec':
        """Return the paper's structure: 99 genome elements for 3 joints, 153 in case 3."""
        return cls(n_joints=n_joints, case=case)

    @classmethod
    def recommended(cls, n_joints=3, case='torque') -> 'NetworkSpec':
        """
        Return our default structure.

        M = L Lᵀ + εI (positive definite by construction), V from M's Christoffel symbols
        (energy-consistent), constant terms beside the RBF units and linear PD gains beside
        the torque sub-networks.
        """
        return cls(n_joints=n_joints, case=case, theta_units=3, torque_units=2,
                   inertia='cholesky', bias=True, torque_linear=True, velocity='christoffel',
                   inertia_floor=0.05)

    def to_dict(self) -> dict:
        """Plain values, for YAML."""
        return {k: (v.item() if isinstance(v, np.generic) else v)
                for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d) -> 'NetworkSpec':
        """Inverse of :meth:`to_dict`."""
        fields = cls.__dataclass_fields__
        unknown = set(d) - set(fields)
        if unknown:
            raise ValueError(f'network: unknown settings {sorted(unknown)}')
        return cls(**d)

    # ----- output layout of the θ-RBF units
    @property
    def n_pairs(self) -> int:
        """n(n-1)/2: the products θ̇_j θ̇_k, j < k."""
        n = self.n_joints
        return n * (n - 1) // 2

    @property
    def n_inertia(self) -> int:
        """n(n+1)/2: entries of M's upper triangle (or of L's lower triangle)."""
        n = self.n_joints
        return n * (n + 1) // 2

    @property
    def n_outputs(self) -> int:
        """Return the θ-RBF output count: inertia, B (n × n(n-1)/2), C (n × n), G (n)."""
        n = self.n_joints
        if self.velocity == 'christoffel':
            return self.n_inertia + n
        return self.n_inertia + n * self.n_pairs + n * n + n

    def output_slices(self) -> Dict[str, slice]:
        """Where each term sits in the θ-RBF output vector."""
        n = self.n_joints
        a = self.n_inertia
        learned = self.velocity == 'learned'
        b = a + n * self.n_pairs * learned
        c = b + n * n * learned
        return {'inertia': slice(0, a), 'coriolis': slice(a, b),
                'centrifugal': slice(b, c), 'gravity': slice(c, c + n)}

    def blocks(self) -> List[Block]:
        """Return the genome layout, in order."""
        n, k, kt = self.n_joints, int(self.theta_units), int(self.torque_units)
        shapes = [('theta_centres', (k, n)), ('theta_widths', (k,)),
                  ('theta_weights', (self.n_outputs, k))]
        if self.bias:
            shapes.append(('theta_bias', (self.n_outputs,)))
        if self.friction:
            shapes.append(('friction', (2, n)))
        if self.case == 'unknown':
            if kt > 0:
                shapes += [('p_net', (3, n, kt)), ('d_net', (3, n, kt))]
            if self.torque_linear:
                shapes.append(('pd_linear', (2, n)))
        blocks, start = [], 0
        for name, shape in shapes:
            block = Block(name, shape, start)
            blocks.append(block)
            start = block.stop
        return blocks

    @property
    def genome_size(self) -> int:
        """Return the number of genome elements."""
        return self.blocks()[-1].stop

    def initial_genome(self, rng=None) -> np.ndarray:
        """
        Return a sensible starting genome, shape (N,).

        Centres spread over ±1.5 spreads of θ (random if ``rng`` is given, else on a fixed
        low-discrepancy pattern), unit widths, zero weights except those that make M the
        diagonal inertia scale and the linear gains (if any) moderately positive.
        """
        g = np.zeros(self.genome_size)
        b = {blk.name: blk for blk in self.blocks()}
        k, n = int(self.theta_units), self.n_joints
        if k:
            if rng is not None:
                centres = rng.uniform(-1.5, 1.5, size=(k, n))
            else:
                golden = (np.sqrt(5.0) - 1.0) / 2.0
                steps = golden + 0.318 * np.arange(n)
                centres = 3.0 * ((np.arange(1, k + 1)[:, None] * steps) % 1.0) - 1.5
            g[b['theta_centres'].start:b['theta_centres'].stop] = centres.ravel()
        diag = [self._tri_index(i, i) for i in range(n)]
        if self.bias:
            start = b['theta_bias'].start
            g[start + np.array(diag)] = 1.0
        elif k:
            w = np.zeros((self.n_outputs, k))
            w[diag, :] = 1.0
            g[b['theta_weights'].start:b['theta_weights'].stop] = w.ravel()
        if self.case == 'unknown':
            if self.torque_linear:
                start = b['pd_linear'].start
                g[start:start + 2 * n] = 1.0
            if 'p_net' in b:
                for name in ('p_net', 'd_net'):
                    arr = np.zeros((3, n, int(self.torque_units)))
                    arr[0] = np.linspace(-1.0, 1.0, int(self.torque_units))[None, :]
                    g[b[name].start:b[name].stop] = arr.ravel()
        return g

    def _tri_index(self, i, j) -> int:
        """Index of element (i, j) of the packed triangle (upper row-major, or lower)."""
        n = self.n_joints
        if self.inertia == 'penalty':
            i, j = min(i, j), max(i, j)
            return i * n - i * (i - 1) // 2 + (j - i)
        i, j = max(i, j), min(i, j)
        return i * (i + 1) // 2 + j

    # ----- decoding
    def decode(self, genomes, scales: Scales) -> Dict[str, np.ndarray]:
        """
        Map normalised genomes to physical network parameters.

        Parameters
        ----------
        genomes : ndarray, shape (P, N) or (N,)
            Normalised genomes.
        scales : Scales
            Physical scales of the data.

        Returns
        -------
        dict of ndarray, each with leading dimension P
            ``centres`` (P, K, n), ``inv_width2`` (P, K) = 1/s², ``weights`` (P, n_out, K),
            ``bias`` (P, n_out), ``viscous``/``coulomb`` (P, n), ``p_centres``,
            ``p_inv_width2``, ``p_weights``, ``d_...`` (P, n, Kt), ``kp``/``kd`` (P, n)
            (linear torque-network gains, zero when absent).

        """
        genomes = np.asarray(genomes, dtype=float)
        if genomes.ndim == 1:
            genomes = genomes[None, :]
        if genomes.ndim != 2 or genomes.shape[1] != self.genome_size:
            raise ValueError(f'genomes must have shape (P, {self.genome_size}), '
                             f'got {genomes.shape}')
        n, kt = self.n_joints, int(self.torque_units)
        pop = genomes.shape[0]
        s = scales
        blk = {b.name: genomes[:, b.start:b.stop].reshape((pop,) + b.shape)
               for b in self.blocks()}
        out_scale = self.output_scales(s)
        width0 = float(np.linalg.norm(s.theta_spread))
        p = {
            'centres': s.theta_center + s.theta_spread * blk['theta_centres'],
            'inv_width2': np.exp(-2.0 * blk['theta_widths']) / width0 ** 2,
            'weights': out_scale[None, :, None] * blk['theta_weights'],
            'bias': (out_scale * blk['theta_bias'] if self.bias
                     else np.zeros((pop, out_scale.size))),
        }
        if self.friction:
            # friction dissipates: both coefficients are |g| (never negative damping)
            p['viscous'] = 0.1 * s.torque / s.velocity * np.abs(blk['friction'][:, 0])
            p['coulomb'] = 0.1 * s.torque * np.abs(blk['friction'][:, 1])
        else:
            p['viscous'] = p['coulomb'] = np.zeros((pop, n))
        for name, scale_in in (('p', s.error), ('d', s.error_rate)):
            if self.case == 'unknown' and kt > 0:
                net = blk[f'{name}_net']
                p[f'{name}_centres'] = scale_in[:, None] * net[:, 0]
                p[f'{name}_inv_width2'] = np.exp(-2.0 * net[:, 1]) / scale_in[:, None] ** 2
                p[f'{name}_weights'] = s.torque[:, None] * net[:, 2]
            else:
                p[f'{name}_centres'] = np.zeros((pop, n, 0))
                p[f'{name}_inv_width2'] = np.zeros((pop, n, 0))
                p[f'{name}_weights'] = np.zeros((pop, n, 0))
        if self.case == 'unknown' and self.torque_linear:
            p['kp'] = s.torque / s.error * blk['pd_linear'][:, 0]
            p['kd'] = s.torque / s.error_rate * blk['pd_linear'][:, 1]
        else:
            p['kp'] = p['kd'] = np.zeros((pop, n))
        return p

    def output_scales(self, s: Scales) -> np.ndarray:
        """Physical scale of each θ-RBF output, shape (n_out,)."""
        n = self.n_joints
        ms = s.inertia
        inertia = np.empty(self.n_inertia)
        for i in range(n):
            for j in range(n):
                if (self.inertia == 'penalty' and j >= i) or (self.inertia == 'cholesky'
                                                              and j <= i):
                    idx = self._tri_index(i, j)
                    if self.inertia == 'penalty':
                        inertia[idx] = np.sqrt(ms[i] * ms[j])
                    else:  # L's row i scales like sqrt(M_ii)
                        inertia[idx] = np.sqrt(ms[i])
        if self.velocity == 'christoffel':
            return np.concatenate([inertia, s.torque])
        pairs = [(j, k) for j in range(n) for k in range(j + 1, n)]
        coriolis = np.array([s.torque[i] / (s.velocity[j] * s.velocity[k])
                             for i in range(n) for (j, k) in pairs])
        centrifugal = np.array([s.torque[i] / s.velocity[j] ** 2
                                for i in range(n) for j in range(n)])
        return np.concatenate([inertia, coriolis, centrifugal, s.torque])

    def inertia_epsilon(self, scales: Scales) -> np.ndarray:
        """ε of M = L Lᵀ + diag(ε) in the Cholesky mode, shape (n,)."""
        return self.inertia_floor * scales.inertia


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
    params : dict
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

    def theta_outputs(self, theta):
        """θ-RBF outputs, ``theta`` shape (P, n) -> (P, n_out)."""
        p = self.p
        # one model (P = 1) broadcasts over any number of states, else one state per model
        d2 = np.sum(np.square(theta[:, None, :] - p['centres']), axis=-1)  # (P, K)
        phi = np.exp(-d2 * p['inv_width2'])
        if p['weights'].shape[0] == phi.shape[0]:
            # same summation order as the compiled kernel (BLAS matmul may use FMA)
            return np.einsum('pk,pok->po', phi, p['weights']) + p['bias']
        return np.matmul(p['weights'], phi[:, :, None])[:, :, 0] + p['bias']

    def mass_matrix(self, theta):
        """M(θ) for each individual, ``theta`` shape (P, n) -> (P, n, n)."""
        return self._assemble_mass(self.theta_outputs(theta))

    def mass_derivatives(self, theta):
        """∂M/∂θ_k for each individual: ``theta`` (P, n) -> (P, n (k), n, n)."""
        p = self.p
        n = self.n
        diff = theta[:, None, :] - p['centres']  # (P, K, n)
        phi = np.exp(-np.sum(np.square(diff), axis=-1) * p['inv_width2'])
        dphi = phi[:, :, None] * (-2.0 * p['inv_width2'][:, :, None] * diff)  # (P, K, n)
        sl = self.slices['inertia']
        w = p['weights'][:, sl, :]
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
            return self.kp_known * err + self.kd_known * derr
        p = self.p
        tau = p['kp'] * err + p['kd'] * derr
        for name, e in (('p', err), ('d', derr)):
            phi = np.exp(-np.square(e[:, :, None] - p[f'{name}_centres'])
                         * p[f'{name}_inv_width2'])
            tau = tau + np.sum(p[f'{name}_weights'] * phi, axis=-1)
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
        f = (self.p['viscous'] * theta_dot
             + self.p['coulomb'] * np.tanh(theta_dot / self.spec.coulomb_velocity))
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


def genome_report(spec: NetworkSpec) -> List[Tuple[str, Tuple[int, ...], int]]:
    """(name, shape, size) of each genome block, for documentation and logs."""
    return [(b.name, b.shape, b.size) for b in spec.blocks()]


def check_genome(spec: NetworkSpec, genome: Sequence[float]) -> np.ndarray:
    """Validate one genome (finite, right length) and return it as an array."""
    g = np.asarray(genome, dtype=float).reshape(-1)
    if g.size != spec.genome_size:
        raise ValueError(f'genome has {g.size} elements, the network needs {spec.genome_size}')
    if not np.all(np.isfinite(g)):
        raise ValueError('genome contains NaN or inf')
    return g

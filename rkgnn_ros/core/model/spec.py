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
The structure of the function network N_f: everything that fixes the genome layout.

N_f maps the state x = [θ, θ̇] (and the input u) to ẋ = [θ̇, θ̈] with

    θ̈ = M(θ)⁻¹ (τ - V(θ, θ̇) - G(θ) - F(θ̇)),   V = B(θ)[θ̇θ̇] + C(θ)[θ̇²].

Every θ-dependent term (the upper triangle of M, B, C, G) is a linear combination of the
features of a basis over θ (:mod:`.basis`); the paper's is shape-adaptive Gaussian RBF units
(eqs. 7-8), shared by all those outputs, which is what gives the paper's genome size: with
3 units and 3 joints, 3 × (3 centre + 1 width + 27 weights) = 93, plus viscous and Coulomb
friction per joint = 99 elements (cases 1 and 2). The torque network of case 3 adds, per
joint, a P and a D RBF sub-network of scalar input (θd - θ and θ̇d - θ̇) with 3 units of
(centre, width, weight): 3 × 2 × 3 × 3 = 54, so 153 elements.

Options beyond the paper (all off in ``NetworkSpec.paper``): a constant term per output
(``bias``: an RBF unit of infinite width; without it M vanishes far from the centres),
M = L Lᵀ + εI with L's lower triangle as the outputs (``inertia='cholesky'``: symmetric
positive definite by construction, as in DeLaN), V from the Christoffel symbols of M
(``velocity='christoffel'``), linear P and D gains beside the RBF torque sub-networks
(``torque_linear``) and other bases (``basis``).

The genome is normalised (:mod:`.scales`); :meth:`NetworkSpec.decode` maps it to one named
record of physical parameters (:mod:`.params`).
"""

from dataclasses import asdict, dataclass
from typing import Dict, List, Sequence, Tuple

import numpy as np

from .basis import registry
from .params import constants, decode, NetworkConstants, NetworkParams
from .scales import Scales

CASES = ('torque', 'pd_gains', 'unknown')
INERTIA_MODES = ('penalty', 'cholesky')
VELOCITY_MODES = ('learned', 'christoffel')


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
        Gaussian RBF units over θ, shared by M, B, C and G (paper: 3); used by the 'rbf'
        basis.
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
    basis : str
        The features of the θ-dependent outputs: a registered basis ('rbf', the paper's;
        'poly') or a sum of them joined by '+' (:mod:`.basis.registry`).

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
    basis: str = 'rbf'

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
        registry.lookup(self.basis)
        if self.n_features == 0 and not self.bias:
            raise ValueError('theta_units = 0 needs bias = true (M would be zero): the '
                             f'basis {self.basis!r} has no features')
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

    # ----- the θ features and the outputs they feed
    @property
    def bases(self) -> tuple:
        """Return the basis objects of :attr:`basis`, in order."""
        return registry.lookup(self.basis)

    @property
    def n_features(self) -> int:
        """Return F, the θ features of all bases together."""
        return sum(b.size(self) for b in self.bases)

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
        """Return the θ-output count: inertia, B (n × n(n-1)/2), C (n × n), G (n)."""
        n = self.n_joints
        if self.velocity == 'christoffel':
            return self.n_inertia + n
        return self.n_inertia + n * self.n_pairs + n * n + n

    def output_slices(self) -> Dict[str, slice]:
        """Where each term sits in the θ-output vector."""
        n = self.n_joints
        a = self.n_inertia
        learned = self.velocity == 'learned'
        b = a + n * self.n_pairs * learned
        c = b + n * n * learned
        return {'inertia': slice(0, a), 'coriolis': slice(a, b),
                'centrifugal': slice(b, c), 'gravity': slice(c, c + n)}

    def blocks(self) -> List[Block]:
        """Return the genome layout, in order."""
        n, kt = self.n_joints, int(self.torque_units)
        shapes = [shape for basis in self.bases for shape in basis.blocks(self)]
        shapes.append(('theta_weights', (self.n_outputs, self.n_features)))
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

        The bases' own blocks from each basis (RBF centres spread over ±1.5 spreads of θ,
        random if ``rng`` is given, else on a fixed low-discrepancy pattern; unit widths),
        zero weights except those that make M the diagonal inertia scale and the linear
        gains (if any) moderately positive.
        """
        g = np.zeros(self.genome_size)
        b = {blk.name: blk for blk in self.blocks()}
        n = self.n_joints
        for basis in self.bases:
            for name, values in basis.initial(self, rng).items():
                g[b[name].start:b[name].stop] = np.asarray(values, dtype=float).ravel()
        diag = [self._tri_index(i, i) for i in range(n)]
        if self.bias:
            start = b['theta_bias'].start
            g[start + np.array(diag)] = 1.0
        elif self.n_features:
            w = np.zeros((self.n_outputs, self.n_features))
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
    def decode(self, genomes, scales: Scales) -> NetworkParams:
        """
        Map normalised genomes to physical network parameters (:func:`.params.decode`).

        ``genomes`` (P, N) or (N,) with the data's ``scales``, as :func:`.params.decode`
        takes them; returns one named record of arrays with leading dimension P.
        """
        return decode(self, genomes, scales)

    def constants(self, scales: Scales, kp=None, kd=None) -> NetworkConstants:
        """Return what the compiled kernels need besides the genome (:func:`.params.constants`)."""
        return constants(self, scales, kp, kd)

    def output_scales(self, s: Scales) -> np.ndarray:
        """Physical scale of each θ output, shape (n_out,)."""
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

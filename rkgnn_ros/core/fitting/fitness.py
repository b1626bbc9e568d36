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
Batched fitness of a population of RKGNN genomes: rollout error plus the inertia penalty.

The cost of one genome is the paper's eq. (11)::

    J = mean_i ( |θ_i - θ̂_i| + |θ̇_i - θ̂̇_i| ) + w_P · max(0, -min leading minor of M̂)

where θ̂ is the RKG rollout of N_f from the first measured state of each segment (or, with
multiple shooting, restarted from the measured state after every ``shooting`` samples),
the mean runs over every sample but the first of each segment, and the minors are those
of the inertia matrix normalised by its scale (dimensionless), taken at every rollout
state. A rollout that leaves the
plausible state range or turns non-finite costs +inf, never NaN.

Three implementations share one :class:`FitnessProblem`: ``cost_loop`` (a per-individual
Python loop), ``cost_numpy`` (batched over the population: the reference) and ``cost`` (the
compiled numba kernel of :mod:`rkgnn_ros.core.model.kernels`, which releases the GIL). Tests
hold them equal. The problem builds the kernels' genome-independent records once
(:class:`..model.kernels.Segments`, :class:`..model.params.NetworkConstants`); a generation
decodes its population into one :class:`..model.params.NetworkParams`.

A thread that must be able to stop mid-generation (the identifier's worker: a generation of
10,000 candidates over 600 s of data takes minutes; an offline fit at the end of its
wall-time budget) registers its stop event with :func:`interrupt_on`; ``cost`` and
``rollouts`` called from that thread then evaluate the population in chunks of about
:data:`CHUNK_S` seconds and raise :class:`Interrupted` between two once the event is set.
Such a thread may also register work to run between two chunks with :func:`between_chunks`
(the identifier checks for a change of the dynamics there, not only once a generation).
Other threads (benchmarks) evaluate in one call, as before.
"""

import threading
import time
from typing import Callable, List, NamedTuple, Optional, Sequence

import numpy as np

from ..data import Dataset
from ..integration.inputs import stage_inputs
from ..integration.rkg import rkg_step
from ..model.network import BatchedNetwork
from ..model.scales import Scales
from ..model.spec import NetworkSpec

#: Seconds of kernel time per chunk of a population evaluated by a thread with an interrupt.
CHUNK_S = 0.25

_interrupts = threading.local()


class Interrupted(Exception):
    """The calling thread's stop event was set during an evaluation (:func:`interrupt_on`)."""


def interrupt_on(event) -> Optional[object]:
    """
    Let ``event`` interrupt the calling thread's population evaluations (None: never).

    ``event`` is anything with ``is_set()`` (a ``threading.Event``, a
    :class:`~.budget.Budget`). From then on :meth:`FitnessProblem.cost` and
    :meth:`FitnessProblem.rollouts` called from this thread check it between chunks of
    about :data:`CHUNK_S` seconds and raise :class:`Interrupted` once it is set, so a
    thread that owns a search stops within a chunk, not a whole generation. Returns the
    event registered before (to restore it).
    """
    previous = getattr(_interrupts, 'event', None)
    _interrupts.event = event
    return previous


def between_chunks(callback: Optional[Callable[[], None]]) -> Optional[Callable[[], None]]:
    """
    Let ``callback()`` run between two chunks of the calling thread's evaluations (None: no).

    Only a thread with an interrupt event (:func:`interrupt_on`) evaluates in chunks, so
    ``callback`` runs about every :data:`CHUNK_S` seconds of a generation; it may raise
    :class:`Interrupted` (or a subclass) to end the evaluation there. Returns the callback
    registered before (to restore it).
    """
    previous = getattr(_interrupts, 'between', None)
    _interrupts.between = callback
    return previous


def _chunked(evaluate, params, event, problem) -> np.ndarray:
    """
    Evaluate ``params`` in chunks of about CHUNK_S s; raise Interrupted once ``event``.

    A chunk holds at least one candidate per numba thread (the kernels run the population
    in parallel); the first, that many, times the rest. An event with a ``left()`` (a
    :class:`~.budget.Budget`) also stops before a chunk that the seconds per candidate
    measured so far (``problem.seconds_per_candidate``, the largest: a candidate that
    diverges early is quick) say would end past it. Between two chunks the thread's
    :func:`between_chunks` callback runs.
    """
    import numba
    pop = params.weights.shape[0]
    out = None
    least = max(1, int(numba.get_num_threads()))
    left = getattr(event, 'left', None)
    between = getattr(_interrupts, 'between', None)
    per = problem.seconds_per_candidate
    start, size = 0, least
    while start < pop:
        stop = min(pop, start + size)
        if start > 0 and between is not None:
            between()
        if event.is_set() or (left is not None and per is not None
                              and left() < per * (stop - start)):
            raise Interrupted('the search was asked to stop')
        t0 = time.perf_counter()
        part = evaluate(params if start == 0 and stop == pop
                        else params.take(slice(start, stop)))
        if out is None:
            out = np.empty((pop,) + part.shape[1:], dtype=part.dtype)
        out[start:stop] = part
        last = max(time.perf_counter() - t0, 1e-9) / (stop - start)
        per = last if per is None else max(per, last)
        problem.seconds_per_candidate = per
        start, size = stop, max(least, int(CHUNK_S / last))
    return out


class RolloutTerms(NamedTuple):
    """How :class:`FitnessProblem` rolls a genome out and what its cost adds (see there)."""

    references: Optional[Sequence] = None
    shooting: object = 0
    penalty_weight: object = 1.0
    bound: object = 100.0
    torque_interpolation: object = 'hold'


class FitnessProblem:
    """
    Everything a generation needs that does not depend on the genome, prepared once.

    Parameters
    ----------
    spec : NetworkSpec
        Network structure.
    datasets : Dataset or list of Dataset
        Gap-free segments, all with the same sampling interval.
    scales : Scales, optional
        Physical scales; measured on ``datasets`` when omitted.
    substeps : int
        RKG steps per sampling interval.
    kp, kd : array_like, shape (n,), optional
        Known PD gains (case 'pd_gains').
    references : list, optional
        One reference object (or None) per segment, evaluated exactly at the stage times.
    shooting : int
        0 for one rollout per segment; k > 0 restarts from the measured state every k
        samples (multiple shooting).
    penalty_weight : float
        Weight of the leading-minor penalty.
    bound : float
        A rollout is diverged when a state leaves ``center ± bound × scale``.
    torque_interpolation : str
        'hold' or 'linear' (case 'torque').

    """

    def __init__(self, spec: NetworkSpec, datasets, scales: Optional[Scales] = None, substeps=4,
                 kp=None, kd=None, **options):
        references, shooting, penalty_weight, bound, torque_interpolation = RolloutTerms(**options)
        if isinstance(datasets, Dataset):
            datasets = [datasets]
        datasets = list(datasets)
        if not datasets:
            raise ValueError('FitnessProblem needs at least one dataset')
        n = spec.n_joints
        for d in datasets:
            if d.n_joints != n:
                raise ValueError(f'dataset has {d.n_joints} joints, the network {n}')
        dts = np.array([d.dt for d in datasets])
        if not np.allclose(dts, dts[0], rtol=1e-6):
            raise ValueError(f'all segments need one sampling interval, got {sorted(set(dts))}')
        substeps = int(substeps)
        if substeps < 1:
            raise ValueError(f'substeps must be >= 1, got {substeps}')
        if int(shooting) < 0:
            raise ValueError(f'shooting must be >= 0, got {shooting}')
        if spec.case == 'pd_gains':
            if kp is None or kd is None:
                raise ValueError("case 'pd_gains' needs kp and kd")
            kp = np.asarray(kp, dtype=float).reshape(-1)
            kd = np.asarray(kd, dtype=float).reshape(-1)
            if kp.size != n or kd.size != n:
                raise ValueError(f'kp and kd need {n} values each')
        else:
            kp = np.zeros(n) if kp is None else np.asarray(kp, dtype=float).reshape(-1)
            kd = np.zeros(n) if kd is None else np.asarray(kd, dtype=float).reshape(-1)
        self.spec = spec
        self.datasets = datasets
        self.scales = scales if scales is not None else Scales.from_datasets(
            datasets, spec.case, kp, kd)
        self.substeps = substeps
        self.dt = float(dts[0])
        self.h = self.dt / substeps
        self.kp = kp
        self.kd = kd
        self.shooting = int(shooting)
        self.penalty_weight = float(penalty_weight)
        self.bound = float(bound)
        refs = list(references) if references is not None else [None] * len(datasets)
        if len(refs) != len(datasets):
            raise ValueError('one reference (or None) per dataset')
        self.inputs: List[np.ndarray] = [
            stage_inputs(spec.case, d.t, substeps, d.tau, d.theta_d, d.theta_d_dot, r,
                         torque_interpolation)
            for d, r in zip(datasets, refs)]
        # flat arrays for the compiled kernel
        self.x_meas = np.ascontiguousarray(np.vstack([d.state for d in datasets]))
        self.seg_start = np.cumsum([0] + [d.n_samples for d in datasets]).astype(np.int64)
        self.u_flat = np.ascontiguousarray(np.concatenate(self.inputs, axis=0))
        self.bound_center = np.concatenate([self.scales.theta_center, np.zeros(n)])
        self.bound_scale = self.bound * np.concatenate(
            [self.scales.theta_spread + 1.0, self.scales.velocity * 10.0 + 1.0])
        self.n_predicted = sum(self._predicted(d.n_samples) for d in datasets)
        self.constants = spec.constants(self.scales, self.kp, self.kd)
        self._segments = None
        #: the most wall seconds per candidate a chunked evaluation took (None: none yet)
        self.seconds_per_candidate: Optional[float] = None

    @staticmethod
    def _predicted(n_samples):
        """Predicted samples of a segment: all but the first (restarts come after a sample)."""
        return n_samples - 1

    @property
    def genome_size(self) -> int:
        """Genome length of the network."""
        return self.spec.genome_size

    def network(self, genomes) -> BatchedNetwork:
        """Return the batched network of a population."""
        return BatchedNetwork(self.spec, self.spec.decode(genomes, self.scales), self.scales,
                              self.kp, self.kd)

    # ----- numpy reference
    def rollout_numpy(self, genomes, segment=0):
        """
        Predicted states of one segment for a population (numpy reference).

        Returns
        -------
        states : ndarray, shape (P, N, 2n)
            Predicted states (rows at shooting restarts hold the predictions, not measurements).
        diverged : ndarray of bool, shape (P,)

        """
        net = self.network(genomes)
        data = self.datasets[segment]
        u = self.inputs[segment]
        pop = net.p.weights.shape[0]
        x_meas = data.state
        out = np.empty((pop, data.n_samples, x_meas.shape[1]))
        x = np.repeat(x_meas[:1], pop, axis=0)
        out[:, 0] = x
        diverged = np.zeros(pop, dtype=bool)
        with np.errstate(all='ignore'):
            for i in range(data.n_samples - 1):
                if self.shooting and i > 0 and i % self.shooting == 0:
                    x = np.repeat(x_meas[i:i + 1], pop, axis=0)
                for s in range(self.substeps):
                    x = rkg_step(net.rhs, x, self.h, u[i, s, 0], u[i, s, 1], u[i, s, 2])
                x = np.where(diverged[:, None], np.nan, x)
                diverged |= self._diverged(x)
                out[:, i + 1] = x
        return out, diverged

    def _diverged(self, x):
        dev = np.abs(x - self.bound_center) > self.bound_scale
        return ~np.all(np.isfinite(x), axis=1) | np.any(dev, axis=1)

    def cost_numpy(self, genomes):
        """Costs of a population, batched numpy reference: (P, N) -> (P,)."""
        genomes = np.atleast_2d(np.asarray(genomes, dtype=float))
        pop = genomes.shape[0]
        n = self.spec.n_joints
        total = np.zeros(pop)
        worst_minor = np.full(pop, np.inf)
        bad = np.zeros(pop, dtype=bool)
        net = self.network(genomes) if self.spec.inertia == 'penalty' else None
        for seg, data in enumerate(self.datasets):
            pred, diverged = self.rollout_numpy(genomes, seg)
            bad |= diverged
            err = pred - data.state[None]
            with np.errstate(invalid='ignore'):
                per_sample = (np.linalg.norm(err[..., :n], axis=-1)
                              + np.linalg.norm(err[..., n:], axis=-1))
            total += np.sum(per_sample[:, 1:], axis=1)
            if net is not None:
                with np.errstate(all='ignore'):  # diverged rows are NaN: scored as inf below
                    for i in range(data.n_samples):
                        worst_minor = np.minimum(worst_minor, net.min_minor(pred[:, i, :n]))
        cost = total / self.n_predicted
        if net is not None:
            cost = cost + self.penalty_weight * np.maximum(0.0, -worst_minor)
        cost[bad | ~np.isfinite(cost)] = np.inf
        return cost

    def cost_loop(self, genomes):
        """Costs one individual at a time (the straightforward implementation)."""
        genomes = np.atleast_2d(np.asarray(genomes, dtype=float))
        return np.array([self.cost_numpy(g[None, :])[0] for g in genomes])

    # ----- compiled fast path
    @property
    def segments(self):
        """Return the measured segments and stage inputs as the kernels take them (once)."""
        if self._segments is None:
            from ..model.kernels import Segments
            self._segments = Segments(self.x_meas, self.seg_start, self.u_flat, self.h,
                                      self.substeps, self.shooting, self.bound_center,
                                      self.bound_scale)
        return self._segments

    def cost(self, genomes):
        """Costs of a population with the compiled kernel: (P, N) -> (P,)."""
        from ..model.kernels import population_cost
        params = self.spec.decode(np.atleast_2d(np.asarray(genomes, dtype=float)), self.scales)

        def evaluate(chunk):
            return population_cost(self.segments, self.constants, chunk, self.penalty_weight,
                                   float(self.n_predicted))
        event = getattr(_interrupts, 'event', None)
        return evaluate(params) if event is None else _chunked(evaluate, params, event, self)

    __call__ = cost

    def rollouts(self, genomes):
        """
        Predicted states of a population for every measured row (compiled kernel).

        Returns
        -------
        ndarray, shape (P, N_total, 2n)
            Row k predicts ``self.x_meas[k]``; NaN after a divergence (until the next
            shooting restart).

        """
        from ..model.kernels import population_rollouts
        params = self.spec.decode(np.atleast_2d(np.asarray(genomes, dtype=float)), self.scales)

        def evaluate(chunk):
            return population_rollouts(self.segments, self.constants, chunk)
        event = getattr(_interrupts, 'event', None)
        return evaluate(params) if event is None else _chunked(evaluate, params, event, self)

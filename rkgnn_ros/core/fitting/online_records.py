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
The records the online identification policy takes and gives (:mod:`.online`).

Settings and an :class:`Observation` go in; events (:class:`ModelUpdate`,
:class:`LoopUpdate`, :class:`GenerationStats`, :class:`LogLine`) and a :class:`Status` come
out. Plain immutable records, so the node's threads can hand them over without sharing
state.
"""

from dataclasses import dataclass, field, replace
import math
from typing import Callable, Dict, List, Mapping, NamedTuple, Optional, Tuple

import numpy as np

from .controller import ClosedLoop as ControllerLoop
from .global_fit import global_spec
from ..data import Dataset
from ..model.model import RKGNNModel
from ..model.spec import NetworkSpec

__all__ = ['OnlineSettings', 'Observation', 'StreamCapture', 'Status', 'ClosedLoop',
           'ModelUpdate', 'LoopUpdate', 'GenerationStats', 'LogLine', 'StepResult',
           'model_update']

#: ``network.basis`` that chooses the global network where the planar trigonometric arm holds.
AUTO_BASIS = 'auto'


@dataclass(frozen=True)
class OnlineSettings:
    """
    One consistent set of settings for a generation.

    The defaults are the identifier's: its parameter table
    (:mod:`rkgnn_ros.identification.parameters`) takes the defaults of the parameters that
    set these fields from here, so each is declared once.

    Attributes
    ----------
    case : str
        'torque', 'pd_gains' or 'unknown': the case the search runs (a node with ``case:
        auto`` passes the one the streams allow); a change restarts the search.
    kp, kd : tuple of float
        Known gains (case 'pd_gains'), one per joint.
    network : mapping
        ``NetworkSpec`` fields replacing those of ``NetworkSpec.recommended``.
    optimizer : str
        'cmaes', 'sep-cmaes' or 'paper'.
    optimizer_settings : mapping
        Settings of :func:`~.optimizers.make_optimizer` (handed over between generations).
    seed : int
        Seed of a new search.
    substeps : int
        RKG steps per sample (0: automatic).
    min_window, validation_fraction, stale_timeout, model_publish_period : float
        See the module docstring.
    max_generations : int
        Generations per search (0: forever).
    version : int
        Changes whenever a setting that restarts the search changed.

    """

    case: str = 'torque'
    kp: Tuple[float, ...] = ()
    kd: Tuple[float, ...] = ()
    network: Mapping = field(default_factory=dict)
    optimizer: str = 'cmaes'
    optimizer_settings: Mapping = field(default_factory=dict)
    seed: int = 0
    substeps: int = 0
    min_window: float = 5.0
    validation_fraction: float = 0.2
    stale_timeout: float = 1.0
    model_publish_period: float = 2.0
    max_generations: int = 0
    version: int = 0

    def spec(self, n_joints: int, trig_holds: bool = False) -> NetworkSpec:
        """
        Return the network for ``n_joints`` joints (raises ValueError if invalid).

        ``network['basis'] == 'auto'``: the global network (:func:`.global_fit.global_spec`)
        where the planar trigonometric arm holds the data (``trig_holds``), else the RBF
        network with the other ``network`` settings.
        """
        network = dict(self.network)
        if network.get('basis') == AUTO_BASIS:
            if trig_holds:
                return global_spec(int(n_joints), self.case)
            network['basis'] = 'rbf'
        return replace(NetworkSpec.recommended(int(n_joints), self.case), **network)


class StreamCapture:
    """
    What :meth:`OnlineIdentification.step` reads from a capture of the buffered streams.

    A protocol: any object with these two methods and ``time_origin`` (the stamp time in s
    of the segments' t = 0) will do (the node passes ``StreamBuffer.capture()``). Both work
    on arrays copied when the capture was taken.
    """

    time_origin: float = 0.0

    def segments(self, min_samples: int, pair_commands: bool) -> List[Dataset]:
        """Return the window as gap-free segments, oldest first (see ``StreamBuffer``)."""
        raise NotImplementedError

    def controller_samples(self) -> Optional[Dict[str, np.ndarray]]:
        """Return states, torque and commands paired at the state stamps, or None."""
        raise NotImplementedError


class Observation(NamedTuple):
    """What the policy is told at one step."""

    settings: OnlineSettings
    joints: Optional[Tuple[str, ...]]
    #: clock time of the newest accepted sample per stream ('state', 'command')
    received: Mapping[str, float]
    paused: bool = False
    reset: bool = False
    #: a StreamCapture, given when data_due() said so (None otherwise)
    data: Optional[object] = None
    #: θ̇ is to be recomputed from θ (the driver publishes none, or it is not trusted)
    estimate_velocity: bool = False
    #: the robot description's rigid-body structure for ``joints`` (None: none given)
    structure: Optional[object] = None
    #: takes a new StreamCapture during the step (a change check within a generation; None:
    #: the step has only ``data``)
    recapture: Optional[Callable[[], object]] = None


class Status(NamedTuple):
    """What the search is doing (for diagnostics)."""

    state: str = 'waiting for data'
    detail: str = 'no joint_states yet'
    generation: int = 0
    best_cost: float = math.nan
    validation_nrmse: float = math.nan
    generations_per_s: float = 0.0
    population_size: int = 0
    condition_number: float = math.nan  # of the excitation memory's regressor (NaN: empty)
    memory_samples: int = 0


class ClosedLoop(NamedTuple):
    """A published ``model`` and, for prediction, the closed loop with a fitted servo law."""

    model: Optional[RKGNNModel]  # None: case 3's linear loop, before any model is published
    loop: ControllerLoop      # rolls the closed loop out (``ControllerLoop.simulate``)
    integral_time: float      # stamp time (s) at which ``loop.law.integral_term`` holds


class ModelUpdate(NamedTuple):
    """Publish ``model``; predict with it (closed with ``loop`` when given)."""

    model: RKGNNModel
    loop: Optional[ClosedLoop]
    generation: int
    cost: float
    validation_nrmse: float
    kp: Tuple[float, ...]  # identified gains: the implied ones, or the fitted law's
    kd: Tuple[float, ...]


class LoopUpdate(NamedTuple):
    """The fitted law changed: predict ``model`` with ``loop`` (None: open loop)."""

    model: Optional[RKGNNModel]  # None: ``loop`` predicts until a model is published
    loop: Optional[ClosedLoop]


class GenerationStats(NamedTuple):
    """One generation (at most 20 per second are reported); the fields of ``~/evolution``."""

    generation: float
    best_cost: float
    mean_cost: float
    spread: float
    evaluations: float
    validation_nrmse: float
    population_size: float
    condition_number: float = math.nan  # the excitation memory's (Status.condition_number)
    memory_samples: float = 0.0


class DynamicsChange(NamedTuple):
    """The arm's dynamics changed (a payload, a tool, wear): when and on which joints."""

    time: float               # stamp time (s) of the change
    joints: Tuple[str, ...]   # the joints whose residual showed it
    statistic: Tuple[float, ...]  # per joint: the residual's mean square / its normal one


class PayloadEstimate(NamedTuple):
    """The last link's change since a :class:`DynamicsChange`, as a payload."""

    time: float               # stamp time (s) of the change
    mass: float               # kg
    com: List[float]          # m, in ``frame``
    inertia: List[float]      # kg m², about the centre of mass: xx, yy, zz, xy, xz, yz
    frame: str
    seconds: float            # of data after the change it was fitted on


class LogLine(NamedTuple):
    """A line for the log: ``level`` is 'info', 'warning' or 'error'."""

    level: str
    text: str


class StepResult(NamedTuple):
    """What one :meth:`OnlineIdentification.step` did."""

    ran: bool  # a generation ran
    events: List[object]


def model_update(model: RKGNNModel, loop: Optional[ClosedLoop] = None,
                 gains=None) -> ModelUpdate:
    """
    Return the :class:`ModelUpdate` that publishes ``model``.

    ``gains`` ``(kp, kd)`` are the identified gains (default: the model's implied gains).
    """
    if gains is None:
        gains = model.implied_gains()
    info = model.info
    return ModelUpdate(
        model, loop, int(info.get('generation', 0)), float(info.get('cost', math.nan)),
        float(info.get('validation_nrmse', math.nan)),
        () if gains is None else tuple(float(v) for v in gains[0]),
        () if gains is None else tuple(float(v) for v in gains[1]))

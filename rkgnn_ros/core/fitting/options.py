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
The options of the fits of :mod:`.identify`, each set one record with its defaults.

- :class:`FitOptions`: :func:`.identify.fit_best`'s (its stages, budget and data split);
- :class:`RolloutChoices`: how :class:`.identify.Evolution` rolls a genome out and where it
  starts;
- :class:`Limits`: when :func:`.identify.fit` stops.
"""

from dataclasses import dataclass, field, fields, replace
import time
from typing import Callable, Mapping, NamedTuple, Optional, Sequence

import numpy as np

from ..model.scales import Scales
from ..model.spec import NetworkSpec

__all__ = ['FitOptions', 'Limits', 'RolloutChoices']


@dataclass(frozen=True)
class FitOptions:
    """
    The options of :func:`fit_best`, in one record; the defaults are the pipeline's.

    Attributes
    ----------
    time_budget : float or None
        Wall time (s) on ``clock`` the call may take (None: no limit).
    spec : NetworkSpec, optional
        The network (default: the global network on ``basis``, or the RBF network).
    kp, kd : array_like, optional
        Known servo gains (case 'pd_gains').
    seed : int
        Seeds the optimizers' random generators.
    shootings : sequence of int
        Levenberg-Marquardt's multiple-shooting intervals (samples), in order.
    lm_fraction : float
        Levenberg-Marquardt's share of the time left after the first stage.
    lm_nfev : int
        Levenberg-Marquardt's residual evaluations per shooting interval, at most.
    polish_sigma : float, optional
        CMA-ES's spread (default 0.01 of each coefficient on a global network, 0.05 on an
        RBF one).
    callback : callable, optional
        Called with each history entry.
    theta_units : int, optional
        RBF units over θ of the RBF network (given: the RBF network is fitted).
    equation_nfev : int
        The equation-error stage's residual evaluations, at most (RBF network; 0: skipped).
    equation_fraction : float
        The equation-error stage's share of the budget (RBF network).
    max_generations, max_evaluations : int, optional
        CMA-ES's generations and the rollouts, at most (None: no limit).
    basis : str
        Basis of the global network ('rbf': the RBF network instead).
    validation_fraction : float
        Newest share of the data held out to choose among the stages' results.
    clock : callable
        Returns the time (s) the budget is counted on.
    structure : RigidStructure, optional
        A robot description's rigid body: fitted in closed form instead.
    learn_chain : bool
        Without ``structure``, case 1 or 3 on 3 to 7 joints: learn the arm's chain first (see
        :func:`.identify.fit_best`).
    evolution : dict
        More arguments of :class:`Evolution` (substeps, shooting, torque_interpolation, init,
        x0).

    """

    time_budget: Optional[float] = 120.0
    spec: Optional[NetworkSpec] = None
    kp: Optional[np.ndarray] = None
    kd: Optional[np.ndarray] = None
    seed: int = 0
    shootings: Sequence[int] = (20, 0)
    lm_fraction: float = 0.7
    lm_nfev: int = 30
    polish_sigma: Optional[float] = None
    callback: Optional[Callable[[dict], None]] = None
    theta_units: Optional[int] = None
    equation_nfev: int = 500
    equation_fraction: float = 0.3
    max_generations: Optional[int] = None
    basis: str = 'trig'
    validation_fraction: float = 0.2
    max_evaluations: Optional[int] = None
    clock: Callable[[], float] = time.perf_counter
    structure: object = None
    learn_chain: bool = False
    evolution: Mapping = field(default_factory=dict)

    def updated(self, **changes) -> 'FitOptions':
        """Return these options with ``changes``; names of no option go to ``evolution``."""
        names = {f.name for f in fields(self)}
        own = {key: value for key, value in changes.items() if key in names}
        more = {key: value for key, value in changes.items() if key not in names}
        if more:
            own['evolution'] = {**self.evolution, **own.get('evolution', {}), **more}
        return replace(self, **own)


@dataclass(frozen=True)
class RolloutChoices:
    """How :class:`Evolution` rolls a genome out and where it starts (see there)."""

    substeps: Optional[int] = None
    shooting: int = 0
    torque_interpolation: str = 'linear'
    scales: Optional[Scales] = None
    x0: Optional[np.ndarray] = None
    init: str = 'default'


class Limits(NamedTuple):
    """When :func:`fit` stops: at the first limit reached (None: no limit on that one)."""

    max_generations: Optional[int] = 200
    max_evaluations: Optional[int] = None
    time_budget: Optional[float] = None     # wall time (s)

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
What a prediction covers: its offsets, the commands over them, and where the plan ends.

:class:`Horizon` is what the predictor rolls a model out over; the commands come from the
newest plan (:class:`FromReference`) or, with none, the newest command held
(:class:`HeldCommand`), both with the rollout's ``evaluate(times)``.
"""

from typing import NamedTuple, Optional

import numpy as np

__all__ = ['FromReference', 'HeldCommand', 'Horizon']


class FromReference:
    """A planned reference from absolute time ``t0`` on (the rollout's ``evaluate`` API)."""

    def __init__(self, plan, t0: float):
        self._plan, self._t0 = plan, t0

    def evaluate(self, times):
        """Return (θd, θ̇d), each (M, n), at ``times`` (M,) relative to ``t0``."""
        return self._plan.at(self._t0 + np.asarray(times, dtype=float))


class HeldCommand:
    """The latest commanded position held, at zero velocity (``evaluate`` API)."""

    def __init__(self, theta_d: np.ndarray):
        self._theta_d = np.asarray(theta_d, dtype=float)

    def evaluate(self, times):
        """Return (θd, θ̇d), each (M, n), at ``times`` (M,)."""
        m = np.asarray(times).size
        return np.tile(self._theta_d, (m, 1)), np.zeros((m, self._theta_d.size))


class Horizon(NamedTuple):
    """The times a prediction covers, the commands over them and how far the plan goes."""

    t: np.ndarray                  # (K,) offsets from the state
    theta_d: Optional[np.ndarray]  # (K, n), None: no plan and no command
    theta_d_dot: Optional[np.ndarray]
    reference: Optional[object]    # the same, for the rollout's exact stage times
    beyond: Optional[float]        # offset where the plan ends, if before the last point
    what: str

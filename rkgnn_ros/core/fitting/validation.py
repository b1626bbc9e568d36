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
Validation of an online fit: hold out the newest data, score a model on it.

Pure functions on :class:`~rkgnn_ros.core.data.Dataset` segments, used by the online policy
(:mod:`.online`) and testable on their own. They take the segments as the buffer gives
them, however short (a gap at each end, a two-sample segment): a cut never makes a piece
shorter than the caller's minimum, which is left out instead.
"""

import math
from typing import List, Sequence, Tuple

import numpy as np

from .policy import MIN_SEGMENT_SAMPLES
from ..data import Dataset
from ..model.model import RKGNNModel
from ..scoring import nrmse

__all__ = ['MIN_SEGMENT_SAMPLES', 'newest_share', 'split_validation', 'validation_nrmse']


def split_validation(segments: Sequence[Dataset], fraction: float,
                     min_samples: int = MIN_SEGMENT_SAMPLES
                     ) -> Tuple[List[Dataset], List[Dataset], float]:
    """
    Hold out the newest ``fraction`` of the data for validation.

    Parameters
    ----------
    segments : sequence of Dataset
        Gap-free segments, oldest first, on one grid.
    fraction : float
        Share of the total duration to hold out (0: none).
    min_samples : int
        A segment is split only if both parts keep this many samples; otherwise it stays
        whole in the training set.

    Returns
    -------
    (train, validation, seconds)
        Both lists oldest first; ``seconds`` is the total duration of ``segments``. A
        split segment's parts share the boundary sample.

    """
    seconds = float(sum(seg.duration for seg in segments))
    hold = fraction * seconds
    train: List[Dataset] = []
    validation: List[Dataset] = []
    for seg in reversed(segments):
        if hold <= 1e-9:
            train.append(seg)
        elif seg.duration <= hold + 1e-9:
            validation.append(seg)
            hold -= seg.duration
        else:
            k = seg.n_samples - 1 - int(round(hold / seg.dt))  # first validation sample
            hold = 0.0
            if seg.n_samples - k >= min_samples and k + 1 >= min_samples:
                train.append(seg.slice(0, k + 1))
                validation.append(seg.slice(k, seg.n_samples))
            else:
                train.append(seg)
    return train[::-1], validation[::-1], seconds


def newest_share(segments: Sequence[Dataset], share: float,
                 min_samples: int = MIN_SEGMENT_SAMPLES) -> List[Dataset]:
    """
    Return the newest ``share`` of the time ``segments`` span, oldest first.

    Whole segments while they fit, then the newest samples of the segment the cut falls in
    (``round(rest / dt) + 1`` of them). A piece of fewer than ``min_samples`` samples (at
    least 2) is left out: a cut just inside a gap's edge would otherwise make a
    one-sample segment, which no fit can use.
    """
    floor = max(2, int(min_samples))
    left = float(share) * sum(seg.duration for seg in segments)
    out: List[Dataset] = []
    for seg in reversed(list(segments)):
        if left <= 0.0:
            break
        keep = seg.n_samples if seg.duration <= left else int(round(left / seg.dt)) + 1
        if keep >= floor:
            out.append(seg.slice(seg.n_samples - keep, seg.n_samples))
        left -= seg.duration
    return out[::-1]


def validation_nrmse(model: RKGNNModel, segments: Sequence[Dataset]) -> float:
    """Return the θ-NRMSE of ``model`` predicting each segment from its first state (NaN: none)."""
    if not segments:
        return math.nan
    n = model.n_joints
    predicted = [model.predict(seg)[:, :n] for seg in segments]
    measured = [seg.theta for seg in segments]
    return nrmse(np.vstack(predicted), np.vstack(measured))

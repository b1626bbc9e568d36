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

"""Scoring predictions against the motion that followed."""

import numpy as np
import pytest
from rkgnn_ros.core.selfcheck import ahead_errors, range_normalised_rmse


def test_perfect_prediction_scores_zero_and_offset_scores_offset():
    t = np.linspace(0.0, 10.0, 1001)
    theta = np.stack([np.sin(t), np.cos(2 * t)], axis=1)
    offsets = np.linspace(0.0, 2.0, 201)
    stamps = [1.0, 3.0, 9.0]  # the last one's target (11 s) is not measured yet: skipped
    good = [np.stack([np.sin(s + offsets), np.cos(2 * (s + offsets))], axis=1) for s in stamps]
    t0, err = ahead_errors(stamps, [offsets] * 3, good, t, theta, 2.0)
    assert t0.tolist() == [1.0, 3.0]
    assert np.max(np.abs(err)) < 1e-3  # linear interpolation of the measured stream only
    shifted = [g + np.array([0.1, -0.2]) for g in good]
    _, err = ahead_errors(stamps, [offsets] * 3, shifted, t, theta, 2.0)
    np.testing.assert_allclose(np.sqrt(np.mean(err ** 2, axis=0)), [0.1, 0.2], atol=1e-3)
    assert range_normalised_rmse(err, [2.0, 2.0]) == pytest.approx(0.075, abs=1e-3)


def test_short_predictions_and_empty_input_are_skipped():
    t = np.linspace(0.0, 5.0, 51)
    theta = np.zeros((51, 1))
    t0, err = ahead_errors([0.0], [np.array([0.0, 1.0])], [np.zeros((2, 1))], t, theta, 2.0)
    assert t0.size == 0 and err.shape == (0, 1)
    assert np.isnan(range_normalised_rmse(err, [1.0]))

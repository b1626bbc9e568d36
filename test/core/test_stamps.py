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

"""Stamps of a steady driver back on its grid: jitter reduced, exact stamps untouched."""

import numpy as np

from rkgnn_ros.core.stamps import StampGrid


def run(stamps):
    grid = StampGrid()
    return np.array([grid(t) for t in stamps])


def test_exact_stamps_come_out_unchanged():
    stamps = 1000.0 + 0.0037 + 0.01 * np.arange(3000)
    np.testing.assert_allclose(run(stamps), stamps, atol=1e-9, rtol=0)


def test_jitter_of_a_millisecond_is_cut_sevenfold_and_drops_keep_their_slots():
    rng = np.random.default_rng(0)
    true = 0.01 * np.arange(6000)
    kept = rng.random(true.size) > 0.02                       # 2 % dropped
    stamps = true + rng.uniform(-1e-3, 1e-3, true.size)
    out = run(stamps[kept])
    error = out[400:] - true[kept][400:]
    assert np.sqrt(np.mean(error ** 2)) < 0.15 * np.sqrt(np.mean((stamps - true) ** 2))
    assert np.max(np.abs(error)) < 3e-4
    assert np.all(np.diff(out) > 0.0)


def test_a_drifting_clock_is_followed():
    true = 0.01 * np.arange(20000)
    stamps = true * (1.0 + 2e-4) + np.random.default_rng(1).uniform(-5e-4, 5e-4, true.size)
    out = run(stamps)
    assert np.max(np.abs(out[1000:] - true[1000:] * (1.0 + 2e-4))) < 3e-4


def test_an_irregular_stream_and_a_pause_are_left_as_they_came():
    rng = np.random.default_rng(2)
    irregular = np.cumsum(rng.uniform(0.002, 0.03, 500))
    np.testing.assert_array_equal(run(irregular), irregular)
    stamps = np.concatenate([0.01 * np.arange(100), 5.0037 + 0.01 * np.arange(100)])
    out = run(stamps)
    assert out[100] == stamps[100]                          # the pause starts the grid anew
    np.testing.assert_allclose(out[120:], stamps[120:], atol=1e-9, rtol=0)


def test_irregular_sampling_stamped_truly_is_not_moved():
    # ~1 kHz with intervals of 0.8-1.2 ms, each stamp the true sampling time
    rng = np.random.default_rng(3)
    stamps = 1.7e9 + np.cumsum(rng.uniform(0.0008, 0.0012, 3000))
    np.testing.assert_array_equal(run(stamps), stamps)


def test_a_repeated_stamp_comes_out_repeated():
    stamps = list(0.01 * np.arange(50))
    stamps.insert(40, stamps[39])
    out = run(stamps)
    assert out[40] == out[39]

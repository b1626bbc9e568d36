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

"""The encoder noise a joint stream shows (rkgnn_ros.core.noise), the self-check's floor."""

import numpy as np
import pytest
from rkgnn_ros.core.noise import encoder_noise


def _stream(rate, seconds, sigma, jitter=0.0, drop=0.0, seed=0):
    """Return stamps (T,) and θ (T, 3) of a moving arm sampled at ``rate`` Hz, noisy."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, seconds, 1.0 / rate)
    t = t + jitter * rng.uniform(-1.0, 1.0, t.size)
    t = np.sort(t[rng.random(t.size) >= drop])
    theta = np.column_stack([np.sin(1.5 * t), 0.5 * np.cos(0.9 * t), 0.8 * np.sin(3.0 * t)])
    return t, theta + sigma * rng.standard_normal(theta.shape)


STREAMS = [(100.0, 0.0, 0.0), (100.0, 0.001, 0.02), (1000.0, 0.0002, 0.02), (50.0, 0.0, 0.0)]


@pytest.mark.parametrize('rate,jitter,drop', STREAMS)
def test_the_noise_of_a_moving_arm_is_found_whatever_the_rate_and_drops(rate, jitter, drop):
    t, theta = _stream(rate, 10.0, 1e-4, jitter, drop)
    sigma = encoder_noise(t, theta)
    assert sigma.shape == (3,)
    np.testing.assert_allclose(sigma, 1e-4, rtol=0.15)


def test_exact_encoders_show_no_noise_and_a_gap_is_not_noise():
    t, theta = _stream(100.0, 10.0, 0.0)
    assert np.all(encoder_noise(t, theta) < 1e-6)
    # a driver that stalled for 0.5 s: the arm moved meanwhile; that jump is not noise
    t, theta = _stream(100.0, 10.0, 1e-4)
    keep = (t < 4.0) | (t > 4.5)
    np.testing.assert_allclose(encoder_noise(t[keep], theta[keep], max_gap=0.1), 1e-4,
                               rtol=0.15)


def test_too_few_samples_give_nan_and_bad_input_is_refused():
    t, theta = _stream(100.0, 0.1, 1e-4)
    assert np.all(np.isnan(encoder_noise(t, theta)))
    with pytest.raises(ValueError, match='shape'):
        encoder_noise(np.arange(5.0), np.zeros((4, 2)))

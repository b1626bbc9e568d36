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

"""θ̇ from θ: the lag-free derivative, the causal one with its delay, the kernel pair."""

import math

import numpy as np
import pytest
from rkgnn_ros.core.differentiate import (causal_coefficients, causal_derivative,
                                          causal_slope, CAUSAL_WINDOW,
                                          centred_derivative, derivative_response,
                                          gaussian_kernels, noise_gain)

DT = 0.01
T = np.arange(0.0, 4.0, DT)


def signal(t):
    """Return a 1.3 Hz sine and a parabola (two joints), and their derivatives."""
    x = np.stack([np.sin(2 * np.pi * 1.3 * t), 0.3 * t ** 2 - t], axis=1)
    v = np.stack([2 * np.pi * 1.3 * np.cos(2 * np.pi * 1.3 * t), 0.6 * t - 1.0], axis=1)
    return x, v


def test_centred_derivative_has_no_lag_and_is_exact_on_cubics():
    x, v = signal(T)
    d = centred_derivative(x, DT)
    assert d.shape == x.shape
    # a 1.3 Hz sine: gain within 0.1 % of 1 (CENTRED_* defaults), no delay
    np.testing.assert_allclose(d[20:-20, 0], v[20:-20, 0], atol=2e-3 * np.max(v[:, 0]))
    cubic = 0.2 * T ** 3 - T
    np.testing.assert_allclose(centred_derivative(cubic, DT), 0.6 * T ** 2 - 1.0, atol=1e-9)
    # a short segment shortens the window instead of failing
    assert centred_derivative(x[:9], DT).shape == (9, 2)
    with pytest.raises(ValueError, match='too few'):
        centred_derivative(x[:3], DT)


def test_causal_derivative_uses_the_past_only_and_its_delay_is_known():
    x, v = signal(T)
    k = 250
    np.testing.assert_allclose(causal_derivative(x[:k + 1], DT)[1], v[k, 1], rtol=1e-9)
    future = x.copy()
    future[k + 1:] += 5.0                      # what comes later cannot change the estimate
    np.testing.assert_array_equal(causal_derivative(future[:k + 1], DT),
                                  causal_derivative(x[:k + 1], DT))
    weights = causal_coefficients(DT)
    gain, delay = derivative_response(weights, DT, [1.0, 1.3])
    assert np.all(np.abs(delay) < 0.006) and np.all(np.abs(gain - 1.0) < 0.12)
    # the documented response predicts the estimate on a 1.3 Hz sine
    w = 2 * np.pi * 1.3
    expected = gain[1] * w * np.cos(w * (T[k] - delay[1]))
    assert causal_derivative(x[:k + 1], DT)[0] == pytest.approx(expected, abs=1e-9)
    # its noise: noise_gain × θ's std (2000 draws: ±3 %)
    rng = np.random.default_rng(0)
    draws = rng.normal(0.0, 1e-4, (2000, weights.size)) @ weights
    assert np.std(draws) == pytest.approx(noise_gain(weights) * 1e-4, rel=0.06)
    assert noise_gain(weights) < 0.2 * math.sqrt(2) / DT   # far below a backward difference


def test_gaussian_kernel_derivative_of_positions_equals_smoothed_velocity():
    x, v = signal(T)
    h, h_prime = gaussian_kernels(DT, 0.03)
    assert h.size == h_prime.size == 2 * 12 + 1 and h.sum() == pytest.approx(1.0)
    for j in range(2):
        smoothed = np.convolve(v[:, j], h, 'valid')
        np.testing.assert_allclose(np.convolve(x[:, j], h_prime, 'valid'), smoothed,
                                   atol=1e-4 * np.max(np.abs(v[:, j])))
    # exact on a parabola (up to rounding)
    np.testing.assert_allclose(np.convolve(x[:, 1], h_prime, 'valid'),
                               np.convolve(v[:, 1], h, 'valid'), atol=1e-12)
    expected = math.sqrt(DT / (4 * math.sqrt(math.pi) * 0.03 ** 3))
    assert noise_gain(h_prime) == pytest.approx(expected, rel=0.01)
    with pytest.raises(ValueError, match='sigma'):
        gaussian_kernels(DT, 0.5 * DT)


def test_causal_slope_on_jittered_stamps_is_the_causal_fit():
    x, v = signal(T)
    k = 300
    rows = slice(k - CAUSAL_WINDOW + 1, k + 1)
    # on uniform stamps it is causal_derivative
    np.testing.assert_allclose(causal_slope(T[rows], x[rows]), causal_derivative(x[:k + 1], DT),
                               rtol=1e-9, atol=1e-12)
    # on a driver's jittered stamps (±0.3 dt) it stays exact for the parabola (column 1)
    # and, for the sine, as close as the uniform fit on uniform stamps
    rng = np.random.default_rng(1)
    stamps = T[rows] + rng.uniform(-0.3, 0.3, CAUSAL_WINDOW) * DT
    stamps[-1] = T[k]
    values, _ = signal(stamps)
    slope = causal_slope(stamps, values)
    assert slope[1] == pytest.approx(v[k, 1], rel=1e-9)
    uniform = causal_derivative(x[:k + 1], DT)[0]
    assert abs(slope[0] - uniform) < 0.01 * np.abs(v[:, 0]).max()
    assert causal_slope(stamps[-2:], values[-2:])[1] == pytest.approx(
        (values[-1, 1] - values[-2, 1]) / (stamps[-1] - stamps[-2]))

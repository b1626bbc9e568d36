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
θ̇ from θ, for drivers that publish no velocity (or a noisy or lagging one).

Two estimates, because the two uses differ:

- **Buffered data** (fits, scoring): :func:`centred_derivative`, the Savitzky–Golay
  derivative, i.e. the slope of a local polynomial fitted over a window centred on each
  sample. A symmetric filter has no phase, so no lag: the fitted dynamics see θ and θ̇
  at the same instant. Near the two ends of a segment the window cannot be centred and the
  polynomial of the first or last window is used (one-sided, noisier).
- **The newest state** a prediction starts from: :func:`causal_derivative`, the slope at
  the end of a polynomial fitted to the last ``window`` samples (only the past exists).
  It is exact for polynomials up to its order, so it has no lag for slow motion; at
  frequency f it has the delay and gain of :func:`derivative_response`, and its noise is
  ``noise_gain(coefficients) * theta_std``. With the defaults at 100 Hz (15 samples,
  order 2) that is about 4 ms of delay and 7 % too much gain at 1 Hz, and 23 × θ's noise
  (the backward difference: 141 ×; a linear fit over the same window: 70 ms of lag).
  :func:`causal_slope` is the same fit on stamps as they come (a driver's jitter).

:func:`gaussian_kernels` gives a smoothing kernel h and its exact derivative h′. Applying
h to an equation's both sides and h′ to θ in place of h to θ̇ (h′ * θ = h * θ̇) keeps a
linear relation exact while removing the noise above the kernel's band: the
controller fit uses it (:mod:`rkgnn_ros.core.fitting.controller`).
"""

import math
from typing import Tuple

import numpy as np

#: Default window (samples) and polynomial order of the centred derivative: flat gain
#: (within 1 %) up to 2 Hz at 100 Hz, noise 9 × θ's.
CENTRED_WINDOW = 21
CENTRED_ORDER = 3
#: The fewest samples the default centred derivative takes (a window of order + 2).
CENTRED_MIN_SAMPLES = CENTRED_ORDER + 2

#: Default window (samples) and order of the causal derivative at the newest sample.
CAUSAL_WINDOW = 15
CAUSAL_ORDER = 2


def _window(window: int, order: int, n_samples: int) -> int:
    """Return the largest usable odd window <= ``window`` for ``n_samples`` samples."""
    window = int(window)
    if window < order + 2:
        raise ValueError(f'window {window} must exceed order + 1 = {order + 1}')
    window = min(window, n_samples if n_samples % 2 else n_samples - 1)
    window -= 1 - window % 2
    if window < order + 2:
        raise ValueError(f'{n_samples} samples are too few for a polynomial of order {order}')
    return window


def centred_derivative(x, dt: float, window: int = CENTRED_WINDOW,
                       order: int = CENTRED_ORDER) -> np.ndarray:
    """
    Return the lag-free Savitzky–Golay derivative of uniformly sampled ``x``.

    Parameters
    ----------
    x : array_like, shape (N,) or (N, n)
        Samples at interval ``dt`` (e.g. θ of one gap-free segment).
    dt : float
        Sampling interval (s).
    window : int
        Samples per local fit (odd; shortened for short segments).
    order : int
        Polynomial order.

    Returns
    -------
    ndarray, the shape of ``x``
        dx/dt; the first and last ``window // 2`` samples come from the one-sided fit of
        the first and last windows.

    """
    x = np.asarray(x, dtype=float)
    if not (math.isfinite(dt) and dt > 0.0):
        raise ValueError(f'dt must be positive, got {dt}')
    window = _window(window, order, x.shape[0])
    from scipy.signal import savgol_filter  # at first use: scipy.signal imports in 0.8 s
    return savgol_filter(x, window, order, deriv=1, delta=dt, axis=0, mode='interp')


def causal_coefficients(dt: float, window: int = CAUSAL_WINDOW,
                        order: int = CAUSAL_ORDER) -> np.ndarray:
    """
    Return the weights of :func:`causal_derivative`, shape (window,), oldest sample first.

    ``weights @ x[-window:]`` is the slope at the last sample of the polynomial of
    ``order`` fitted to the last ``window`` samples.
    """
    window = _window(window, order, int(window))
    from scipy.signal import savgol_coeffs  # at first use: scipy.signal imports in 0.8 s
    return savgol_coeffs(window, order, deriv=1, delta=dt, pos=window - 1, use='dot')


def causal_derivative(x, dt: float, window: int = CAUSAL_WINDOW,
                      order: int = CAUSAL_ORDER) -> np.ndarray:
    """
    Return the derivative at the newest sample from past samples only.

    Parameters
    ----------
    x : array_like, shape (N,) or (N, n)
        Samples at interval ``dt``, newest last; at least ``order + 2`` of them (fewer
        than ``window`` shorten the window).
    dt : float
        Sampling interval (s).
    window, order : int
        Samples and polynomial order of the fit.

    Returns
    -------
    ndarray, shape () or (n,)

    """
    x = np.asarray(x, dtype=float)
    window = _window(window, order, x.shape[0])
    return np.tensordot(causal_coefficients(dt, window, order), x[-window:], axes=(0, 0))


def causal_slope(times, x, order: int = CAUSAL_ORDER) -> np.ndarray:
    """
    Return the slope at the newest sample of the polynomial fitted to samples at ``times``.

    :func:`causal_derivative` for stamps that are not exactly uniform (a driver's jitter):
    the same local least-squares polynomial, on the times as they are; on uniform times the
    two agree. With fewer than ``order + 2`` samples the order drops (two samples: the
    backward difference).

    Parameters
    ----------
    times : array_like, shape (W,)
        Increasing sample times (s), newest last, at least two.
    x : array_like, shape (W,) or (W, n)
        The samples.
    order : int
        Polynomial order.

    Returns
    -------
    ndarray, shape () or (n,)

    """
    times = np.asarray(times, dtype=float)
    x = np.asarray(x, dtype=float)
    if times.ndim != 1 or times.size < 2 or x.shape[0] != times.size:
        raise ValueError(f'need at least two times matching x, got {times.shape}, {x.shape}')
    order = max(1, min(int(order), times.size - 2)) if times.size > 2 else 1
    s = times - times[-1]
    span = max(-s[0], 1e-12)
    basis = np.vander(s / span, order + 1, increasing=True)        # (W, order + 1)
    coef, _, _, _ = np.linalg.lstsq(basis, x.reshape(times.size, -1), rcond=None)
    slope = coef[1] / span
    return slope.reshape(x.shape[1:])


def derivative_response(weights, dt: float, frequency) -> Tuple[np.ndarray, np.ndarray]:
    """
    Return the gain and the delay of a derivative filter on a sinusoid of ``frequency``.

    Parameters
    ----------
    weights : array_like, shape (W,)
        Filter weights, oldest sample first, applied to the last W samples (as from
        :func:`causal_coefficients`).
    dt : float
        Sampling interval (s).
    frequency : array_like of float
        Frequencies (Hz), positive.

    Returns
    -------
    gain : ndarray
        |response| / ω: 1 for an exact derivative.
    delay : ndarray
        Seconds by which the estimate lags the true derivative (phase / ω).

    """
    weights = np.asarray(weights, dtype=float)
    omega = 2.0 * math.pi * np.asarray(frequency, dtype=float)
    age = (weights.size - 1 - np.arange(weights.size)) * dt
    response = np.sum(weights * np.exp(-1j * np.multiply.outer(omega, age)), axis=-1)
    relative = response / (1j * omega)
    return np.abs(relative), -np.angle(relative) / omega


def noise_gain(weights) -> float:
    """Return the factor from white noise on the samples to noise on the estimate."""
    return float(np.sqrt(np.sum(np.square(weights))))


def gaussian_kernels(dt: float, sigma: float) -> Tuple[np.ndarray, np.ndarray]:
    """
    Return a Gaussian smoothing kernel h and its derivative h′, sampled, centred.

    Both have shape (2m + 1,) with m = ceil(4 σ / dt) (truncated at 4 σ, renormalised to a
    unit sum), for use as ``np.convolve(x, h, 'valid')``: the discrete h′ * x equals
    h * ẋ exactly for polynomials up to degree 2 and to the accuracy of the sampling
    otherwise. The band passed is about 1 / (2π σ) Hz (gain exp(−(2π f σ)² / 2)); white
    noise of std s on x becomes about s √(dt / (4 √π σ³)) on h′ * x.

    Parameters
    ----------
    dt : float
        Sampling interval (s).
    sigma : float
        Standard deviation of the kernel (s), at least ``dt``.

    """
    if not (math.isfinite(sigma) and sigma >= dt > 0.0):
        raise ValueError(f'sigma must be >= dt > 0, got sigma {sigma}, dt {dt}')
    m = int(math.ceil(4.0 * sigma / dt))
    s = np.arange(-m, m + 1) * dt
    h = np.exp(-0.5 * (s / sigma) ** 2)
    h /= h.sum()
    # convolution flips the kernel: (h′ * x)[k] = Σ_j h′_j x(t_k − s_j) with h′_j = h′(s_j) dt,
    # scaled by the discrete variance so that a ramp (and a parabola) is differentiated
    # exactly; it is odd, so a constant gives exactly 0
    h_prime = -s * h / np.sum(s * s * h)
    return h, h_prime

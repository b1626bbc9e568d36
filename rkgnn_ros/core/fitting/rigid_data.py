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
The rows a rigid-body fit takes: the regressor and the torques through one low-pass filter.

The arm's equation Y(θ, θ̇, θ̈) π = τ needs θ̈, which no driver publishes, and a
differentiated θ is noisy. Parallel filtering keeps the equation exact on filtered data:
Y is evaluated at every sample (θ as measured; θ̇ and θ̈ by short, lag-free derivative
kernels of standard deviation σ₁ = :data:`DERIVATIVE_SIGMA`, at least one sample interval,
from θ, or from the driver's θ̇ with ``measured_velocity``), and then every column of Y,
the torque, the tracking errors e = θd − θ, ė and ∫e, and a servo's gravity features are
filtered by one Gaussian h of σ₂ with σ₁² + σ₂² = σ² (:data:`DEFAULT_SIGMA`). Y π = τ holds
sample by sample, so h * (Y π) = (h * Y) π = h * τ holds too, whatever the motion: the
filter removes noise (the linear part sees the same smoothing σ as a θ̈ filtered directly)
without biasing the fit. The filtered rows carry nothing above about 1 / (2π σ) Hz and are
kept every :data:`STRIDE_SIGMA` σ. About 4 σ at each end of a segment is not used.
"""

import math
from typing import Callable, NamedTuple, Optional, Sequence

import numpy as np

from ..data import Dataset
from ..differentiate import gaussian_kernels

__all__ = ['DEFAULT_SIGMA', 'DERIVATIVE_SIGMA', 'FilteredRows', 'NOISE_SHARE', 'SIGMAS',
           'STRIDE_SIGMA', 'choose_sigma', 'encoder_noise', 'error_integral', 'filtered_rows',
           'second_derivative_kernel']

#: Standard deviation (s) of the whole low-pass the rows see (σ).
DEFAULT_SIGMA = 0.02

#: Standard deviation (s) of the derivative kernels (σ₁), at least one sample interval.
DERIVATIVE_SIGMA = 0.004

#: Filtered rows are kept this many σ apart (at least every sample).
STRIDE_SIGMA = 0.5

#: The σ :func:`choose_sigma` takes from, shortest first (s).
SIGMAS = (0.02, 0.03, 0.05, 0.08)

#: Largest share of θ̈'s RMS that the encoders' noise may leave in the filtered θ̈.
NOISE_SHARE = 0.02


class FilteredRows(NamedTuple):
    """
    Filtered, thinned rows of one or more segments, oldest first (K kept samples).

    ``regressor`` (K, n, C) are the columns asked for; ``tau``, ``error``, ``error_rate``,
    ``integral`` (∫e from each segment's start) (K, n) are None where the segments lack
    them; ``gravity`` maps 'measured' / 'desired' to a servo's filtered features
    (K, n, F) when features were given; ``theta`` (K, n) is θ at the kept samples and
    ``segment`` (K,) the segment each came from.
    """

    regressor: np.ndarray
    tau: Optional[np.ndarray]
    error: Optional[np.ndarray]
    error_rate: Optional[np.ndarray]
    integral: Optional[np.ndarray]
    gravity: dict
    theta: np.ndarray
    segment: np.ndarray
    time: Optional[np.ndarray] = None    # (K,) the kept samples' times (the segments' t)

    @property
    def n_samples(self) -> int:
        """Return the number of kept samples K."""
        return self.theta.shape[0]

    def take(self, index) -> 'FilteredRows':
        """Return the rows at ``index`` (a slice or index array)."""
        def cut(a):
            return None if a is None else a[index]
        return FilteredRows(self.regressor[index], cut(self.tau), cut(self.error),
                            cut(self.error_rate), cut(self.integral),
                            {k: v[index] for k, v in self.gravity.items()}, self.theta[index],
                            self.segment[index], cut(self.time))


def error_integral(e: np.ndarray, dt: float) -> np.ndarray:
    """Return ∫e dt from the first sample (rad s), trapezoids of ``dt`` (s), shape of ``e``."""
    z = np.zeros_like(e)
    z[1:] = np.cumsum(0.5 * (e[1:] + e[:-1]), axis=0) * dt
    return z


def second_derivative_kernel(dt: float, sigma: float) -> np.ndarray:
    """
    Return h″, the sampled second derivative of the Gaussian of :func:`gaussian_kernels`.

    Exact (as ``np.convolve(x, h2, 'valid')``) on polynomials up to degree 3: it sums to
    zero, is even, and maps t² to 2.
    """
    h, _ = gaussian_kernels(dt, sigma)
    m = h.size // 2
    s = np.arange(-m, m + 1) * dt
    spread = float(np.sum(s * s * h) / np.sum(h))
    h2 = (s * s - spread) * h
    return 2.0 * h2 / float(np.sum(h2 * s * s))


def encoder_noise(segments: Sequence[Dataset]) -> float:
    """
    Return the white noise on θ (rad), from the fourth differences of the samples.

    On motion of a few hertz sampled at 100 Hz and more, the fourth difference of θ is
    noise alone (std √70 σ for white noise σ); its median absolute value is used, so a
    few spikes do not count. The largest joint's figure, 0 without data.
    """
    values = []
    for seg in segments:
        if seg.n_samples >= 20:
            d4 = np.diff(seg.theta, n=4, axis=0)
            values.append(np.median(np.abs(d4), axis=0) / (0.6745 * math.sqrt(70.0)))
    return float(np.max(values)) if values else 0.0


def choose_sigma(segments: Sequence[Dataset]) -> float:
    """
    Return the shortest σ of :data:`SIGMAS` whose θ̈ keeps the noise under NOISE_SHARE.

    White noise σ_θ through the second derivative of a Gaussian of σ leaves
    σ_θ √(3 dt / (8 √π σ⁵)) on θ̈ (dt the sample interval); θ̈'s RMS is taken through the
    longest σ, for the median joint. Noise in θ̈ dilutes the inertial parameters'
    estimates (by the squared share) and hides the model's error in its held-out score, so
    the filter is widened until the noise is a small share.
    """
    usable = [seg for seg in segments if seg.n_samples >= 20]
    if not usable:
        return SIGMAS[0]
    noise = encoder_noise(usable)
    if noise <= 0.0:
        return SIGMAS[0]
    dt = min(seg.dt for seg in usable)
    widest = max(SIGMAS[-1], dt)
    power, count = 0.0, 0
    for seg in usable:
        kernel = second_derivative_kernel(seg.dt, max(widest, seg.dt))
        if seg.n_samples > kernel.size:
            acc = _convolve(seg.theta, kernel)
            power = power + np.sum(acc ** 2, axis=0)
            count += acc.shape[0]
    if count == 0:
        return SIGMAS[-1]
    signal = float(np.median(np.sqrt(power / count)))    # the median joint's θ̈ RMS
    for sigma in SIGMAS:
        s = max(sigma, dt)
        if noise * math.sqrt(3.0 * dt / (8.0 * math.sqrt(math.pi) * s ** 5)) \
                <= NOISE_SHARE * signal:
            return sigma
    return SIGMAS[-1]


def _convolve(x: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """Return ``np.convolve(column, kernel, 'valid')`` of every column of x (N, ...)."""
    flat = x.reshape(x.shape[0], -1)
    out = np.stack([np.convolve(flat[:, j], kernel, 'valid') for j in range(flat.shape[1])], 1)
    return out.reshape((out.shape[0],) + x.shape[1:])


def _smooth_at(x: np.ndarray, kernel: np.ndarray, stride: int) -> np.ndarray:
    """Return the 'valid' convolution of x (N, ...) with a symmetric kernel, every stride-th."""
    windows = np.lib.stride_tricks.sliding_window_view(x, kernel.size, axis=0)[::stride]
    return windows @ kernel


#: Samples whose regressor is evaluated at once (bounds the memory of long recordings).
CHUNK = 2048


def _chunked(regressor, theta, theta_dot, theta_ddot, h, stride):
    """Return ``_smooth_at(regressor(θ, θ̇, θ̈), h, stride)``, evaluated in chunks."""
    width = h.size
    count = theta.shape[0] - width + 1           # filtered outputs before thinning
    out = []
    step = max(stride, (CHUNK // stride) * stride)
    for first in range(0, count, step):
        last = min(count, first + step)             # outputs first .. last - 1
        part = slice(first, last - 1 + width)
        y = regressor(theta[part], theta_dot[part], theta_ddot[part])
        out.append(_smooth_at(y, h, stride))
    return np.concatenate(out)


def filtered_rows(segments: Sequence[Dataset], regressor: Callable,
                  sigma: Optional[float] = DEFAULT_SIGMA, measured_velocity: bool = False,
                  features: Optional[Callable] = None,
                  stride_sigma: float = STRIDE_SIGMA) -> Optional[FilteredRows]:
    """
    Return the filtered rows of ``segments`` (module docstring), None if none is long enough.

    ``regressor(θ, θ̇, θ̈)`` gives Y (N, n, C) for states (N, n); ``features(θ)`` a servo's
    gravity features (N, n, F). ``sigma`` (s) is raised to one sample interval where the data
    are coarser; None: :func:`choose_sigma` of the segments.
    """
    if sigma is None:
        sigma = choose_sigma(segments)
    parts = []
    for index, seg in enumerate(segments):
        dt = seg.dt
        s1 = max(DERIVATIVE_SIGMA, dt)
        s = max(float(sigma), math.sqrt(2.0) * s1)
        s2 = math.sqrt(s * s - s1 * s1)
        _, d1 = gaussian_kernels(dt, s1)
        d2 = second_derivative_kernel(dt, s1)
        h, _ = gaussian_kernels(dt, s2)
        m1, m2 = d1.size // 2, h.size // 2
        if seg.n_samples < 2 * (m1 + m2) + 2:
            continue
        stride = max(1, int(round(stride_sigma * s / dt)))
        inner = slice(m1, seg.n_samples - m1)
        theta = seg.theta[inner]
        if measured_velocity:
            theta_dot = seg.theta_dot[inner]
            theta_ddot = _convolve(seg.theta_dot, d1)
        else:
            theta_dot, theta_ddot = _convolve(seg.theta, d1), _convolve(seg.theta, d2)
        part = {'regressor': _chunked(regressor, theta, theta_dot, theta_ddot, h, stride)}
        kept = slice(m2, theta.shape[0] - m2, stride)
        part['theta'] = theta[kept]
        part['time'] = seg.t[inner][kept]
        for name, value in (('tau', seg.tau), ('theta_d', seg.theta_d),
                            ('theta_d_dot', seg.theta_d_dot)):
            part[name] = None if value is None else value[inner]
        if part['tau'] is not None:
            part['tau'] = _smooth_at(part['tau'], h, stride)
        part['gravity'] = {}
        part['error'] = part['error_rate'] = part['integral'] = None
        if part['theta_d'] is not None and part['theta_d_dot'] is not None:
            e = part['theta_d'] - theta
            z = error_integral(e, dt)
            part['error'] = _smooth_at(e, h, stride)
            part['error_rate'] = _smooth_at(part['theta_d_dot'] - theta_dot, h, stride)
            part['integral'] = _smooth_at(z, h, stride)
            if features is not None:
                part['gravity'] = {'measured': _smooth_at(features(theta), h, stride),
                                   'desired': _smooth_at(features(part['theta_d']), h, stride)}
        elif features is not None:
            part['gravity'] = {'measured': _smooth_at(features(theta), h, stride)}
        part['segment'] = np.full(part['theta'].shape[0], index, dtype=np.int64)
        parts.append(part)
    if not parts:
        return None

    def join(name):
        values = [p[name] for p in parts]
        return None if any(v is None for v in values) else np.concatenate(values)

    keys = set.intersection(*(set(p['gravity']) for p in parts))
    gravity = {k: np.concatenate([p['gravity'][k] for p in parts]) for k in keys}
    return FilteredRows(join('regressor'), join('tau'), join('error'), join('error_rate'),
                        join('integral'), gravity, join('theta'), join('segment'), join('time'))

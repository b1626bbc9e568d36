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
The 4th-order Runge-Kutta-Gill scheme, as in the paper (with its typo fixed).

Gill's form keeps one accumulator ``q`` beside the state::

    k0 = h f(x);   x1 = x + k0/2;              q1 = k0
    k1 = h f(x1);  x2 = x1 + alpha (k1 - q1);  q2 = beta q1 + e k1
    k2 = h f(x2);  x3 = x2 + d (k2 - q2);      q3 = gamma q2 + g k2
    k3 = h f(x3);  x4 = x3 + k3/6 - q3/3       (the paper prints a3 for q3)

with alpha = (sqrt2 - 1)/sqrt2, beta = -2 + 3/sqrt2, d = (sqrt2 + 1)/sqrt2,
e = 2 - sqrt2, g = 2 + sqrt2, gamma = -(2 + 3/sqrt2). The same method as a Butcher tableau
(``A``, ``B``, ``C`` below, scipy's convention) is what the tests hold the coefficients to.
The four evaluations happen at the times t, t + h/2, t + h/2 and t + h.
"""

import numpy as np

SQRT2 = np.sqrt(2.0)

# Gill's coefficients, named as in the paper.
ALPHA = (SQRT2 - 1.0) / SQRT2
BETA = -2.0 + 3.0 / SQRT2
D = (SQRT2 + 1.0) / SQRT2
E = 2.0 - SQRT2
G = 2.0 + SQRT2
GAMMA = -(2.0 + 3.0 / SQRT2)

# The equivalent Butcher tableau.
A = np.array([
    [0.0, 0.0, 0.0, 0.0],
    [0.5, 0.0, 0.0, 0.0],
    [(SQRT2 - 1.0) / 2.0, (2.0 - SQRT2) / 2.0, 0.0, 0.0],
    [0.0, -SQRT2 / 2.0, 1.0 + SQRT2 / 2.0, 0.0],
])
B = np.array([1.0 / 6.0, (2.0 - SQRT2) / 6.0, (2.0 + SQRT2) / 6.0, 1.0 / 6.0])
C = np.array([0.0, 0.5, 0.5, 1.0])

# |h lambda| on the negative real axis beyond which any 4-stage 4th-order RK step diverges.
STABILITY_LIMIT = 2.785293563405282


def rkg_step(f, x, h, u0=None, u_half=None, u1=None):
    """
    Advance ``x`` by one Runge-Kutta-Gill step of width ``h``.

    Parameters
    ----------
    f : callable
        ``f(x, u) -> dx/dt``, vectorised over any leading batch dimensions of ``x``.
    x : ndarray, shape (..., m)
        State at time t.
    h : float
        Step width.
    u0, u_half, u1 : optional
        Inputs at t, t + h/2 and t + h (passed to ``f`` as its second argument).

    Returns
    -------
    ndarray, shape (..., m)
        State at t + h.

    """
    k = h * f(x, u0)
    x = x + 0.5 * k
    q = k
    k = h * f(x, u_half)
    x = x + ALPHA * (k - q)
    q = BETA * q + E * k
    k = h * f(x, u_half)
    x = x + D * (k - q)
    q = GAMMA * q + G * k
    k = h * f(x, u1)
    return x + k / 6.0 - q / 3.0


def rkg_integrate(f, t, x0, substeps=1, inputs=None):
    """
    Integrate ``dx/dt = f(x, u(t))`` over the grid ``t`` with ``substeps`` RKG steps per interval.

    Parameters
    ----------
    f : callable
        ``f(x, u) -> dx/dt``.
    t : ndarray, shape (N,)
        Output times (increasing; need not be uniform).
    x0 : ndarray, shape (..., m)
        State at ``t[0]``.
    substeps : int
        RKG steps per interval ``[t[i], t[i+1]]``.
    inputs : callable or None
        ``inputs(time) -> u`` evaluated at the stage times; None passes ``u=None``.

    Returns
    -------
    ndarray, shape (N, ..., m)
        The states at ``t``.

    """
    t = np.asarray(t, dtype=float)
    substeps = int(substeps)
    if substeps < 1:
        raise ValueError(f'substeps must be >= 1, got {substeps}')
    x = np.asarray(x0, dtype=float)
    out = np.empty((t.size,) + x.shape)
    out[0] = x
    u = inputs if inputs is not None else (lambda _time: None)
    for i in range(t.size - 1):
        h = (t[i + 1] - t[i]) / substeps
        for s in range(substeps):
            ts = t[i] + s * h
            x = rkg_step(f, x, h, u(ts), u(ts + 0.5 * h), u(ts + h))
        out[i + 1] = x
    return out


def choose_substeps(dt, stiffness=None, max_step=None, safety=0.5):
    """
    Choose the RKG substeps per sampling interval that keep a rollout stable.

    Parameters
    ----------
    dt : float
        Sampling interval (s).
    stiffness : float or None
        Largest |eigenvalue| (1/s) of the dynamics' Jacobian expected along the data.
    max_step : float or None
        Upper bound on the step width (s), applied as well.
    safety : float
        Fraction of the stability limit ``h |lambda| < 2.785`` used.

    Returns
    -------
    int
        Substeps (at least 1).

    """
    if not np.isfinite(dt) or dt <= 0.0:
        raise ValueError(f'dt must be positive and finite, got {dt}')
    steps = 1
    if stiffness is not None and stiffness > 0.0:
        steps = max(steps, int(np.ceil(dt * stiffness / (safety * STABILITY_LIMIT) - 1e-12)))
    if max_step is not None:
        steps = max(steps, int(np.ceil(dt / max_step - 1e-12)))
    return steps

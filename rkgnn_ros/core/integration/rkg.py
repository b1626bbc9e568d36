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
The 4th-order Runge-Kutta-Gill scheme, as in the paper (with its typo fixed): data plus one step.

Gill's form keeps one accumulator ``q`` beside the state::

    k0 = h f(x);   x1 = x + k0/2;              q1 = k0
    k1 = h f(x1);  x2 = x1 + alpha (k1 - q1);  q2 = beta q1 + e k1
    k2 = h f(x2);  x3 = x2 + d (k2 - q2);      q3 = gamma q2 + g k2
    k3 = h f(x3);  x4 = x3 + k3/6 - q3/3       (the paper prints a3 for q3)

with alpha = (sqrt2 - 1)/sqrt2, beta = -2 + 3/sqrt2, d = (sqrt2 + 1)/sqrt2,
e = 2 - sqrt2, g = 2 + sqrt2, gamma = -(2 + 3/sqrt2). The same method as a Butcher tableau
(``A``, ``B``, ``C`` below, scipy's convention) is what the tests hold the coefficients to.
The four evaluations happen at the times t, t + h/2, t + h/2 and t + h.

The update of one stage is written once, :func:`gill_update`, and used two ways (as scipy's
``_ivp/rk.py`` keeps one tableau and one ``rk_step``): :func:`rkg_step` applies it to numpy
arrays (any batch shape; the reference every compiled path is tested against), and
:func:`gill_stage` is its compiled twin (numba, inlined) that the compiled loops call after
evaluating their rate at a stage: the model's kernels, the PD-tuning kernel and the
``sim_arm`` node. Each of those keeps its own stage loop, because each evaluates a different
right-hand side with buffers of its own; only the update is shared.

Also here: the stability of the scheme (a 4-stage 4th-order method has the stability
polynomial of classical RK4) and the choice of substeps per sampling interval.
"""

from numba import njit
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

#: Where each stage takes its input, in half steps from t (2 C): t, t + h/2, t + h/2, t + h.
STAGE_NODES = tuple(int(round(2.0 * c)) for c in C)

#: |h λ| on the negative real axis beyond which any 4-stage 4th-order RK step diverges: the
#: real root of z³ + 4z² + 12z + 24 = 0.
STABILITY_LIMIT = 2.785293563405282

#: The same limit on the imaginary axis, 2√2.
IMAG_STABILITY_LIMIT = 2.0 * np.sqrt(2.0)


def gill_update(stage, hk, x, xs, q):
    """
    Return the state after stage ``stage`` of Gill's form and the new accumulator.

    Works element by element on floats (the compiled twin :func:`gill_stage`) and on numpy
    arrays of any shape (:func:`rkg_step`).

    Parameters
    ----------
    stage : int
        0 to 3.
    hk : float or ndarray
        ``h f(xs)``: the step times the rate at the stage's state.
    x : float or ndarray
        The state at the start of the step (used by stage 0).
    xs : float or ndarray
        The stage's state (stages 1 to 3).
    q : float or ndarray
        Gill's accumulator (stages 1 to 3; anything at stage 0).

    Returns
    -------
    (next, q)
        The next stage's state, or after stage 3 the state at t + h; the accumulator.

    """
    if stage == 0:
        return x + 0.5 * hk, hk
    if stage == 1:
        return xs + ALPHA * (hk - q), BETA * q + E * hk
    if stage == 2:
        return xs + D * (hk - q), GAMMA * q + G * hk
    return xs + hk / 6.0 - q / 3.0, q


_gill_update = njit(cache=True, nogil=True, inline='always')(gill_update)


@njit(cache=True, nogil=True, inline='always')
def gill_stage(stage, h, x, xs, k, q):
    """
    Apply stage ``stage`` of the Runge-Kutta-Gill step in place: the compiled twin.

    Call it after evaluating the rate ``k = f(xs)`` of the stage (at stage 0, ``xs`` holds
    ``x``). Stages 0 to 2 write the next stage's state into ``xs``; stage 3 writes the state
    at t + h into ``x``. :func:`gill_update` element by element, so a compiled stage loop
    computes exactly what :func:`rkg_step` does.

    Parameters
    ----------
    stage : int
        0 to 3.
    h : float
        Step width.
    x : ndarray, shape (m,)
        State at the start of the step; overwritten by the result after stage 3.
    xs : ndarray, shape (m,)
        The stage's state; overwritten by the next stage's.
    k : ndarray, shape (m,)
        The rate f(xs) (not multiplied by h).
    q : ndarray, shape (m,)
        Gill's accumulator, carried from stage to stage.

    """
    # one loop per stage, so that the compiler specialises the update to it
    m = k.shape[0]
    if stage == 0:
        for j in range(m):
            nxt, acc = _gill_update(0, h * k[j], x[j], xs[j], q[j])
            xs[j] = nxt
            q[j] = acc
    elif stage == 1:
        for j in range(m):
            nxt, acc = _gill_update(1, h * k[j], x[j], xs[j], q[j])
            xs[j] = nxt
            q[j] = acc
    elif stage == 2:
        for j in range(m):
            nxt, acc = _gill_update(2, h * k[j], x[j], xs[j], q[j])
            xs[j] = nxt
            q[j] = acc
    else:
        for j in range(m):
            nxt, acc = _gill_update(3, h * k[j], x[j], xs[j], q[j])
            x[j] = nxt


@njit(cache=True, nogil=True, inline='always')
def gill_node(stage):
    """Return where stage ``stage`` takes its input, in half steps from t (0, 1, 1, 2)."""
    return STAGE_NODES[stage]


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
    inputs = (u0, u_half, u1)
    xs, q = x, None
    for stage in range(4):
        xs, q = gill_update(stage, h * f(xs, inputs[STAGE_NODES[stage]]), x, xs, q)
    return xs


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


def stability_polynomial(z):
    """
    Return R(z) = 1 + z + z²/2 + z³/6 + z⁴/24: one step multiplies the mode e^(λt) by R(hλ).

    Every 4-stage 4th-order explicit Runge-Kutta method (classical RK4, Runge-Kutta-Gill) has
    this stability polynomial (the tests derive it from the tableau).
    """
    return 1.0 + z * (1.0 + z * (0.5 + z * (1.0 / 6.0 + z / 24.0)))


def stability_radius(lam):
    """
    Return the distance r to the stability boundary along the ray through each λ.

    ``|R(r λ/|λ|)| = 1`` with R the :func:`stability_polynomial`. For λ in the open left
    half-plane this is the first exit from the stability region (:data:`STABILITY_LIMIT`
    on the negative real axis). Eigenvalues with Re λ >= 0 belong to undamped or growing
    modes that no step size stabilises; they get the imaginary-axis value 2√2 so that the
    step still resolves their time scale.

    Parameters
    ----------
    lam : array_like, complex, shape (...)
        Non-zero eigenvalues.

    Returns
    -------
    ndarray, shape (...)

    """
    lam = np.asarray(lam, dtype=complex)
    u = lam / np.abs(lam)
    radius = np.full(u.shape, IMAG_STABILITY_LIMIT)
    left = u.real < -1e-12
    if np.any(left):
        ul = u[left]

        def unstable(r):
            return np.abs(stability_polynomial(r * ul)) > 1.0

        # the boundary lies within |z| < 3 in the left half-plane; scan, then bisect
        grid = np.linspace(0.0, 3.0, 601)[1:]
        exits = np.array([unstable(r) for r in grid])               # (601-1, L)
        first = np.where(exits.any(axis=0), exits.argmax(axis=0), grid.size - 1)
        hi = grid[first]
        lo = np.where(first > 0, grid[np.maximum(first - 1, 0)], 0.0)
        for _ in range(50):
            mid = 0.5 * (lo + hi)
            bad = unstable(mid)
            hi = np.where(bad, mid, hi)
            lo = np.where(bad, lo, mid)
        radius[left] = lo
    return radius

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

"""The Runge-Kutta-Gill scheme: coefficients, the step and its compiled twin, order, stability."""

from numba import njit
import numpy as np
import pytest
from rkgnn_ros.core.integration import rkg
from scipy.integrate import solve_ivp


def test_gill_coefficients_are_the_papers():
    s2 = np.sqrt(2.0)
    assert rkg.ALPHA == pytest.approx(1.0 - 1.0 / s2)
    assert rkg.D == pytest.approx(1.0 + 1.0 / s2)
    assert rkg.E == pytest.approx(2.0 - s2)
    assert rkg.G == pytest.approx(2.0 + s2)
    assert rkg.BETA == pytest.approx(-2.0 + 3.0 / s2)
    assert rkg.GAMMA == pytest.approx(-(2.0 + 3.0 / s2))


def test_tableau_identities():
    # consistency: rows of A sum to C, weights sum to one
    np.testing.assert_allclose(rkg.A.sum(axis=1), rkg.C, atol=1e-15)
    assert rkg.B.sum() == pytest.approx(1.0, abs=1e-15)
    # order conditions up to 4
    b, a, c = rkg.B, rkg.A, rkg.C
    assert b @ c == pytest.approx(1 / 2)
    assert b @ c ** 2 == pytest.approx(1 / 3)
    assert b @ (a @ c) == pytest.approx(1 / 6)
    assert b @ c ** 3 == pytest.approx(1 / 4)
    assert (b * c) @ (a @ c) == pytest.approx(1 / 8)
    assert b @ (a @ c ** 2) == pytest.approx(1 / 12)
    assert b @ (a @ (a @ c)) == pytest.approx(1 / 24)


def _tableau_step(f, x, h):
    k = []
    for i in range(4):
        xi = x + h * sum(rkg.A[i, j] * k[j] for j in range(i))
        k.append(f(xi, None))
    return x + h * sum(rkg.B[i] * k[i] for i in range(4))


def test_gill_form_equals_tableau():
    mat = np.array([[0.0, 1.0, 0.2], [-4.0, -0.3, 0.1], [0.5, 0.0, -1.0]])

    def f(x, _u):
        return mat @ x + np.sin(x)

    x = np.array([0.3, -0.2, 1.0])
    for h in (0.5, 0.1, 0.01):
        np.testing.assert_allclose(rkg.rkg_step(f, x, h), _tableau_step(f, x, h),
                                   rtol=1e-13, atol=1e-15)


@njit
def _compiled_rate(x, out):
    for j in range(x.shape[0]):
        out[j] = 0.5 - x[j] * x[j] + 0.25 * x[(j + 1) % x.shape[0]]


def _numpy_rate(x, _u):
    return 0.5 - x * x + 0.25 * np.roll(x, -1, axis=-1)


@njit
def _compiled_steps(x0, h, steps):
    """Integrate with a compiled stage loop as the kernels write it: rate, shared update."""
    x = x0.copy()
    xs = np.empty_like(x)
    k = np.empty_like(x)
    q = np.empty_like(x)
    for _ in range(steps):
        xs[:] = x
        for stage in range(4):
            _compiled_rate(xs, k)
            rkg.gill_stage(stage, h, x, xs, k, q)
    return x


def test_compiled_stage_update_equals_the_numpy_step_and_the_tableau():
    x = np.array([0.3, -0.2, 1.0, 0.7])
    for h in (0.5, 0.1, 0.01):
        numpy_step = rkg.rkg_step(_numpy_rate, x, h)
        # the same update on the same arithmetic: equal to the last bit
        np.testing.assert_array_equal(_compiled_steps(x, h, 1), numpy_step)
        np.testing.assert_allclose(numpy_step, _tableau_step(_numpy_rate, x, h), rtol=1e-13,
                                   atol=1e-15)


def test_compiled_stage_loop_converges_with_order_four():
    x0 = np.array([0.3, -0.2, 1.0, 0.7])
    ref = solve_ivp(lambda _t, y: _numpy_rate(y, None), (0.0, 2.0), x0, rtol=1e-13,
                    atol=1e-14).y[:, -1]
    steps = np.array([10, 20, 40, 80])
    errors = np.array([np.linalg.norm(_compiled_steps(x0, 2.0 / m, m) - ref) for m in steps])
    orders = np.log2(errors[:-1] / errors[1:])
    assert np.all(orders > 3.8) and np.all(orders < 4.3), orders


def test_stage_nodes_are_the_tableau_nodes():
    assert rkg.STAGE_NODES == (0, 1, 1, 2)
    np.testing.assert_array_equal(np.array(rkg.STAGE_NODES) / 2.0, rkg.C)
    assert [rkg.gill_node(stage) for stage in range(4)] == [0, 1, 1, 2]


def test_stability_polynomial_is_the_tableaus():
    # R(z) = 1 + z bᵀ (I - zA)⁻¹ 1 for the Butcher tableau; explicit, so a polynomial
    for z in (-2.785, -1.0 + 1.0j, 0.3 - 2.0j, 1e-3):
        expected = 1.0 + z * rkg.B @ np.linalg.solve(np.eye(4) - z * rkg.A, np.ones(4))
        assert rkg.stability_polynomial(z) == pytest.approx(expected, rel=1e-13)
    assert abs(rkg.stability_polynomial(-rkg.STABILITY_LIMIT)) == pytest.approx(1.0, abs=1e-12)


def test_fourth_order_convergence():
    def f(x, _u):
        return np.array([x[1], -np.sin(x[0]) - 0.1 * x[1]])

    x0 = np.array([1.0, 0.0])
    t_end = 2.0
    ref = solve_ivp(lambda _t, y: f(y, None), (0, t_end), x0, rtol=1e-13, atol=1e-14).y[:, -1]
    errors = []
    steps = [10, 20, 40, 80]
    for m in steps:
        out = rkg.rkg_integrate(f, np.linspace(0.0, t_end, m + 1), x0)
        errors.append(np.linalg.norm(out[-1] - ref))
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert np.all(orders > 3.8) and np.all(orders < 4.3), orders


def test_agrees_with_scipy_rk45_on_time_varying_input():
    def f(x, u):
        return np.array([x[1], -4.0 * x[0] - 0.5 * x[1] + u])

    def u_of_t(t):
        return np.cos(3.0 * t)

    t = np.linspace(0.0, 5.0, 501)
    ours = rkg.rkg_integrate(f, t, np.array([0.1, 0.0]), substeps=2, inputs=u_of_t)
    sol = solve_ivp(lambda tt, y: f(y, u_of_t(tt)), (0, 5), [0.1, 0.0], t_eval=t,
                    method='RK45', rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(ours, sol.y.T, atol=1e-8)


def test_stability_limit_and_substeps():
    lam = -380.0

    def f(x, _u):
        return lam * x

    dt = 0.01
    one = rkg.rkg_integrate(f, np.arange(0, 0.5, dt), np.array([1.0]), substeps=1)
    assert not np.all(np.abs(one[-1]) < 1.0)  # h|lambda| = 3.8 > 2.785: it diverges
    steps = rkg.choose_substeps(dt, stiffness=380.0)
    assert steps >= 3
    ok = rkg.rkg_integrate(f, np.arange(0, 0.5, dt), np.array([1.0]), substeps=steps)
    assert abs(ok[-1, 0]) < 1e-6
    assert rkg.choose_substeps(0.01, max_step=0.0025) == 4
    with pytest.raises(ValueError):
        rkg.choose_substeps(0.0)


def test_stability_radius():
    # real axis: the root of z³ + 4z² + 12z + 24 = 0
    root = np.roots([1.0, 4.0, 12.0, 24.0])
    assert rkg.STABILITY_LIMIT == pytest.approx(-root[np.isreal(root)].real[0], rel=1e-12)
    assert rkg.stability_radius(-5.0) == pytest.approx(rkg.STABILITY_LIMIT, rel=1e-9)
    assert rkg.stability_radius(3.0j) == pytest.approx(rkg.IMAG_STABILITY_LIMIT)
    lam = np.exp(1j * np.linspace(0.55 * np.pi, 1.45 * np.pi, 25))
    r = rkg.stability_radius(lam)
    z = r * lam
    np.testing.assert_allclose(np.abs(1 + z + z ** 2 / 2 + z ** 3 / 6 + z ** 4 / 24), 1.0,
                               atol=1e-9)

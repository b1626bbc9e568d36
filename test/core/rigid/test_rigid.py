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

"""The rigid-body core: kernels against Pinocchio, base parameters, consistent parameters."""

import numpy as np
import pytest

pinocchio = pytest.importorskip('pinocchio')

from rkgnn_ros.core.rigid import consistency  # noqa: E402
from rkgnn_ros.core.rigid.kernels import N_INERTIAL  # noqa: E402
from rkgnn_ros.core.rigid.solve import fit_consistent  # noqa: E402
from rkgnn_ros.core.rigid.structure import (DescriptionError, RigidStructure,  # noqa: E402
                                            to_pinocchio_order)
from rkgnn_ros.core.sim.urdf_arm import UrdfArm  # noqa: E402

UR5 = 'example-robot-data:ur_description/urdf/ur5_robot.urdf'
PANDA = 'example-robot-data:panda_description/urdf/panda.urdf'


@pytest.fixture(scope='module', params=[UR5, PANDA], ids=['ur5', 'panda'])
def pair(request):
    arm = UrdfArm(request.param)
    structure = RigidStructure(arm.urdf, arm.joint_names)
    params = structure.prior.copy()
    params[N_INERTIAL * structure.n_joints:] = 0.0   # Pinocchio's RNEA has no joint terms
    return arm, structure, params


def test_the_kernels_give_pinocchios_dynamics(pair):
    arm, structure, params = pair
    rng = np.random.default_rng(3)
    q, v, a = structure.random_states(8, rng)
    tau = arm.inverse_dynamics(q, v, a)
    np.testing.assert_allclose(structure.inverse_dynamics(params, q, v, a), tau, atol=1e-10)
    y = structure.regressor(q, v, a)
    np.testing.assert_allclose(np.einsum('knp,p->kn', y, params), tau, atol=1e-10)
    np.testing.assert_allclose(structure.mass_matrix(params, q), arm.mass_matrix(q), atol=1e-12)
    np.testing.assert_allclose(structure.gravity_torque(params, q), arm.gravity_terms(q),
                               atol=1e-10)
    np.testing.assert_allclose(structure.accelerations(params, q, v, tau), a, atol=1e-8)
    rows = structure.rows(q, v, a, [0, 5, 11])
    np.testing.assert_array_equal(rows, y.reshape(-1, y.shape[-1])[:, [0, 5, 11]])


def test_the_parameters_convert_to_and_from_pinocchios_order(pair):
    arm, structure, _ = pair
    body = structure.prior[:N_INERTIAL]
    expected = np.asarray(arm.model.inertias[1].toDynamicParameters()).ravel()
    np.testing.assert_allclose(to_pinocchio_order(body), expected)


def test_joint_terms_add_rotor_inertia_friction_and_an_offset(pair):
    _, structure, params = pair
    n = structure.n_joints
    p = params.copy()
    joint = p[N_INERTIAL * n:].reshape(n, 4)
    joint[:] = [0.1, 2.0, 0.5, -0.3]
    q, v, a = structure.random_states(3, np.random.default_rng(1))
    bare = structure.inverse_dynamics(params, q, v, a)
    vc = structure.tree.coulomb_velocity
    expected = bare + 0.1 * a + 2.0 * v + 0.5 * np.tanh(v / vc) - 0.3
    np.testing.assert_allclose(structure.inverse_dynamics(p, q, v, a), expected, atol=1e-10)
    np.testing.assert_allclose(structure.mass_matrix(p, q),
                               structure.mass_matrix(params, q) + 0.1 * np.eye(n), atol=1e-12)


def test_the_base_parameters_span_every_column(pair):
    _, structure, _ = pair
    base = structure.base
    q, v, a = structure.random_states(30, np.random.default_rng(9))
    y = structure.rows(q, v, a)
    np.testing.assert_allclose(y[:, base.dependent], y[:, base.independent] @ base.combination,
                               atol=1e-8)
    assert 0 < base.rank < structure.n_parameters
    p = np.random.default_rng(2).normal(size=structure.n_parameters)
    np.testing.assert_allclose(y @ p, y[:, base.independent] @ base.of(p), atol=1e-8)


def test_the_log_cholesky_map_gives_realizable_bodies_and_its_jacobian():
    rng = np.random.default_rng(0)
    phi = rng.normal(size=(4, 10))
    pi, jac = consistency.parameters(phi, jacobian=True)
    assert np.all(consistency.realizable(pi))
    eps = 1e-6
    for k in range(10):
        step = np.zeros(10)
        step[k] = eps
        numeric = (consistency.parameters(phi + step) - consistency.parameters(phi - step)) / (
            2 * eps)
        np.testing.assert_allclose(jac[:, :, k], numeric, atol=1e-7)
    np.testing.assert_allclose(consistency.coordinates(pi), phi, atol=1e-10)


def test_an_unrealizable_body_is_moved_inside():
    # a rod whose inertia breaks the triangle inequality, and a massless link
    bad = np.array([[1.0, 0, 0, 0, 1.0, 0.1, 0.1, 0, 0, 0], [0.0] * 10])
    assert not consistency.realizable(bad).all()
    inside = consistency.parameters(consistency.coordinates(bad))
    assert np.all(consistency.realizable(inside))
    assert abs(inside[0, 0] - 1.0) < 1e-3


def test_the_consistent_fit_recovers_exact_torques_and_stays_realizable(pair):
    _, structure, params = pair
    rng = np.random.default_rng(5)
    q, v, a = structure.random_states(400, rng)
    truth = params.copy()
    truth[N_INERTIAL * structure.n_joints:].reshape(-1, 4)[:] = [0.02, 0.5, 0.2, 0.1]
    rows = structure.rows(q, v, a)
    tau = rows @ truth
    # a prior off by 30 % in every mass (the CAD guess a user has)
    prior = params.copy()
    prior[:N_INERTIAL * structure.n_joints] *= 1.3
    fit = fit_consistent(structure, rows, tau, prior=prior)
    bodies = fit.parameters[:N_INERTIAL * structure.n_joints].reshape(-1, 10)
    assert np.all(consistency.realizable(bodies, 1e-9))
    assert fit.rms_residual < 1e-3 * np.sqrt(np.mean(tau ** 2))
    # and it holds on states it never saw
    q, v, a = structure.random_states(50, np.random.default_rng(6))
    fresh = structure.rows(q, v, a)
    error = np.sqrt(np.mean((fresh @ fit.parameters - fresh @ truth) ** 2))
    assert error < 1e-2 * np.sqrt(np.mean((fresh @ truth) ** 2))


def exact_rows(structure, params, seed, n=200):
    """Return the regressor's rows at ``n`` random states and their exact torque."""
    q, v, a = structure.random_states(n, np.random.default_rng(seed))
    rows = structure.rows(q, v, a)
    return rows, rows @ params


def test_an_svd_that_does_not_converge_falls_back_to_the_iterative_step(pair, monkeypatch):
    # LAPACK's SVD in the dense trust-region step failed to converge once online; the fit
    # takes the iterative step then instead of failing the refit
    import scipy.optimize
    _, structure, params = pair
    rows, tau = exact_rows(structure, params, seed=7)
    real = scipy.optimize.least_squares
    solvers = []

    def flaky(*args, **kwargs):
        solvers.append(kwargs.get('tr_solver', 'exact'))
        if solvers[-1] == 'exact':
            raise np.linalg.LinAlgError('SVD did not converge')
        return real(*args, **kwargs)

    monkeypatch.setattr(scipy.optimize, 'least_squares', flaky)
    fit = fit_consistent(structure, rows, tau)
    assert solvers == ['exact', 'lsmr']
    assert fit.rms_residual < 1e-2 * np.sqrt(np.mean(tau ** 2))


def test_a_trial_step_that_overflows_is_no_warning_of_the_consistent_fit(pair, monkeypatch):
    # the trust region may try a step whose log-Cholesky exponentials overflow; the solver
    # rejects the non-finite residual, and the node's log gets no RuntimeWarning for it
    import scipy.optimize
    import warnings
    _, structure, params = pair
    rows, tau = exact_rows(structure, params, seed=8)
    real = scipy.optimize.least_squares
    tried = []

    def far_first(residual, x0, **kwargs):
        tried.append(residual(np.full_like(x0, 800.0)))   # a step far out: exp overflows
        return real(residual, x0, **kwargs)

    monkeypatch.setattr(scipy.optimize, 'least_squares', far_first)
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        fit = fit_consistent(structure, rows, tau)
    assert not np.all(np.isfinite(tried[0]))
    assert fit.rms_residual < 1e-2 * np.sqrt(np.mean(tau ** 2))


def test_a_description_with_a_prismatic_joint_is_refused():
    urdf = ('<robot name="r"><link name="a"/><link name="b"><inertial><mass value="1"/>'
            '<inertia ixx="1" iyy="1" izz="1" ixy="0" ixz="0" iyz="0"/></inertial></link>'
            '<joint name="j" type="prismatic"><parent link="a"/><child link="b"/>'
            '<axis xyz="0 0 1"/><limit lower="0" upper="1" effort="1" velocity="1"/></joint>'
            '</robot>')
    with pytest.raises(DescriptionError, match='only revolute'):
        RigidStructure(urdf, ['j'])


def test_joint_names_that_differ_from_the_description_are_refused():
    arm = UrdfArm(UR5)
    with pytest.raises(DescriptionError, match='moving joints'):
        RigidStructure(arm.urdf, list(arm.joint_names[:5]) + ['elsewhere'])


def test_the_identified_urdf_reads_back_as_the_same_dynamics(pair):
    from rkgnn_ros.core.rigid.urdf_out import identified_urdf
    _, structure, params = pair
    n = structure.n_joints
    fitted = params.copy()
    fitted[:N_INERTIAL * n] *= 1.2
    fitted[N_INERTIAL * n:].reshape(n, 4)[:] = [0.0, 0.7, 0.4, 0.0]
    text = identified_urdf(structure, fitted, 'a test')
    again = RigidStructure(text, structure.joint_names)
    q, v, a = structure.random_states(6, np.random.default_rng(4))
    # the URDF's <dynamics> carries the friction back; rotor inertia and offset were 0
    np.testing.assert_allclose(again.inverse_dynamics(again.prior, q, v, a),
                               structure.inverse_dynamics(fitted, q, v, a), atol=1e-9)
    assert text.startswith('<!-- identified by rkgnn_ros: a test')


@pytest.mark.parametrize('rows', [3, 7, 4001, 4500])
def test_triangular_rows_keep_every_residual_by_blocks_of_rows(rows, monkeypatch):
    from rkgnn_ros.core.rigid import solve
    from rkgnn_ros.core.rigid.solve import triangular_rows
    monkeypatch.setattr(solve, 'QR_BLOCK_ROWS', 1000)
    rng = np.random.default_rng(rows)
    a, y = rng.standard_normal((rows, 6)), rng.standard_normal(rows)
    r, c, rest = triangular_rows(a, y)
    assert r.shape == (6, 6) and c.shape == (6,) and rest >= 0.0
    assert np.allclose(np.tril(r, -1), 0.0)
    for x in rng.standard_normal((5, 6)):
        np.testing.assert_allclose(np.sum((a @ x - y) ** 2),
                                   np.sum((r @ x - c) ** 2) + rest, rtol=1e-10)

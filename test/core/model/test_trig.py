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

"""The trigonometric basis: features, gradients, counts, and the serial-chain structure."""

import itertools

import numpy as np
import pytest
from rkgnn_ros.core.model.trig import (evaluate_features, feature_counts, feature_names,
                                       mass_support, modes, run_modes, TrigBasis)
from rkgnn_ros.core.sim.parameters import ArmParameters
from rkgnn_ros.core.sim.plant import PlanarArm
from spatial_arm import SpatialArm


@pytest.fixture
def rng():
    return np.random.default_rng(20261124)


def planar_arm(n, mass_model, rng):
    return PlanarArm(ArmParameters(masses=rng.uniform(0.5, 6.0, n),
                                   lengths=rng.uniform(0.1, 0.5, n), mass_model=mass_model))


def residual_in_span(features, values):
    """Relative residual of the least-squares fit of ``values`` (T, K) by ``features``."""
    coef, *_ = np.linalg.lstsq(features, values, rcond=None)
    return float(np.abs(features @ coef - values).max() / np.abs(values).max())


# -- features -----------------------------------------------------------------------------

@pytest.mark.parametrize('settings', [{'n_joints': 3, 'mass_degree': 1},
                                      {'n_joints': 3, 'mass_degree': 2},
                                      {'n_joints': 4, 'planar': True},
                                      {'n_joints': 4, 'mass_degree': 2, 'max_order': 2}])
def test_gradients_match_central_differences(settings, rng):
    basis = TrigBasis(**settings)
    theta = rng.uniform(-np.pi, np.pi, (20, basis.n_joints))
    values, grads = basis.values(theta, gradient=True)
    np.testing.assert_allclose(values, basis.values(theta))
    step = 1e-6
    for k in range(basis.n_joints):
        e = np.zeros(basis.n_joints)
        e[k] = step
        fd = (basis.values(theta + e) - basis.values(theta - e)) / (2 * step)
        np.testing.assert_allclose(grads[..., k], fd, atol=1e-8)


def test_modes_span_exactly_the_products_of_factors(rng):
    # products of (1, cos, sin, cos 2θ, sin 2θ) over 2 joints, against the 25 modes
    theta = rng.uniform(-np.pi, np.pi, (400, 2))
    c, s = np.cos(theta), np.sin(theta)
    factors = np.stack([np.ones_like(c), c, s, np.cos(2 * theta), np.sin(2 * theta)], -1)
    products = np.stack([factors[:, 0, a] * factors[:, 1, b]
                         for a, b in itertools.product(range(5), repeat=2)], axis=-1)
    freq, kinds = modes(2, [0, 1], degree=2)
    fourier = evaluate_features(freq, kinds, theta)
    assert fourier.shape[1] == products.shape[1] == 25
    assert residual_in_span(fourier, products) < 1e-12
    assert residual_in_span(products, fourier) < 1e-12
    assert np.linalg.matrix_rank(fourier) == 25


def test_every_mode_appears_once():
    freq, kinds = modes(3, [0, 1, 2], degree=2)
    keys = {(tuple(m), k) for m, k in zip(freq.tolist(), kinds.tolist())}
    assert len(keys) == freq.shape[0] == 5 ** 3
    # m and -m give the same feature: only the first non-zero entry positive is kept
    assert all(next(c for c in m if c) > 0 for m in freq.tolist() if any(m))


def test_feature_names():
    freq, kinds = run_modes(3, [1, 2])
    assert feature_names(freq, kinds) == ('1', 'cos(θ2)', 'sin(θ2)', 'cos(θ2+θ3)',
                                          'sin(θ2+θ3)', 'cos(θ3)', 'sin(θ3)')
    assert feature_names([[0, 2, -1]], [1]) == ('sin(2θ2-θ3)',)


def test_run_modes_refuse_joints_that_are_not_consecutive():
    with pytest.raises(ValueError, match='consecutive'):
        run_modes(4, [0, 2])


# -- counts -------------------------------------------------------------------------------

@pytest.mark.parametrize('n', [1, 2, 3, 4])
@pytest.mark.parametrize('settings', [{'mass_degree': 1}, {'mass_degree': 2},
                                      {'mass_degree': 1, 'chain': False},
                                      {'mass_degree': 2, 'max_order': 1},
                                      {'planar': True}, {'planar': True, 'tied': True}])
def test_counts_in_closed_form_match_the_tables(n, settings):
    basis = TrigBasis(n, **settings)
    counts = feature_counts(n, **settings)
    assert counts['mass'] == basis.n_mass_coefficients
    assert counts['potential'] == basis.n_potential_coefficients


def test_documented_counts():
    total = {n: feature_counts(n, 2) for n in (2, 3, 4, 6, 7)}
    assert [(c['mass'], c['potential']) for c in total.values()] == [
        (11, 8), (86, 26), (586, 80), (22461, 728), (131836, 2186)]
    planar = [feature_counts(n, planar=True) for n in (2, 3, 4, 6, 7)]
    assert [(c['mass'], c['potential']) for c in planar] == [
        (7, 4), (28, 6), (80, 8), (371, 12), (672, 14)]
    tied = feature_counts(6, planar=True, tied=True)
    assert tied == {'mass': 36, 'potential': 12, 'total': 48}
    assert feature_counts(6, 2, max_order=2)['mass'] == 1981
    assert feature_counts(7, 2, max_order=2)['mass'] == 3836
    # without the chain structure every entry takes all 3^n (degree 1) modes
    assert feature_counts(3, 1, chain=False)['mass'] == 6 * 27


def test_pruning_rules_hold_in_the_table():
    basis = TrigBasis(5, mass_degree=2, max_order=2)
    for (i, j), ix in zip(basis.mass_entries, basis.mass_index):
        used = np.flatnonzero(np.any(basis.frequencies[ix] != 0, axis=0))
        assert set(used) <= set(mass_support(i, j, 5))
        assert np.count_nonzero(basis.frequencies[ix], axis=1).max() <= 2
        assert np.abs(basis.frequencies[ix]).max() == (2 if mass_support(i, j, 5) else 0)
    # U keeps every joint and every order, at degree 1
    pot = basis.frequencies[basis.potential_index]
    assert np.count_nonzero(pot, axis=1).max() == 5 and np.abs(pot).max() == 1
    assert basis.kinds[0] == 0 and not np.any(basis.frequencies[0])        # the constant
    assert 0 not in set(basis.potential_index)
    skip = TrigBasis(3, potential_skips_first=True)
    assert not np.any(skip.frequencies[skip.potential_index][:, 0])


def test_basis_round_trips_through_its_settings():
    basis = TrigBasis(4, mass_degree=2, max_order=3, potential_skips_first=True)
    again = TrigBasis(**basis.to_dict())
    np.testing.assert_array_equal(again.frequencies, basis.frequencies)
    assert again.n_mass_coefficients == basis.n_mass_coefficients


# -- the serial-chain structure -----------------------------------------------------------

def invariance(mass_matrix, n, rng, count=30):
    """Return, per entry (i, j) and joint k, the largest change of M_ij when θ_k moves."""
    theta = rng.uniform(-np.pi, np.pi, (count, n))
    base = mass_matrix(theta)
    change = np.zeros((n, n, n))
    for k in range(n):
        moved = theta.copy()
        moved[:, k] += rng.uniform(0.5, 2.5, count)
        change[:, :, k] = np.abs(mass_matrix(moved) - base).max(axis=0)
    return change / np.abs(base).max()


@pytest.mark.parametrize('arm_kind', ['point', 'rod', 'spatial'])
def test_mass_entry_depends_only_on_the_joints_after_min_index(arm_kind, rng):
    arm = SpatialArm.elbow() if arm_kind == 'spatial' else planar_arm(4, arm_kind, rng)
    n = arm.n_joints
    change = invariance(arm.mass_matrix, n, rng)
    for i in range(n):
        for j in range(n):
            for k in range(n):
                if k <= min(i, j):
                    assert change[i, j, k] < 1e-12, (i, j, k)
    # and it does depend on the joint right after min(i, j) (the rule is not vacuous)
    assert all(change[i, i, i + 1] > 1e-3 for i in range(n - 1))


def test_link_potential_depends_only_on_joints_up_to_the_link(rng):
    arm = SpatialArm.elbow()
    theta = rng.uniform(-np.pi, np.pi, (30, 3))
    for link in range(3):
        base = arm.link_potential(theta, link)
        for k in range(3):
            moved = theta.copy()
            moved[:, k] += 1.0
            change = np.abs(arm.link_potential(moved, link) - base).max()
            if k > link:
                assert change < 1e-12
            else:
                assert change > 1e-3


@pytest.mark.parametrize('mass_model', ['point', 'rod'])
def test_a_planar_arm_lies_in_the_planar_basis(mass_model, rng):
    arm = planar_arm(4, mass_model, rng)
    theta = rng.uniform(-np.pi, np.pi, (300, 4))
    m = arm.mass_matrix(theta)
    for name, basis in (('planar', TrigBasis(4, planar=True)),
                        ('degree 1', TrigBasis(4, mass_degree=1))):
        phi, grad = basis.values(theta, gradient=True)
        for (i, j), ix in zip(basis.mass_entries, basis.mass_index):
            assert residual_in_span(phi[:, ix], m[:, i, j]) < 1e-10, (name, i, j)
        # G = ∇U with U in the potential's features: fit G through their gradients
        pot = grad[:, basis.potential_index, :].transpose(0, 2, 1)
        pot = pot.reshape(-1, basis.potential_index.size)
        assert residual_in_span(pot, arm.gravity_terms(theta).reshape(-1)) < 1e-10, name


def test_a_spatial_arm_needs_degree_two_in_its_mass_matrix(rng):
    arm = SpatialArm.elbow()
    theta = rng.uniform(-np.pi, np.pi, (150, 3))
    m = arm.mass_matrix(theta)
    worst = {}
    for degree in (1, 2):
        basis = TrigBasis(3, mass_degree=degree)
        phi = basis.values(theta)
        worst[degree] = max(residual_in_span(phi[:, ix], m[:, i, j])
                            for (i, j), ix in zip(basis.mass_entries, basis.mass_index))
    assert worst[2] < 1e-10
    assert worst[1] > 1e-2
    # the potential: degree 1 in every joint, all joints with gravity across joint 1 ...
    basis = TrigBasis(3)
    phi = basis.values(theta)
    u = arm.potential(theta)
    with_constant = np.column_stack([np.ones(len(theta)), phi[:, basis.potential_index]])
    assert residual_in_span(with_constant, u - u.mean()) < 1e-10
    # ... and none of joint 1 when gravity is parallel to its axis
    vertical = SpatialArm.elbow(gravity=(0.0, 0.0, -9.81))
    skip = TrigBasis(3, potential_skips_first=True)
    phi = skip.values(theta)
    u = vertical.potential(theta)
    with_constant = np.column_stack([np.ones(len(theta)), phi[:, skip.potential_index]])
    assert residual_in_span(with_constant, u - u.mean()) < 1e-10


def test_tied_planar_basis_holds_every_planar_arm_and_no_spatial_one(rng):
    basis = TrigBasis(4, planar=True, tied=True)
    tie = basis.mass_tie
    assert tie.shape == (basis.n_entry_features, 16)
    theta = rng.uniform(-np.pi, np.pi, (300, 4))
    phi = basis.values(theta)

    def entry_features(entry_coefficients):
        # the (T, E) values of the entries for the tied coefficients' columns
        cols, start = [], 0
        for ix in basis.mass_index:
            cols.append(phi[:, ix] @ entry_coefficients[start:start + ix.size])
            start += ix.size
        return np.stack(cols, axis=1)

    design = np.stack([entry_features(tie[:, c]) for c in range(16)], axis=-1)  # (T, E, C)
    design = design.reshape(-1, 16)
    for mass_model in ('point', 'rod'):
        arm = planar_arm(4, mass_model, rng)
        m = arm.mass_matrix(theta)
        target = np.stack([m[:, i, j] for i, j in basis.mass_entries], axis=1).reshape(-1)
        assert residual_in_span(design, target) < 1e-10
    # the tying is the planar chain's own structure: a spatial arm's M is not in it
    spatial = SpatialArm.elbow()
    tied3 = TrigBasis(3, planar=True, tied=True)
    phi3 = tied3.values(theta[:, :3])
    cols = []
    for c in range(9):
        start, entries = 0, []
        for ix in tied3.mass_index:
            entries.append(phi3[:, ix] @ tied3.mass_tie[start:start + ix.size, c])
            start += ix.size
        cols.append(np.stack(entries, axis=1))
    m = spatial.mass_matrix(theta[:, :3])
    target = np.stack([m[:, i, j] for i, j in tied3.mass_entries], axis=1).reshape(-1)
    assert residual_in_span(np.stack(cols, axis=-1).reshape(-1, 9), target) > 1e-2


def test_tied_needs_the_planar_chain():
    with pytest.raises(ValueError, match='tied needs planar'):
        TrigBasis(3, tied=True)

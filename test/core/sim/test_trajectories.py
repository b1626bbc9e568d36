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

"""Reference trajectories: shapes, exact derivatives, interpolation, validation."""

from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
import pytest
from rkgnn_ros.core.sim.trajectories import (
    Chirp, hanging_pose, heldout_reference, paper_reference, SampledReference, SumOfSines,
    Switched)


def central_difference(reference, t, eps=1e-6):
    plus, _ = reference.evaluate(t + eps)
    minus, _ = reference.evaluate(t - eps)
    return (plus - minus) / (2 * eps)


@pytest.fixture
def sines():
    return SumOfSines([0.1, -0.2], [[0.3, 0.1], [0.2, 0.05]], [[0.2, 0.7], [0.4, 1.3]],
                      [[0.0, 1.0], [2.0, 3.0]])


def test_shapes_scalar_and_array(sines):
    theta_d, theta_d_dot = sines.evaluate(0.3)
    assert theta_d.shape == (2,) and theta_d_dot.shape == (2,)
    theta_d, theta_d_dot = sines.evaluate(np.linspace(0, 1, 7))
    assert theta_d.shape == (7, 2) and theta_d_dot.shape == (7, 2)
    theta_d, _ = sines.evaluate(np.float64(0.3))
    assert theta_d.shape == (2,)
    np.testing.assert_array_equal(sines.evaluate(0.3)[0], sines.evaluate([0.3])[0][0])


def test_sum_of_sines_values_and_derivative(sines):
    t = np.linspace(-2.0, 20.0, 301)
    theta_d, theta_d_dot = sines.evaluate(t)
    expected = 0.1 + 0.3 * np.sin(2 * np.pi * 0.2 * t) + 0.1 * np.sin(2 * np.pi * 0.7 * t + 1)
    np.testing.assert_allclose(theta_d[:, 0], expected, atol=1e-14)
    np.testing.assert_allclose(theta_d_dot, central_difference(sines, t), atol=1e-8)


def test_chirp_derivative_and_held_final_frequency():
    chirp = Chirp([0.0, -1.0], [0.5, 0.2], 0.1, [1.0, 2.0], duration=10.0)
    t = np.concatenate([np.linspace(-3.0, 15.0, 401), [10.0]])
    _, theta_d_dot = chirp.evaluate(t)
    np.testing.assert_allclose(theta_d_dot, central_difference(chirp, t), atol=1e-7)
    # after the sweep the final frequency is held: periodic with period 1 / f1
    late = np.linspace(11.0, 14.0, 50)
    np.testing.assert_allclose(chirp.evaluate(late)[0][:, 0],
                               chirp.evaluate(late + 1.0)[0][:, 0], atol=1e-12)
    np.testing.assert_allclose(chirp.evaluate(late)[0][:, 1],
                               chirp.evaluate(late + 0.5)[0][:, 1], atol=1e-12)
    # continuous at the end of the sweep
    before, after = chirp.evaluate([10.0 - 1e-9, 10.0 + 1e-9])
    np.testing.assert_allclose(before[0], before[1], atol=1e-8)
    np.testing.assert_allclose(after[0], after[1], atol=1e-6)


def test_sampled_reference_reproduces_a_smooth_function():
    t = np.linspace(0.0, 5.0, 501)
    omega = np.array([1.3, 2.9])
    truth = np.sin(np.outer(t, omega))
    truth_dot = omega * np.cos(np.outer(t, omega))
    ref = SampledReference(t, truth, truth_dot)
    # exact at the knots
    theta_d, theta_d_dot = ref.evaluate(t)
    np.testing.assert_array_equal(theta_d, truth)
    np.testing.assert_array_equal(theta_d_dot, truth_dot)
    # between the knots: cubic Hermite error O(h⁴)
    mid = 0.5 * (t[1:] + t[:-1])
    theta_d, theta_d_dot = ref.evaluate(mid)
    np.testing.assert_allclose(theta_d, np.sin(np.outer(mid, omega)), atol=1e-9)
    np.testing.assert_allclose(theta_d_dot, omega * np.cos(np.outer(mid, omega)), atol=1e-6)
    # velocities from finite differences when absent: still accurate
    ref_fd = SampledReference(t, truth)
    theta_d, theta_d_dot = ref_fd.evaluate(mid)
    np.testing.assert_allclose(theta_d, np.sin(np.outer(mid, omega)), atol=1e-5)
    np.testing.assert_allclose(theta_d_dot, omega * np.cos(np.outer(mid, omega)), atol=1e-3)


def test_sampled_reference_is_held_outside_its_range():
    t = np.array([1.0, 2.0, 3.0])
    theta = np.array([[0.0], [1.0], [4.0]])
    ref = SampledReference(t, theta, np.array([[1.0], [2.0], [3.0]]))
    theta_d, theta_d_dot = ref.evaluate([-5.0, 0.999, 3.5, 100.0])
    np.testing.assert_array_equal(theta_d[:, 0], [0.0, 0.0, 4.0, 4.0])
    np.testing.assert_array_equal(theta_d_dot[:, 0], 0.0)
    assert ref.evaluate(2.0)[1][0] == pytest.approx(2.0)


@settings(max_examples=30, deadline=None)
@given(st.integers(2, 12), st.integers(1, 4), st.integers(0, 2 ** 32 - 1))
def test_sampled_reference_exact_at_knots_property(n_samples, n_joints, seed):
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.01, 1.0, n_samples))
    theta = rng.normal(size=(n_samples, n_joints))
    theta_dot = rng.normal(size=(n_samples, n_joints))
    theta_d, theta_d_dot = SampledReference(t, theta, theta_dot).evaluate(t)
    np.testing.assert_array_equal(theta_d, theta)
    np.testing.assert_array_equal(theta_d_dot, theta_dot)


@pytest.mark.parametrize('args, match', [
    (([0.0, 1.0, 1.0], np.zeros((3, 1))), 'increasing'),
    (([0.0], np.zeros((1, 1))), 'at least 2'),
    (([0.0, 1.0], np.zeros((3, 1))), 'theta_d'),
    (([0.0, 1.0], np.zeros(2)), 'theta_d'),
    (([0.0, 1.0], np.zeros((2, 1)), np.zeros((2, 2))), 'theta_d_dot'),
    (([0.0, np.nan], np.zeros((2, 1))), 't must be finite'),
    (([0.0, 1.0], [[0.0], [np.inf]]), 'theta_d must be finite'),
])
def test_sampled_reference_validation(args, match):
    with pytest.raises(ValueError, match=match):
        SampledReference(*args)


def test_sum_of_sines_and_chirp_validation():
    with pytest.raises(ValueError, match='amplitudes'):
        SumOfSines([0.0, 0.0], [[1.0]], [[1.0]], [[0.0]])
    with pytest.raises(ValueError, match='frequencies_hz'):
        SumOfSines([0.0], [[1.0]], [[np.nan]], [[0.0]])
    with pytest.raises(ValueError, match='phases'):
        SumOfSines([0.0], [[1.0]], [[1.0]], [[0.0, 1.0]])
    with pytest.raises(ValueError, match='duration'):
        Chirp([0.0], [1.0], 0.1, 1.0, duration=0.0)
    with pytest.raises(ValueError, match='f1_hz'):
        Chirp([0.0], [1.0], 0.1, [1.0, 2.0], duration=1.0)
    with pytest.raises(ValueError, match='t must be finite'):
        paper_reference().evaluate(np.nan)
    with pytest.raises(ValueError, match='t must be'):
        paper_reference().evaluate(np.zeros((2, 2)))


def test_paper_reference_swings_about_the_hanging_pose():
    ref = paper_reference()
    assert ref.n_joints == 3
    np.testing.assert_allclose(ref.offsets, [-np.pi / 2, 0.0, 0.0])
    total = ref.amplitudes.sum(axis=1)
    assert np.all((total >= 0.3) & (total <= 0.6))
    assert np.all((ref.frequencies_hz >= 0.1) & (ref.frequencies_hz <= 0.8))
    t = np.linspace(0.0, 60.0, 6001)
    theta_d, _ = ref.evaluate(t)
    np.testing.assert_array_equal(theta_d, paper_reference().evaluate(t)[0])  # fixed numbers
    assert np.all(np.abs(theta_d - ref.offsets) <= total + 1e-12)
    for n in (1, 2, 5):
        assert paper_reference(n).evaluate(t)[0].shape == (t.size, n)
    np.testing.assert_array_equal(hanging_pose(4), [-np.pi / 2, 0.0, 0.0, 0.0])


def test_heldout_reference_differs_and_is_reproducible():
    paper, heldout = paper_reference(), heldout_reference(seed=3)
    assert heldout.amplitudes.shape == (3, 4)
    assert not np.any(np.isclose(heldout.frequencies_hz[:, :, None],
                                 paper.frequencies_hz[:, None, :], atol=1e-3))
    np.testing.assert_allclose(heldout.offsets, paper.offsets)
    np.testing.assert_array_equal(heldout.frequencies_hz,
                                  heldout_reference(seed=3).frequencies_hz)
    assert not np.array_equal(heldout.phases, heldout_reference(seed=4).phases)


def test_random_sum_of_sines_uses_the_given_rng():
    a = SumOfSines.random(3, np.random.default_rng(7), amplitude=0.4, max_frequency_hz=0.5)
    b = SumOfSines.random(3, np.random.default_rng(7), amplitude=0.4, max_frequency_hz=0.5)
    np.testing.assert_array_equal(a.phases, b.phases)
    np.testing.assert_allclose(a.amplitudes.sum(axis=1), 0.4)
    assert np.all(a.frequencies_hz <= 0.5) and np.all(a.frequencies_hz >= 0.1)


def _task_change(at=5.0, blend=2.0):
    second = SumOfSines.random(3, np.random.default_rng(2), offsets=hanging_pose(3) + 0.4)
    return paper_reference(3), second, Switched(paper_reference(3), second, at, blend)


def test_switched_is_the_first_before_and_the_second_after_the_join():
    first, second, switched = _task_change()
    for t, source in ((np.linspace(0.0, 5.0, 51), first),
                      (np.linspace(7.0, 20.0, 131), second)):
        theta, theta_dot = switched.evaluate(t)
        want, want_dot = source.evaluate(t)
        np.testing.assert_allclose(theta, want, rtol=0, atol=1e-12)
        np.testing.assert_allclose(theta_dot, want_dot, rtol=0, atol=1e-12)


def test_switched_velocity_is_the_derivative_and_nothing_jumps():
    _, _, switched = _task_change()
    t = np.linspace(4.0, 8.0, 401)                 # across both ends of the join
    _, theta_dot = switched.evaluate(t)
    np.testing.assert_allclose(theta_dot, central_difference(switched, t), rtol=0, atol=1e-6)
    for edge in (5.0, 7.0):
        before, before_dot = switched.evaluate(edge - 1e-9)
        after, after_dot = switched.evaluate(edge + 1e-9)
        np.testing.assert_allclose(after, before, atol=1e-7)
        np.testing.assert_allclose(after_dot, before_dot, atol=1e-6)


def test_switched_refuses_a_joint_mismatch_and_a_blend_that_is_not_positive():
    with pytest.raises(ValueError, match='joints'):
        Switched(paper_reference(3), paper_reference(2), 1.0)
    for blend in (0.0, -1.0, float('nan')):
        with pytest.raises(ValueError):
            Switched(paper_reference(3), paper_reference(3), 1.0, blend)

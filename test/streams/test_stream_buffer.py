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
StreamBuffer: reliability items 4, 9, 10, 12-15, pairing, resampling, threads.

Plain pytest, no middleware: samples are given as arrays with absolute stamps.
"""

import math
import threading

from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
import pytest
from rkgnn_ros.core.data import Dataset
from rkgnn_ros.streams.buffer import DROP_REASONS, StreamBuffer

JOINTS = ('joint1', 'joint2')
T0 = 1000.0
# counted later (no_command, resample_failed) or events on an accepted sample (clock jumps)
ADD_TIME_REASONS = set(DROP_REASONS) - {'no_command', 'resample_failed', 'clock_jump',
                                        'clock_jump_forward'}


def theta_of(t):
    """Return the analytic test signal θ (n,), θ̇ (n,) at absolute time t."""
    s = t - T0
    return (np.array([np.sin(2.0 * s), 0.5 * np.cos(3.0 * s)]),
            np.array([2.0 * np.cos(2.0 * s), -1.5 * np.sin(3.0 * s)]))


def desired_of(t):
    s = t - T0
    return np.array([np.sin(s), s]), np.array([np.cos(s), np.ones_like(s)])


def make_buffer(**overrides):
    settings_ = {'joints': JOINTS, 'model_step': 0.01, 'window': 10.0,
                 'gap_threshold': 0.1, 'need_tau': False, 'need_desired': False}
    settings_.update(overrides)
    return StreamBuffer(**settings_)


def feed_states(buffer, times, tau=False):
    for t in times:
        theta, theta_dot = theta_of(t)
        result = buffer.add_state(t, theta, theta_dot, 10.0 * theta if tau else None)
        assert result, result


def feed_commands(buffer, times):
    for t in times:
        assert buffer.add_command(t, *desired_of(t))


def grid(start, stop, step):
    return T0 + np.arange(int(round((stop - start) / step)) + 1) * step + start


def observed(buffer):
    """Return the observable buffered data as plain copies."""
    latest = buffer.latest_state()
    segments = [(d.t.copy(), d.state.copy(),
                 None if d.theta_d is None else d.theta_d.copy()) for d in buffer.snapshot()]
    stats = buffer.stats()
    return stats['state_samples'], stats['command_samples'], latest, segments


def assert_unchanged(before, after):
    assert before[:2] == after[:2]
    assert before[2][0] == after[2][0]
    np.testing.assert_array_equal(before[2][1], after[2][1])
    assert len(before[3]) == len(after[3])
    for a, b in zip(before[3], after[3]):
        for x, y in zip(a, b):
            np.testing.assert_array_equal(x, y)


def assert_counts_add_up(buffer, attempts):
    stats = buffer.stats()
    for stream, tried in attempts.items():
        dropped = sum(count for reason, count in stats['drops'][stream].items()
                      if reason in ADD_TIME_REASONS)
        assert stats['accepted'][stream] + dropped == tried, (stream, stats)


# ---------------------------------------------------------------- reliability items


@pytest.mark.parametrize('theta, reason', [
    ([math.nan, 0.0], 'non_finite'), ([0.0, math.inf], 'non_finite'),
    ([1e300, 0.0], 'out_of_range'), ([0.0], 'bad_shape'), ('abc', 'bad_shape'),
    ([[0.0, 0.0]], 'bad_shape')])
def test_item04_non_finite_sample_rejected_outputs_stay_finite(theta, reason):
    buffer = make_buffer(need_desired=True, need_tau=True)
    times = grid(0.0, 1.0, 0.01)
    feed_states(buffer, times, tau=True)
    feed_commands(buffer, times)
    before = observed(buffer)
    result = buffer.add_state(T0 + 1.005, theta, [0.0, 0.0], [0.0, 0.0])
    assert not result and result.reason == reason
    assert buffer.counters[reason] == 1
    bad_command = buffer.add_command(T0 + 1.005, theta, [0.0, 0.0])
    assert bad_command.reason == reason
    assert buffer.stats()['drops']['command'][reason] == 1
    assert buffer.add_state(math.nan, [0.0, 0.0], [0.0, 0.0], [0.0, 0.0]).reason == \
        'bad_stamp'
    assert_unchanged(before, observed(buffer))
    for segment in buffer.snapshot():
        assert np.isfinite(segment.state).all() and np.isfinite(segment.tau).all()


def test_item04_nan_torque_is_missing_when_needed():
    buffer = make_buffer(need_tau=True)
    assert buffer.add_state(T0, [0.0, 0.0], [0.0, 0.0], None).reason == 'missing_tau'
    assert buffer.add_state(T0, [0.0, 0.0], [0.0, 0.0], [math.nan, 0.0]).reason == \
        'missing_tau'
    assert buffer.add_state(T0, [0.0, math.nan], [0.0, 0.0], [math.nan, 0.0]).reason == \
        'non_finite'
    assert buffer.counters['missing_tau'] == 2
    assert buffer.stats()['state_samples'] == 0


def test_item09_out_of_order_reordered_within_tolerance_else_dropped():
    buffer = make_buffer(reorder_tolerance=0.015)
    times = grid(0.0, 1.0, 0.01)
    shuffled = list(times)
    shuffled[50], shuffled[51] = shuffled[51], shuffled[50]  # 10 ms late: reordered
    feed_states(buffer, shuffled)
    before = observed(buffer)
    late = buffer.add_state(T0 + 0.975, *theta_of(T0 + 0.975))  # 25 ms late: dropped
    assert not late and late.reason == 'out_of_order'
    assert buffer.counters['out_of_order'] == 1
    assert_unchanged(before, observed(buffer))
    assert buffer.stats()['state_samples'] == times.size
    (segment,) = buffer.snapshot()
    assert np.all(np.diff(segment.t) > 0.0)
    theta, _ = theta_of(segment.t + buffer.time_origin)
    np.testing.assert_allclose(segment.theta[:, 0], theta[0], atol=1e-3)


def test_item09_never_zero_or_negative_dt():
    buffer = make_buffer(reorder_tolerance=0.05, max_rate_hz=1000.0)
    rng = np.random.default_rng(3)
    times = T0 + np.sort(rng.uniform(0.0, 2.0, 3000))
    jittered = times + rng.normal(0.0, 0.01, times.size)
    for t in jittered:
        buffer.add_state(t, *theta_of(t))
    for segment in buffer.snapshot():
        assert np.all(np.diff(segment.t) > 0.0)
    stats = buffer.stats()
    assert stats['counters']['rate_limited'] + stats['counters']['out_of_order'] > 0
    assert_counts_add_up(buffer, {'state': times.size})


def test_item10_duplicate_stamp_keeps_first_and_counts():
    buffer = make_buffer(reorder_tolerance=0.01)
    times = grid(0.0, 1.0, 0.01)
    feed_states(buffer, times)
    before = observed(buffer)
    t_dup = times[-1]
    result = buffer.add_state(t_dup, [7.0, 7.0], [7.0, 7.0])
    assert not result and result.reason == 'duplicate_stamp'
    t_late = times[-2]  # a late duplicate (within the reorder tolerance) too
    assert buffer.add_state(t_late, [7.0, 7.0], [7.0, 7.0]).reason == 'duplicate_stamp'
    assert buffer.counters['duplicate_stamp'] == 2
    assert_unchanged(before, observed(buffer))
    t, theta, _ = buffer.latest_state()
    np.testing.assert_array_equal(theta, theta_of(t_dup)[0])  # the first one


def test_item12_gap_splits_segments_never_crossed():
    buffer = make_buffer(gap_threshold=0.05)
    first = grid(0.0, 1.0, 0.01)
    second = grid(1.5, 3.0, 0.01)
    feed_states(buffer, np.concatenate([first, second]))
    segments = buffer.snapshot()
    assert len(segments) == 2
    origin = segments.time_origin
    a, b = segments
    assert a.t[0] + origin == pytest.approx(first[0])
    assert a.t[-1] + origin == pytest.approx(first[-1])
    assert b.t[0] + origin == pytest.approx(second[0])
    assert b.t[-1] + origin == pytest.approx(second[-1])
    assert a.t[-1] + origin < T0 + 1.0 + 1e-9 and b.t[0] + origin > T0 + 1.5 - 1e-9
    assert buffer.counters['rate_limited'] == 0


def test_item13_clock_jump_back_clears_counts_and_continues():
    buffer = make_buffer(need_desired=True)
    times = grid(0.0, 2.0, 0.01)
    feed_states(buffer, times)
    feed_commands(buffer, times)
    epoch = buffer.snapshot().epoch
    first = grid(-100.0, -99.98, 0.01)  # a simulator reset: the stream moves, 3 samples
    for t in first[:2]:  # outliers until the third confirms the jump
        result = buffer.add_state(t, *theta_of(t))
        assert result.reason == 'stamp_outlier' and buffer.stats()['state_samples'] == 201
    result = buffer.add_state(first[2], *theta_of(first[2]))
    assert result.accepted and result.clock_jump
    assert buffer.counters['clock_jump'] == 1
    stats = buffer.stats()
    assert stats['state_samples'] == 3 and stats['command_samples'] == 0
    assert buffer.stream_status(T0 - 100.0, 1.0) == 'waiting'
    restart = grid(-100.0 + 0.03, -99.0, 0.01)
    feed_states(buffer, restart)
    feed_commands(buffer, np.concatenate([[T0 - 100.0], restart]))
    snapshot = buffer.snapshot()
    assert snapshot.epoch == epoch + 1
    (segment,) = snapshot
    assert segment.t[0] + snapshot.time_origin == pytest.approx(T0 - 100.0)
    assert segment.t[-1] + snapshot.time_origin == pytest.approx(T0 - 99.0)
    assert buffer.counters['clock_jump'] == 1


def test_item13_small_step_back_is_out_of_order_not_a_jump():
    buffer = make_buffer(clock_jump_threshold=1.0)
    feed_states(buffer, grid(0.0, 2.0, 0.01))
    result = buffer.add_state(T0 + 1.5, *theta_of(T0 + 1.5))
    assert result.reason == 'out_of_order' and not result.clock_jump
    assert buffer.stats()['state_samples'] == 201


def test_item14_desired_stream_waiting_stale_resumes():
    buffer = make_buffer(need_desired=True, gap_threshold=0.05, window=20.0)
    # never arrives: waiting, nothing to identify on, states wait (bounded)
    feed_states(buffer, grid(0.0, 1.0, 0.01))
    assert buffer.staleness(T0 + 1.0) is None
    assert buffer.stream_status(T0 + 1.0, 0.5) == 'waiting'
    assert buffer.snapshot() == []
    assert buffer.stats()['waiting_for_command'] == 101
    # arrives late: the waiting states are paired
    feed_commands(buffer, grid(0.0, 1.0, 0.01))
    assert buffer.stream_status(T0 + 1.0, 0.5) == 'ok'
    (segment,) = buffer.snapshot()
    assert segment.n_samples == 101
    # stops while states go on: stale, those states wait and are not used
    feed_states(buffer, grid(1.01, 3.0, 0.01))
    assert buffer.staleness(T0 + 3.0) == pytest.approx(2.0)
    assert buffer.stream_status(T0 + 3.0, 0.5) == 'stale'
    (segment,) = buffer.snapshot()
    assert segment.t[-1] + buffer.time_origin == pytest.approx(T0 + 1.01)  # 10 ms hold
    # returns: status ok, new data used, the uncovered states counted once
    feed_states(buffer, grid(3.01, 4.0, 0.01))
    feed_commands(buffer, grid(3.0, 4.0, 0.01))
    assert buffer.stream_status(T0 + 4.0, 0.5) == 'ok'
    first, second = buffer.snapshot()
    assert second.t[0] + buffer.time_origin == pytest.approx(T0 + 2.99)  # 10 ms hold
    assert second.t[-1] + buffer.time_origin == pytest.approx(T0 + 4.0)
    no_command = buffer.counters['no_command']
    assert no_command == 197  # states 1.02 ... 2.98: beyond the 10 ms tolerance
    buffer.snapshot()
    assert buffer.counters['no_command'] == no_command  # counted once


def test_item15_burst_10khz_bounded_and_counted():
    buffer = make_buffer(window=2.0, max_rate_hz=2000.0)
    times = T0 + np.arange(50_000) * 1e-4  # 10 kHz for 5 simulated seconds
    theta = np.zeros(2)
    lengths = []
    for k, t in enumerate(times):
        buffer.add_state(t, theta, theta)
        if k % 5000 == 0:
            lengths.append(buffer.stats()['state_samples'])
    stats = buffer.stats()
    assert stats['state_samples'] <= buffer.max_samples
    assert buffer.max_samples <= (2.0 + 0.1 + 0.01) * 2000 + 16
    assert max(lengths) <= buffer.max_samples
    assert stats['counters']['rate_limited'] >= 0.79 * times.size
    assert_counts_add_up(buffer, {'state': times.size})
    (segment,) = buffer.snapshot()
    assert segment.duration == pytest.approx(2.0, abs=0.0101)


# ---------------------------------------------------------------- resampling and pairing


def test_resampling_accuracy_on_smooth_signal_wall_clock_stamps():
    t0 = 1.7e9 + 0.123  # wall-clock stamps: resolution 0.24 us in float64
    buffer = make_buffer(model_step=0.005, need_tau=True, need_desired=True)
    rng = np.random.default_rng(0)
    state_times = t0 + np.cumsum(rng.uniform(0.0008, 0.0012, 3000))  # ~1 kHz, jittered
    command_times = t0 + np.arange(0.0, 3.2, 0.004)  # 250 Hz, not aligned
    for t in state_times:
        theta, theta_dot = theta_of(t - t0 + T0)
        assert buffer.add_state(t, theta, theta_dot, 10.0 * theta)
    for t in command_times:
        assert buffer.add_command(t, *desired_of(t - t0 + T0))
    (segment,) = buffer.snapshot()
    assert isinstance(segment, Dataset)
    assert segment.dt == pytest.approx(0.005, rel=1e-9)
    s = segment.t + buffer.time_origin - t0 + T0
    theta, theta_dot = theta_of(s)
    desired, desired_dot = desired_of(s)
    assert np.abs(segment.theta - np.array(theta).T).max() < 5e-6
    assert np.abs(segment.theta_dot - np.array(theta_dot).T).max() < 2e-5
    assert np.abs(segment.tau - 10.0 * np.array(theta).T).max() < 5e-5
    assert np.abs(segment.theta_d - np.array(desired).T).max() < 5e-6
    np.testing.assert_allclose(segment.theta_d_dot, np.array(desired_dot).T, atol=1e-5)
    assert segment.t[0] == pytest.approx(round(segment.t[0] / 0.005) * 0.005, abs=1e-9)


def test_same_stamps_pair_exactly():
    buffer = make_buffer(need_desired=True)
    times = grid(0.0, 1.0, 0.01)
    feed_states(buffer, times)
    feed_commands(buffer, times)
    (segment,) = buffer.snapshot()
    np.testing.assert_allclose(segment.theta_d[:, 1], segment.t + buffer.time_origin - T0,
                               atol=1e-9)


def test_states_before_first_command_counted_no_command():
    buffer = make_buffer(need_desired=True)
    feed_states(buffer, grid(0.0, 2.0, 0.01))
    feed_commands(buffer, grid(1.0, 2.0, 0.01))
    (segment,) = buffer.snapshot()
    assert segment.t[0] + buffer.time_origin == pytest.approx(T0 + 0.99)  # 10 ms hold
    assert buffer.counters['no_command'] == 99


def test_window_limits_snapshot_and_memory():
    buffer = make_buffer(window=1.0)
    feed_states(buffer, grid(0.0, 5.0, 0.01))
    (segment,) = buffer.snapshot()
    assert segment.duration == pytest.approx(1.0)
    assert segment.t[-1] + buffer.time_origin == pytest.approx(T0 + 5.0)
    assert buffer.stats()['state_samples'] <= 112  # window + gap_threshold at 100 Hz


def test_min_samples_filters_short_segments():
    buffer = make_buffer(gap_threshold=0.05)
    feed_states(buffer, np.concatenate([grid(0.0, 0.05, 0.01), grid(1.0, 2.0, 0.01)]))
    assert len(buffer.snapshot(min_samples=2)) == 2
    (segment,) = buffer.snapshot(min_samples=10)
    assert segment.n_samples == 101


def test_snapshot_is_a_copy():
    buffer = make_buffer(need_desired=True)
    times = grid(0.0, 1.0, 0.01)
    feed_states(buffer, times)
    feed_commands(buffer, times)
    (segment,) = buffer.snapshot()
    reference = segment.theta.copy()
    segment.theta[:] = 123.0
    segment.theta_d[:] = 123.0
    latest = buffer.latest_state()
    latest[1][:] = 123.0
    (again,) = buffer.snapshot()
    np.testing.assert_array_equal(again.theta, reference)
    assert not np.any(again.theta_d == 123.0)
    assert not np.any(buffer.latest_state()[1] == 123.0)


def test_clear_forgets_data_keeps_counters():
    buffer = make_buffer()
    feed_states(buffer, grid(0.0, 1.0, 0.01))
    buffer.add_state(buffer.latest_state()[0], [0.0, 0.0], [0.0, 0.0])
    buffer.clear()
    assert buffer.latest_state() is None and buffer.snapshot() == []
    assert buffer.counters['duplicate_stamp'] == 1


def test_forward_jump_clears_and_rebases():
    buffer = make_buffer(window=2.0)
    feed_states(buffer, grid(0.0, 1.0, 0.01))
    for t in (1.7e9, 1.7e9 + 0.01):  # outliers until a third sample confirms the jump
        assert buffer.add_state(t, [0.0, 0.0], [0.0, 0.0]).reason == 'stamp_outlier'
    result = buffer.add_state(1.7e9 + 0.02, [0.0, 0.0], [0.0, 0.0])
    assert result and result.clock_jump
    assert buffer.counters['clock_jump_forward'] == 1
    assert buffer.time_origin == 1.7e9
    assert buffer.stats()['state_samples'] == 3


def test_reference_interpolates_and_holds_at_rest():
    buffer = make_buffer(need_desired=True)
    times = np.array([0.0, 1.0, 2.0])
    positions = np.array([[0.0, 0.0], [1.0, 2.0], [3.0, 2.0]])
    assert buffer.reference_at([T0]) is None
    assert buffer.add_reference(T0, times, positions)
    theta_d, theta_d_dot = buffer.reference_at(T0 + np.array([-1.0, 0.5, 1.5, 5.0]))
    np.testing.assert_allclose(theta_d, [[0.0, 0.0], [0.5, 1.0], [2.0, 2.0], [3.0, 2.0]])
    np.testing.assert_allclose(theta_d_dot[[0, 3]], 0.0)  # held at rest outside
    np.testing.assert_allclose(theta_d_dot[1], [1.25, 1.5])  # from np.gradient
    bad = buffer.add_reference(T0, [0.0, 0.0, 1.0], positions)
    assert bad.reason == 'non_increasing_time'
    assert buffer.add_reference(T0, times, positions[:2]).reason == 'bad_shape'
    assert buffer.stats()['drops']['reference']['bad_shape'] == 1
    np.testing.assert_allclose(buffer.reference_at([T0 + 0.5])[0], [[0.5, 1.0]])


def test_reference_with_velocities_is_the_cubic_through_them():
    # as joint_trajectory_controller samples positions + velocities: a sine planned every
    # 20 ms is met to 1e-6 rad between its points (linear interpolation misses it by 1e-3)
    buffer = make_buffer(need_desired=True)
    w = 2.0 * math.pi * 0.7
    times = np.arange(0.0, 2.0 + 1e-9, 0.02)
    positions = np.stack([np.sin(w * times), 0.5 * np.cos(w * times)], axis=1)
    velocities = np.stack([w * np.cos(w * times), -0.5 * w * np.sin(w * times)], axis=1)
    assert buffer.add_reference(T0, times, positions, velocities)
    s = np.linspace(0.0, 2.0, 1001)
    theta_d, theta_d_dot = buffer.reference_at(T0 + s)
    np.testing.assert_allclose(theta_d[:, 0], np.sin(w * s), atol=1e-6)
    np.testing.assert_allclose(theta_d[:, 1], 0.5 * np.cos(w * s), atol=1e-6)
    np.testing.assert_allclose(theta_d_dot[:, 0], w * np.cos(w * s), atol=1e-4)
    np.testing.assert_allclose(theta_d[[0, -1]], positions[[0, -1]], atol=1e-12)  # its points
    outside = buffer.reference_at(T0 + np.array([-1.0, 3.0]))
    np.testing.assert_allclose(outside[0], positions[[0, -1]])
    np.testing.assert_allclose(outside[1], 0.0)  # held at rest outside


@pytest.mark.parametrize('overrides', [
    {'model_step': 0.0}, {'window': math.nan}, {'gap_threshold': -1.0},
    {'max_rate_hz': math.inf}, {'joints': ()}, {'joints': ('a', 'a')},
    {'reorder_tolerance': 2.0, 'clock_jump_threshold': 1.0}, {'window': 0.001}])
def test_bad_settings_refused(overrides):
    with pytest.raises(ValueError):
        make_buffer(**overrides)


# ---------------------------------------------------------------- threads and properties


def test_thread_safety_smoke():
    buffer = make_buffer(window=1.0, need_desired=True, need_tau=True, max_rate_hz=5000.0)
    attempts = {'state': 0, 'command': 0}
    errors = []
    done = threading.Event()

    def produce():
        try:
            rng = np.random.default_rng(1)
            for k in range(20_000):
                t = T0 + k * 2e-4 + (0.05 if k % 97 == 0 else 0.0)  # some out of order
                theta = rng.normal(size=2)
                if k % 101 == 0:
                    theta[0] = math.nan
                buffer.add_state(t, theta, theta, theta)
                attempts['state'] += 1
                if k % 2 == 0:
                    buffer.add_command(t, theta, theta)
                    attempts['command'] += 1
        except Exception as error:  # reported to the main thread
            errors.append(error)
        finally:
            done.set()

    snapshots = 0

    def consume():
        nonlocal snapshots
        try:
            while not done.is_set():
                for segment in buffer.snapshot():
                    assert np.isfinite(segment.state).all()
                    assert np.all(np.diff(segment.t) > 0.0)
                buffer.stats()
                buffer.latest_state()
                snapshots += 1
        except Exception as error:  # reported to the main thread
            errors.append(error)

    threads = [threading.Thread(target=produce), threading.Thread(target=consume)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=60.0)
    assert not errors, errors
    assert snapshots > 0
    assert_counts_add_up(buffer, attempts)
    drops = buffer.stats()['drops']
    assert drops['state']['non_finite'] == len(range(0, 20_000, 101))
    assert drops['command']['non_finite'] == len(range(0, 20_000, 202))


@settings(max_examples=500, deadline=None)
@given(events=st.lists(st.tuples(
    st.sampled_from(['state', 'command']),
    st.one_of(st.floats(allow_nan=True, allow_infinity=True),
              st.integers(0, 300).map(lambda k: T0 + 0.01 * k)),
    st.lists(st.one_of(st.floats(-10.0, 10.0), st.floats()), min_size=0, max_size=3),
    st.lists(st.floats(-10.0, 10.0), min_size=2, max_size=2)), max_size=60),
    need_tau=st.booleans(), need_desired=st.booleans())
def test_property_arbitrary_samples_never_raise_and_stay_finite(events, need_tau,
                                                                need_desired):
    buffer = make_buffer(need_tau=need_tau, need_desired=need_desired, gap_threshold=0.5,
                         window=2.0)
    attempts = {'state': 0, 'command': 0}
    for stream, t, values, other in events:
        if stream == 'state':
            buffer.add_state(t, values, other, other)
        else:
            buffer.add_command(t, values, other)
        attempts[stream] += 1
    for segment in buffer.snapshot():
        assert np.isfinite(segment.state).all()
        assert np.all(np.diff(segment.t) > 0.0)
        for values in (segment.tau, segment.theta_d, segment.theta_d_dot):
            assert values is None or np.isfinite(values).all()
        assert (segment.tau is not None) == need_tau
        assert (segment.theta_d is not None) == need_desired
    assert_counts_add_up(buffer, attempts)
    assert buffer.counters['resample_failed'] == 0


def test_staleness_of_an_unknown_stream_is_a_clear_error():
    buf = make_buffer()
    with pytest.raises(ValueError, match="'state' or 'command'"):
        buf.staleness(1.0, 'reference')
    assert buf.staleness(1.0, 'state') is None


@pytest.mark.parametrize('phase', [0.0, 0.0037, 0.0061])
def test_a_steady_stream_is_resampled_on_its_own_samples(phase):
    # a driver stamping at 100 Hz from any point within a second: the grid of the snapshot
    # goes through the samples, so the data are the samples themselves; with the whole
    # second below the first stamp as the time base, θ was interpolated linearly between
    # samples (off by up to h²/8 θ̈ = 5e-5 rad here where the phase is not 0)
    buffer = make_buffer()
    times = grid(phase, phase + 2.0, 0.01)
    feed_states(buffer, times)
    (segment,) = buffer.snapshot()
    assert segment.n_samples == times.size
    theta, theta_dot = theta_of(segment.t + buffer.time_origin)
    np.testing.assert_allclose(segment.theta, theta.T, rtol=0.0, atol=1e-9)
    np.testing.assert_allclose(segment.theta_dot, theta_dot.T, rtol=0.0, atol=1e-9)
    np.testing.assert_allclose(segment.t + buffer.time_origin, times, rtol=0.0, atol=1e-9)

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

"""Which model predicts: offers into use, candidates on trial, and a change of the arm."""

from types import SimpleNamespace

import numpy as np
import pytest
from rkgnn_ros.core.fitting.online_records import ClosedLoop
from rkgnn_ros.core.selfcheck import SelfCheck
from rkgnn_ros.identification.candidates import Models, predicts, Slot


def stand_in(generation):
    """Return a stand-in for a model that predicts without a loop (case unknown)."""
    return SimpleNamespace(case='unknown', info={'generation': generation})


def test_first_offer_is_taken_into_use_and_later_ones_wait_for_a_trial():
    check, models = SelfCheck(2), Models()
    first, second, third = stand_in(1), stand_in(2), stand_in(3)
    models.offer_model(first)
    in_use, candidate = models.take(check, 0.0)
    assert in_use.model is first and candidate is None
    models.offer_model(second)
    in_use, candidate = models.take(check, 0.1)
    assert in_use.model is first and candidate.model is second
    models.offer_model(third)
    in_use, candidate = models.take(check, 0.2)
    # the second stays on trial, the third waits for that trial to end
    assert in_use.model is first and candidate.model is second
    assert [slot.model for slot in models.pending()] == [second, third]


def test_a_change_drops_the_candidate_and_the_offer_waiting():
    check, models = SelfCheck(2), Models()
    before, stale, waiting, after = stand_in(1), stand_in(2), stand_in(3), stand_in(4)
    models.offer_model(before)
    models.take(check, 0.0)
    models.offer_model(stale)
    models.take(check, 0.1)
    models.offer_model(waiting)
    models.take(check, 0.15)
    assert len(models.pending()) == 2
    models.dynamics_changed()
    models.offer_model(after)        # fitted on the data after the change
    in_use, candidate = models.take(check, 0.2)
    # the model in use predicts until the new one earns it; the new one is on trial at once
    assert in_use.model is before and candidate.model is after
    assert [slot.model for slot in models.pending()] == [after]


def test_a_change_with_nothing_pending_keeps_the_model_in_use():
    check, models = SelfCheck(2), Models()
    only = stand_in(1)
    models.offer_model(only)
    models.take(check, 0.0)
    models.dynamics_changed()
    in_use, candidate = models.take(check, 0.1)
    assert in_use.model is only and candidate is None and models.pending() == []


def test_a_pid_loops_integral_is_carried_past_the_self_checks_window():
    # θd − θ = 0.1 rad throughout; Ki 2 N m/(rad s); the law's term is 1 N m at t = 0
    check, models = SelfCheck(1, window=10.0), Models()
    law = SimpleNamespace(ki=np.array([2.0]), integral_term=np.array([1.0]))
    closed = ClosedLoop(stand_in(1), SimpleNamespace(law=law), 0.0)
    t = np.arange(0.0, 40.01, 0.01)
    asked = []
    for until in (5.0, 10.0, 15.0, 20.0, 25.0, 30.0, 35.0, 40.0):
        new = (t > until - 5.0) | (until == 5.0)
        new &= t <= until
        check.add_references(t[new], np.full((new.sum(), 1), 0.6))
        check.add_states(t[new], np.full((new.sum(), 1), 0.5))
        asked.append(float(models.integral(closed, until, check)[0]))
    # 1 + 2 * 0.1 * t at each: the record keeps only the last 13 s, the carry all of it
    np.testing.assert_allclose(asked, 1.0 + 0.2 * np.array([5, 10, 15, 20, 25, 30, 35, 40]),
                               rtol=1e-9)
    # asked afresh from the loop's own time, 40 s back, the record no longer reaches it
    assert float(Models().integral(closed, 40.0, check)[0]) == 1.0


def test_a_pid_loops_integral_at_a_past_state_is_not_carried():
    # θd − θ = 0.1 rad; Ki 2; the law's term is 1 N m at its own time, 10 s: a prediction
    # made again from 5 s starts from 1 − 2 · 0.1 · 5, and the carry stays where it was
    check, models = SelfCheck(1, window=20.0), Models()
    law = SimpleNamespace(ki=np.array([2.0]), integral_term=np.array([1.0]))
    closed = ClosedLoop(stand_in(1), SimpleNamespace(law=law), 10.0)
    t = np.arange(0.0, 15.01, 0.01)
    check.add_references(t, np.full((t.size, 1), 0.6))
    check.add_states(t, np.full((t.size, 1), 0.5))
    assert float(models.integral(closed, 12.0, check)[0]) == pytest.approx(1.4)
    assert float(models.integral(closed, 5.0, check, carry=False)[0]) == pytest.approx(0.0)
    assert float(models.integral(closed, 14.0, check)[0]) == pytest.approx(1.8)


def test_a_candidate_that_cannot_predict_gives_way_to_one_that_can():
    # after a change, case 1's search restarts: its first model comes without the law (it
    # cannot predict) and held the trial for 10 s while the refitted loop waited
    check, models = SelfCheck(2), Models()
    before, lawless, after = stand_in(1), SimpleNamespace(case='torque', info={}), stand_in(3)
    models.offer_model(before)
    models.take(check, 0.0)
    models.dynamics_changed()
    models.offer_model(lawless)
    in_use, candidate = models.take(check, 0.1)
    assert candidate.model is lawless
    models.offer_model(after)
    in_use, candidate = models.take(check, 0.2)
    assert in_use.model is before and candidate.model is after
    assert models.pending() == [candidate]


def test_a_rigid_body_without_its_loop_cannot_predict_and_gives_way():
    # a rigid-body fit whose closed loop does not predict is published without one (case
    # unknown); taken for a predicting candidate, its rollout raised at every prediction and
    # no model was ever scored (the perturbed UR5's no-effort cell with gravity compensation)
    check, models = SelfCheck(2), Models()
    before = stand_in(1)
    lone = SimpleNamespace(case='unknown', kind='rigid_body', info={'generation': 2})
    assert not predicts(Slot(lone, None))
    models.offer_model(before)
    models.take(check, 0.0)
    models.offer_model(lone)
    models.take(check, 0.1)
    after = stand_in(3)
    models.offer_model(after)
    in_use, candidate = models.take(check, 0.2)
    assert in_use.model is before and candidate.model is after

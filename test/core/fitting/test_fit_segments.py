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
Every fit entry point takes the segments a gappy buffer gives: two samples, short ends.

A ``Dataset`` holds at least two samples; the one-sample segment of a gap comes from a
cut (the newest half of segments whose boundary falls half a step from the cut), and the
segments of two to four samples from drops at the ends of the window. The online policy's
fits must take them all without an exception; the offline estimators may refuse data with
nothing usable in it, with a ValueError that says so.
"""

from dataclasses import replace

import numpy as np
import pytest
from rkgnn_ros.core.fitting import (case_one, case_three, controller, global_fit, offline,
                                    search_starts, trig_loop, validation, warmstart)
from rkgnn_ros.core.fitting.identify import Evolution, fit, fit_best
from rkgnn_ros.core.fitting.linear import LinearDynamics
from rkgnn_ros.core.fitting.memory import MemoryFeed
from rkgnn_ros.core.fitting.refine import refine_equation_error
from rkgnn_ros.core.model.model import RKGNNModel
from rkgnn_ros.core.model.scales import Scales
from rkgnn_ros.core.model.spec import NetworkSpec
from rkgnn_ros.core.model.trig import TrigBasis
from rkgnn_ros.core.sim.plant import PDController, PlanarArm
from rkgnn_ros.core.sim.simulate import simulate
from rkgnn_ros.core.sim.trajectories import paper_reference

KP = np.array([32.84, 42.05, 42.31])   # the paper's servo


@pytest.fixture(scope='module')
def data():
    """8 s at 100 Hz of the paper's arm under its PD (torque and commands)."""
    return simulate(PlanarArm.paper(), PDController.paper(), paper_reference(3), 8.0,
                    rate=100.0)


def segment_lists(data):
    return {
        'two': [data.slice(500, 502)],
        'ends': [data.slice(0, 2), data.slice(10, 410), data.slice(420, 422)],
        'short_tail': [data.slice(0, 400), data.slice(410, 413)],
        # 3.00 s and 2.99 s: the newest half ends half a step into the older segment
        'half_cut': [data.slice(0, 301), data.slice(301, 601)],
        'many4': [data.slice(k, k + 4) for k in range(0, 600, 6)],
    }


def entry_points(data):
    long = data.slice(0, 401)
    law = case_one.fit_law([long])
    spec1, spec3 = NetworkSpec.recommended(3, 'torque'), NetworkSpec.recommended(3, 'unknown')
    global1 = global_fit.global_spec(3, 'torque')
    scales = Scales.from_datasets([long], 'torque')
    model = RKGNNModel(spec1, scales, spec1.initial_genome())
    loop3 = trig_loop.fit_closed_trig_loop([long], 0.25, 10)
    keeper = case_one.LawKeeper()
    keeper.law = law
    penalty = replace(spec1, inertia='penalty', velocity='learned')
    return {
        'fit_law': lambda s: case_one.fit_law(s),
        'LawKeeper.refit': lambda s: case_one.LawKeeper().refit(s, 0.0, None),
        'LawKeeper.fit_trig': lambda s: keeper.fit_trig(s, 0.25, 0.0),
        'search_segments': lambda s: case_one.search_segments(s, law),
        'fit_gains': lambda s: case_three.fit_gains(s),
        'start_genome': lambda s: case_three.start_genome(Evolution(spec3, [long]), s, 1.0, 3),
        'ArmKeeper.fit': lambda s: case_three.ArmKeeper().fit(s, 0.25, 0.0, 0.0),
        'fit_closed_trig_loop': lambda s: trig_loop.fit_closed_trig_loop(s, 0.25, 10),
        'closed_loop_error': lambda s: trig_loop.closed_loop_error(loop3, s, 0.25),
        'fit_trig_loop': lambda s: trig_loop.fit_trig_loop(s, s, law, 10),
        'fit_controller': lambda s: controller.fit_controller(s),
        'least_squares_genome': lambda s: warmstart.least_squares_genome(penalty, s, scales),
        'MemoryFeed.feed': lambda s: MemoryFeed().feed(s, 0.0, 'unknown'),
        'split_validation': lambda s: validation.split_validation(s, 0.25),
        'validation_nrmse': lambda s: validation.validation_nrmse(model, s),
        'refine_equation_error': lambda s: refine_equation_error(
            spec1, s, scales, spec1.initial_genome(), max_nfev=3),
        'warm_start': lambda s: search_starts.warm_start(Evolution(spec1, [long]), s, None,
                                                         None, 1.0, 3),
        'rewarm': lambda s: search_starts.rewarm(Evolution(global1, [long]), s, 5.0, 1.0, 3),
        'Evolution.step': lambda s: Evolution(spec1, s).step(),
        'fit': lambda s: fit(s, 'torque', max_generations=1),
        'heldout_prediction': lambda s: offline.heldout_prediction(model, s),
        # offline estimators: may refuse data with nothing usable, saying so
        'LinearDynamics.fit': lambda s: LinearDynamics(
            TrigBasis(3, planar=True, tied=True)).fit(s, 'torque'),
        'linear_fit case 3': lambda s: global_fit.linear_fit(
            s, 'unknown', global_fit.trig_table(global_fit.global_spec(3, 'unknown'))),
        'fit_best case 3': lambda s: fit_best(s, 'unknown', time_budget=0.0),
    }


#: (entry point, segment list) that refuse, and the words of their ValueError
REFUSED = {
    ('LinearDynamics.fit', 'two'): 'too few samples',
    ('linear_fit case 3', 'two'): 'no segment of at least 5 samples',
    ('linear_fit case 3', 'many4'): 'no segment of at least 5 samples',
    ('fit_best case 3', 'two'): 'no segment of at least 5 samples',
    ('fit_best case 3', 'many4'): 'no segment of at least 5 samples',
}


def test_every_fit_entry_point_takes_short_segments_and_gaps_at_both_ends(data):
    lists = segment_lists(data)
    failures = []
    for name, call in entry_points(data).items():
        for kind, segments in lists.items():
            words = REFUSED.get((name, kind))
            try:
                call(segments)
            except ValueError as error:
                if words is None or words not in str(error):
                    failures.append(f'{name} on {kind}: {type(error).__name__}: {error}')
            except Exception as error:  # noqa: B902 - every other exception is a failure
                failures.append(f'{name} on {kind}: {type(error).__name__}: {error}')
            else:
                if words is not None:
                    failures.append(f'{name} on {kind}: no ValueError ({words})')
    assert not failures, '\n'.join(failures)


def test_the_newest_half_leaves_a_one_sample_piece_out(data):
    older, newer = data.slice(0, 301), data.slice(301, 601)   # 3.00 s, 2.99 s
    half = validation.newest_share([older, newer], 0.5)
    assert [seg.t.tolist() for seg in half] == [newer.t.tolist()]
    # a cut well inside the older segment keeps round(rest / dt) + 1 samples of it
    part, whole = validation.newest_share([older, newer], 0.6)
    assert np.array_equal(whole.t, newer.t)
    assert part.n_samples == int(round((0.6 * 5.99 - 2.99) / 0.01)) + 1
    assert part.t[-1] == older.t[-1]
    # pieces shorter than the caller's minimum are left out too
    cut = validation.newest_share([older, newer], 0.6, min_samples=200)
    assert [seg.t.tolist() for seg in cut] == [newer.t.tolist()]
    assert validation.newest_share([data.slice(0, 2)], 0.5) == []


def test_the_law_and_the_gains_of_data_cut_half_a_step_from_a_gap(data):
    # the cut that made a one-sample segment before: the laws are still found
    segments = segment_lists(data)['half_cut']
    law = case_one.fit_law(segments)
    assert law is not None and law.usable(0.1)
    np.testing.assert_allclose(law.kp, KP, rtol=1e-2)
    gains = case_three.fit_gains(segments)
    if gains is not None:   # 6 s may not determine them; if given, they are the servo's
        np.testing.assert_allclose(gains[0] / gains[0].mean(), KP / KP.mean(), rtol=0.05)

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

"""identify_bag judges its model against baselines, and keeps its budget."""

from dataclasses import replace
import json
from pathlib import Path

from bag_helpers import simulated_run, write_run
import numpy as np
import pytest

pytest.importorskip('rosbags')

from rkgnn_ros.core.fitting.identify import RKGNNModel  # noqa: E402
from rkgnn_ros.identify_bag import EXIT_WORSE_THAN_BASELINE, main  # noqa: E402


def identify(capsys, bag, out, *extra):
    """Run identify_bag in-process; return (exit code, stderr, report)."""
    code = main([str(bag), '--out', str(out), '--quiet', *extra])
    err = capsys.readouterr().err
    return code, err, json.loads((Path(out) / 'report.json').read_text())


def test_a_model_worse_than_a_baseline_is_written_marked_and_exits_3(tmp_path, capsys):
    # the arm stops in the held-out 10 s while its plan goes on: holding the last state
    # predicts it exactly, a model of the servo following the plan cannot
    run = simulated_run(20.0)
    theta, theta_dot = run.theta.copy(), run.theta_dot.copy()
    still = run.t >= run.t[-1] - 10.0
    theta[still], theta_dot[still] = theta[np.argmax(still)], 0.0
    frozen = replace(run, theta=theta, theta_dot=theta_dot)
    write_run(tmp_path / 'bag', frozen)
    code, err, report = identify(capsys, tmp_path / 'bag', tmp_path / 'out',
                                 '--max-generations', '1', '--budget', '60')
    assert code == EXIT_WORSE_THAN_BASELINE == 3
    verdict = report['verdict']
    assert verdict['judged'] and verdict['worse'] and verdict['baseline'] == 'hold_last_state'
    assert report['heldout']['nrmse'] > report['heldout']['baselines']['hold_last_state']
    assert 'worse than hold last state' in err and 'Traceback' not in err
    assert RKGNNModel.load(tmp_path / 'out' / 'model.yaml').n_joints == 3   # kept
    markdown = (tmp_path / 'out' / 'report.md').read_text().splitlines()
    assert markdown[2].startswith('**Warning: the model is worse than hold last state')


def test_a_budget_of_zero_fits_one_generation_and_skips_the_figures(tmp_path, capsys):
    write_run(tmp_path / 'bag', simulated_run(20.0))
    code, err, report = identify(capsys, tmp_path / 'bag', tmp_path / 'out', '--budget', '0')
    assert code == 0, err
    assert report['fit']['generations'] == 1 and report['fit']['budget_s'] == 0.0
    assert report['figures'] == [] and 'of the budget left' in report['figures_skipped']
    assert not list((tmp_path / 'out').glob('*.png'))
    # the paper's arm closed with its learned servo law: better than both baselines
    baselines = report['heldout']['baselines']
    assert set(baselines) == {'hold_last_state', 'follow_reference'}
    assert report['verdict']['judged'] and not report['verdict']['worse']
    assert report['heldout']['nrmse'] < min(baselines.values())
    assert np.isfinite(report['heldout']['nrmse'])

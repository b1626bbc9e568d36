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

"""identify_bag: recordings written by rosbags in the test, good and bad."""

import json
import os
from pathlib import Path
import subprocess

from bag_helpers import simulated_run, write_run
import numpy as np
import pytest

pytest.importorskip('rosbags')

from repo_paths import REPO_ROOT  # noqa: E402
from rkgnn_ros.core.fitting.identify import RKGNNModel  # noqa: E402
from rkgnn_ros.identify_bag import main, read_parameters  # noqa: E402

REPO = Path(REPO_ROOT)
CONFIG = str(REPO / 'config' / 'identifier.yaml')
FAST = ['--max-generations', '3', '--budget', '60', '--quiet']


@pytest.fixture(scope='module')
def run():
    """Return 20 s of the paper's arm under its PD at 100 Hz."""
    return simulated_run(20.0)


def identify(capsys, bag, out, *extra):
    """Run identify_bag in-process; return (exit code, stdout, stderr, report or None)."""
    code = main([str(bag), '--out', str(out), *extra])
    captured = capsys.readouterr()
    report = None
    if (Path(out) / 'report.json').exists():
        report = json.loads((Path(out) / 'report.json').read_text())
    return code, captured.out, captured.err, report


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_a_recording_gives_a_model_a_report_and_figures(run, tmp_path, capsys, storage):
    bag = tmp_path / 'arm'
    write_run(bag, run, storage=storage)
    code, out, err, report = identify(capsys, bag, tmp_path / 'out', '--params-file', CONFIG,
                                      '--heldout', '5', *FAST[:-1])
    assert code == 0, err
    assert 'fitting (case torque' in out and 'held-out 5 s θ-NRMSE' in out  # progress
    model = RKGNNModel.load(tmp_path / 'out' / 'model.yaml')
    assert model.joint_names == ('joint1', 'joint2', 'joint3')
    assert report['storage'] == storage
    assert report['data']['messages']['states'] == report['data']['messages']['commands']
    assert report['data']['training']['seconds'] == pytest.approx(15.0, abs=0.2)
    assert report['data']['heldout']['seconds'] == pytest.approx(5.0, abs=0.2)
    assert report['fit']['generations'] >= 3 and len(report['history']) >= 3
    # a 3-generation fit of the paper's arm, predicted in closed loop for 5 s: a few percent
    assert 0.0 < report['heldout']['nrmse'] < 0.3
    assert 'closed loop' in report['heldout']['how']
    for name in ('report.md', 'heldout.png', 'evolution.png', 'coverage.png'):
        assert (tmp_path / 'out' / name).stat().st_size > 0


def test_controller_states_decoded_by_the_bags_own_definitions_stand_for_commands(
        run, tmp_path, capsys):
    commands, states = tmp_path / 'commands', tmp_path / 'states'
    write_run(commands, run)
    write_run(states, run, commands='', controller_state='/arm/jtc/controller_state')
    reports = []
    for bag in (commands, states):
        code, _, err, report = identify(capsys, bag, tmp_path / f'{bag.name}_out', *FAST)
        assert code == 0, err
        reports.append(report)
    assert reports[1]['topics']['controller_state'] == '/arm/jtc/controller_state'
    counts = reports[1]['data']['messages']
    assert counts['controller_states'] == counts['states'] == 1000  # the training part
    # the same θd, θ̇d: the same fit, held-out figure to rounding
    assert reports[1]['heldout']['nrmse'] == pytest.approx(reports[0]['heldout']['nrmse'],
                                                           rel=1e-6)


def test_gaps_split_the_data_and_bad_messages_are_dropped_by_the_nodes_rules(
        run, tmp_path, capsys):
    bag = tmp_path / 'gappy'
    write_run(bag, run, skip=lambda t: 6.0 <= t < 6.5, garbage=25)
    code, _, err, report = identify(capsys, bag, tmp_path / 'out', *FAST)
    assert code == 0, err
    assert report['data']['training']['segments'] == 2
    assert report['data']['drops'] == {'malformed': 25}


def test_a_recording_cut_short_is_used_up_to_where_it_breaks(run, tmp_path, capsys):
    bag = tmp_path / 'cut'
    write_run(bag, run)
    mcap = next(bag.glob('*.mcap'))
    os.truncate(mcap, mcap.stat().st_size // 2)  # a recorder killed: no index, no footer
    code, out, err, report = identify(capsys, bag, tmp_path / 'out', '--heldout', '2', *FAST)
    assert code == 0, err
    assert 'read record by record' in report['data']['truncated']
    assert 0 < report['data']['messages']['states'] < run.t.size
    assert 'Traceback' not in out + err


@pytest.mark.parametrize('case, args, message', [
    ('missing', [], 'no such file or folder'),
    ('text', [], "unknown storage format '.txt'"),
    ('junk', [], 'cannot open the mcap recording'),
    ('no_states', [], 'no sensor_msgs/msg/JointState topic named joint_states'),
    ('other_joints', ['--params-file', 'JOINTS'], 'missing_joint'),
    # case 'auto' (the default) takes a recording without effort as case 3: case 1 set
    ('no_effort', ['--params-file', 'CASE1'], 'missing_effort'),
    ('no_commands_case3', ['--params-file', 'CASE3'],
     "case 'unknown' needs joint_commands or a controller_state topic"),
    ('wrong_topic', ['--joint-states', '/joint_commands_x'], "no topic '/joint_commands_x'"),
    ('bad_params', ['--params-file', 'BAD'], "no entry for the node 'identifier'"),
])
def test_bad_recordings_end_with_one_clear_line_and_exit_code_1(
        run, tmp_path, capsys, case, args, message):
    bag = tmp_path / 'bag'
    short = simulated_run(20.0)
    if case == 'text':
        bag = tmp_path / 'notes.txt'
        bag.write_text('not a bag')
    elif case == 'junk':
        bag = tmp_path / 'junk.mcap'
        bag.write_bytes(np.random.default_rng(0).integers(0, 256, 4096,
                                                          dtype=np.uint8).tobytes())
    elif case == 'no_states':
        write_run(bag, short, states='/other_states', commands='')
    elif case in ('other_joints', 'wrong_topic', 'no_commands_case3', 'bad_params'):
        write_run(bag, short, commands='' if case == 'no_commands_case3' else '/joint_commands')
    elif case == 'no_effort':
        write_run(bag, short, effort=False)
    files = {'JOINTS': "/**/identifier:\n  ros__parameters:\n    joints: ['a', 'b', 'c']\n",
             'CASE1': "/**:\n  ros__parameters:\n    case: 'torque'\n",
             'CASE3': "/**:\n  ros__parameters:\n    case: 'unknown'\n",
             'BAD': 'sim_arm:\n  ros__parameters:\n    kp: [1.0]\n'}
    for i, arg in enumerate(args):
        if arg in files:
            path = tmp_path / f'{arg}.yaml'
            path.write_text(files[arg])
            args = args[:i] + [str(path)] + args[i + 1:]
    code, out, err, report = identify(capsys, bag, tmp_path / 'out', *args, *FAST)
    assert code == 1
    assert report is None
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith('identify_bag: error: '), err
    assert message in lines[0] and 'Traceback' not in err + out


def test_params_file_entries_apply_in_any_namespace(tmp_path):
    path = tmp_path / 'p.yaml'
    path.write_text('/**:\n  ros__parameters:\n    window: 30.0\n'
                    '/**/identifier:\n  ros__parameters:\n    es:\n      sigma: 0.3\n'
                    "/arm1/identifier:\n  ros__parameters:\n    case: 'unknown'\n"
                    'sim_arm:\n  ros__parameters:\n    kp: [1.0]\n')
    values = read_parameters(str(path))
    assert values == {'window': 30.0, 'es.sigma': 0.3}
    assert read_parameters(str(path), 'identifier') == values


def test_identify_bag_is_an_installed_executable_ros2_run_finds(run, tmp_path):
    from ament_index_python.packages import get_package_prefix
    exe = Path(get_package_prefix('rkgnn_ros')) / 'lib' / 'rkgnn_ros' / 'identify_bag'
    assert exe.is_file() and os.access(exe, os.X_OK), exe
    bag = tmp_path / 'arm'
    write_run(bag, run)
    done = subprocess.run([str(exe), str(bag), '--out', str(tmp_path / 'out'), *FAST],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert (tmp_path / 'out' / 'model.yaml').exists()

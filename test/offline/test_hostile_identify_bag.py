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
identify_bag against what the third adversarial probe (issue 31) found.

Each input ends in one line on stderr and a non-zero exit code, in bounded time and
memory: a FIFO as the recording, inside a recording folder or as ``--params-file`` (no
hang); a folder without ``metadata.yaml``; ``--heldout 1e308``, ``--budget nan``,
``--heldout nan``; a junk file (memory independent of its size); a recording in which 7
of 10 joints never move (identify_bag exited 0 with a held-out θ-NRMSE of 1.2e11).
"""

import os
import threading
import tracemalloc
import types

from bag_helpers import simulated_run, write_run
import numpy as np
import pytest

pytest.importorskip('rosbags')

from rkgnn_ros.identify_bag import main  # noqa: E402
from rkgnn_ros.recordings.reader import open_recording, RecordingError  # noqa: E402

PATIENCE = 60.0


def bounded_main(argv, timeout=PATIENCE):
    """Run identify_bag's main in a thread; return its exit code (None: it hung)."""
    outcome = {}

    def run():
        try:
            outcome['code'] = main(argv)
        except SystemExit as exc:  # argparse refusing an argument
            outcome['code'] = exc.code
    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(timeout)
    return outcome.get('code')


def _fifo(path):
    os.mkfifo(path)
    return path


@pytest.mark.parametrize('where', ['bag.mcap', 'bag', 'folder_metadata', 'folder_storage'])
def test_a_fifo_as_the_recording_is_refused_without_hanging(tmp_path, capsys, where):
    if where.startswith('folder'):
        bag = tmp_path / 'folder'
        bag.mkdir()
        if where == 'folder_metadata':
            _fifo(bag / 'metadata.yaml')
        else:
            (bag / 'metadata.yaml').write_text('rosbag2_bagfile_information: {}\n')
            _fifo(bag / 'folder_0.mcap')
    else:
        bag = _fifo(tmp_path / where)
    code = bounded_main([str(bag), '--out', str(tmp_path / 'out'), '--quiet'])
    err = capsys.readouterr().err
    assert code == 1, err
    assert 'a FIFO, not a regular file' in err and 'Traceback' not in err
    assert len(err.strip().splitlines()) == 1, err


def test_a_fifo_as_the_params_file_is_refused_without_hanging(tmp_path, capsys):
    params = _fifo(tmp_path / 'params.yaml')
    code = bounded_main([str(tmp_path / 'missing.mcap'), '--params-file', str(params),
                         '--quiet'])
    err = capsys.readouterr().err
    assert code == 1 and 'a FIFO, not a regular file' in err, err


def test_a_params_file_that_is_huge_is_refused_before_it_is_read(tmp_path, capsys):
    params = tmp_path / 'params.yaml'
    with open(params, 'wb') as f:
        f.truncate(64 * 1024 * 1024)  # sparse: 64 MiB that cost no disk
    code = bounded_main([str(tmp_path / 'missing.mcap'), '--params-file', str(params),
                         '--quiet'])
    err = capsys.readouterr().err
    assert code == 1 and 'more than the limit' in err, err


@pytest.mark.parametrize('inside', [[], ['run_0.mcap']])
def test_a_folder_without_metadata_says_so_in_one_line(tmp_path, capsys, inside):
    bag = tmp_path / 'folder'
    bag.mkdir()
    for name in inside:
        (bag / name).write_bytes(b'\x89MCAP0\r\n')
    code = bounded_main([str(bag), '--out', str(tmp_path / 'out'), '--quiet'])
    err = capsys.readouterr().err
    assert code == 1 and 'without metadata.yaml' in err and 'Traceback' not in err, err
    assert all(name in err for name in inside)


@pytest.mark.parametrize('argument, value', [
    ('--heldout', '1e308'), ('--heldout', 'nan'), ('--heldout', 'inf'), ('--heldout', '-1'),
    ('--budget', 'nan'), ('--budget', '-1'), ('--budget', '-inf'),
    ('--max-generations', '-2')])
def test_numbers_out_of_range_are_refused_where_they_are_parsed(
        tmp_path, capsys, argument, value):
    code = bounded_main([str(tmp_path / 'bag.mcap'), argument, value])
    err = capsys.readouterr().err
    assert code == 2 and argument in err and 'Traceback' not in err, err


def test_an_out_path_that_is_a_file_is_refused_before_the_fit(tmp_path, capsys):
    out = tmp_path / 'out'
    out.write_text('not a folder')
    code = bounded_main([str(tmp_path / 'bag.mcap'), '--out', str(out), '--quiet'])
    err = capsys.readouterr().err
    assert code == 1 and 'is not a folder' in err, err


@pytest.mark.parametrize('magic', [b'', b'\x89MCAP0\r\n'])
def test_a_junk_file_is_refused_in_memory_independent_of_its_size(tmp_path, magic):
    junk = tmp_path / 'junk.mcap'
    size = 64 * 1024 * 1024
    with open(junk, 'wb') as f:
        f.write(magic + os.urandom(1024))
        f.truncate(size)  # the rest reads as zeros
    tracemalloc.start()
    try:
        with pytest.raises(RecordingError, match='junk.mcap'):
            open_recording(str(junk))
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < size / 8, f'{peak / 2 ** 20:.1f} MiB allocated to refuse a junk file'


def test_joints_that_never_move_are_refused_naming_them(tmp_path, capsys):
    run = simulated_run(20.0)

    def widen(values, still):  # 7 more joints that hold still
        return np.hstack([values, np.full((values.shape[0], 7), still)])
    data = types.SimpleNamespace(
        t=run.t, theta=widen(run.theta, 0.3), theta_dot=widen(run.theta_dot, 0.0),
        tau=widen(run.tau, 0.0), theta_d=widen(run.theta_d, 0.3),
        theta_d_dot=widen(run.theta_d_dot, 0.0))
    names = [f'joint{i + 1}' for i in range(10)]
    bag = tmp_path / 'still'
    write_run(bag, data, names=names)
    out = tmp_path / 'out'
    code = bounded_main([str(bag), '--out', str(out), '--max-generations', '3', '--quiet'])
    err = capsys.readouterr().err
    assert code == 1 and '7 of 10 joints never move' in err, err
    assert all(f"'joint{i}'" in err for i in range(4, 11)) and 'Traceback' not in err
    assert not (out / 'model.yaml').exists()  # no model saved
    # what the message advises: the moving joints alone are identified
    params = tmp_path / 'three.yaml'
    params.write_text('/**:\n  ros__parameters:\n    joints: [joint1, joint2, joint3]\n')
    code = bounded_main([str(bag), '--out', str(out), '--max-generations', '3', '--quiet',
                         '--params-file', str(params)], timeout=4 * PATIENCE)
    assert code == 0, capsys.readouterr().err
    assert (out / 'model.yaml').exists()

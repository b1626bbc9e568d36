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

"""The identified model's files: YAML round trip, atomic saves, refusals, stale temp files."""

import os

from model_helpers import make_model, NAMES, simulate_model
import numpy as np
import pytest
from rkgnn_ros.core.model import files
from rkgnn_ros.core.model.model import RKGNNModel
import yaml


@pytest.mark.parametrize('case', ['torque', 'pd_gains', 'unknown'])
def test_save_load_round_trip_gives_identical_predictions(tmp_path, case):
    model = make_model(case, info={'cost': np.float64(0.25), 'history': np.arange(3),
                                   'generation': np.int64(7)})
    path = tmp_path / 'model.yaml'
    model.save(path)
    loaded = RKGNNModel.load(path)
    np.testing.assert_array_equal(loaded.genome, model.genome)
    assert loaded.to_dict() == model.to_dict()
    assert loaded.joint_names == NAMES
    assert loaded.info == {'cost': 0.25, 'history': [0, 1, 2], 'generation': 7}
    t = np.arange(51) * 0.01
    np.testing.assert_array_equal(simulate_model(loaded, t), simulate_model(model, t))
    # and with the joints configured as in the file
    assert RKGNNModel.load(str(path), joint_names=list(NAMES)).joint_names == NAMES


def test_save_is_atomic(tmp_path, monkeypatch):
    path = tmp_path / 'models' / 'arm.yaml'  # the folder is created
    old = make_model(seed=1)
    old.save(path)
    assert sorted(os.listdir(path.parent)) == ['arm.yaml']
    new = make_model(seed=2)
    new.save(path)  # overwrite
    assert os.listdir(path.parent) == ['arm.yaml']
    np.testing.assert_array_equal(RKGNNModel.load(path).genome, new.genome)

    def failing_replace(src, dst):
        raise OSError('disk full')

    monkeypatch.setattr(files.os, 'replace', failing_replace)
    with pytest.raises(OSError, match='disk full'):
        old.save(path)
    # the previous file is intact and no temporary file is left behind
    assert os.listdir(path.parent) == ['arm.yaml']
    np.testing.assert_array_equal(RKGNNModel.load(path).genome, new.genome)


def test_saved_model_file_has_the_usual_permissions(tmp_path):
    """
    Check an atomic save leaves the file readable like any other file written there.

    Regression test (fixed in 3a690c8): ``save_text_atomic`` wrote through
    ``tempfile.mkstemp``, which creates the file with mode 0600, and ``os.replace`` kept that
    mode, so a model saved by the identifier was unreadable for other users (0644 with the
    usual umask 022).
    """
    plain = tmp_path / 'plain.yaml'
    plain.write_text('a: 1\n', encoding='utf-8')
    path = tmp_path / 'model.yaml'
    make_model().save(path)
    assert oct(path.stat().st_mode & 0o777) == oct(plain.stat().st_mode & 0o777)


def _edit(d, key, value):
    d = dict(d)
    if value is _DELETE:
        del d[key]
    else:
        d[key] = value
    return d


_DELETE = object()


@pytest.mark.parametrize('mutate, message', [
    (lambda d: _edit(d, 'format', 'other/model'), "format must be 'rkgnn_ros/model'"),
    (lambda d: _edit(d, 'format', _DELETE), "format must be 'rkgnn_ros/model'"),
    (lambda d: _edit(d, 'version', 2), 'version 2 is not supported'),
    (lambda d: _edit(d, 'version', '1'), "version '1' is not supported"),
    (lambda d: _edit(d, 'genome', _DELETE), "missing 'genome'"),
    (lambda d: _edit(d, 'scales', _DELETE), "missing 'scales'"),
    (lambda d: _edit(d, 'genome', d['genome'][:-1]), 'genome must have'),
    (lambda d: _edit(d, 'genome', d['genome'] + [0.0]), 'genome must have'),
    (lambda d: _edit(d, 'genome', [float('nan')] + d['genome'][1:]), 'genome contains NaN'),
    (lambda d: _edit(d, 'genome', [float('inf')] + d['genome'][1:]), 'genome contains NaN'),
    (lambda d: _edit(d, 'genome', ['x'] + d['genome'][1:]), 'model file'),
    (lambda d: _edit(d, 'case', 'torque'), 'contradicts'),
    (lambda d: _edit(d, 'kp', _DELETE), 'needs kp and kd'),
    (lambda d: _edit(d, 'kd', [1.0, float('nan'), 1.0]), 'kd contains NaN'),
    (lambda d: _edit(d, 'joint_names', ['a', 'b']), '2 joint names for a 3-joint model'),
    (lambda d: _edit(d, 'joint_names', ['a', 'a', 'b']), 'duplicate joint names'),
    (lambda d: _edit(d, 'network', {**d['network'], 'layers': 2}), 'unknown settings'),
    (lambda d: _edit(d, 'network', {**d['network'], 'n_joints': 2}),
     'scales are for 3 joints, the network has 2'),
    (lambda d: _edit(d, 'scales', {**d['scales'], 'torque': [1.0, -1.0, 1.0]}),
     'torque must be positive'),
    (lambda d: _edit(d, 'integration', {'dt': -0.01}), 'dt must be positive'),
    (lambda d: _edit(d, 'integration', {'substeps': 0}), 'substeps must be >= 1'),
    (lambda d: _edit(d, 'integration', {'torque_interpolation': 'cubic'}),
     'torque_interpolation'),
])
def test_load_refuses_a_bad_model_file(tmp_path, mutate, message):
    d = mutate(make_model().to_dict())
    path = tmp_path / 'bad.yaml'
    path.write_text(yaml.safe_dump(d), encoding='utf-8')
    with pytest.raises(ValueError, match=message) as info:
        RKGNNModel.load(path)
    assert str(info.value).startswith('model file: ')


@pytest.mark.parametrize('text, message', [
    ('format: [unclosed\n', 'not valid YAML'),
    ('genome: {a: 1\n  b: 2', 'not valid YAML'),
    ('', 'expected a mapping'),
    ('- 1\n- 2\n', 'expected a mapping'),
    ('just a string', 'expected a mapping'),
])
def test_load_refuses_text_that_is_not_a_model(tmp_path, text, message):
    path = tmp_path / 'bad.yaml'
    path.write_text(text, encoding='utf-8')
    with pytest.raises(ValueError, match=message):
        RKGNNModel.load(path)


def test_load_checks_the_configured_joints(tmp_path):
    path = tmp_path / 'model.yaml'
    make_model().save(path)
    with pytest.raises(ValueError, match='the model has 3 joints, 2 are configured'):
        RKGNNModel.load(path, joint_names=['shoulder', 'elbow'])
    with pytest.raises(ValueError, match='the model has 3 joints, 4 are configured'):
        RKGNNModel.load(path, joint_names=['a', 'b', 'c', 'd'])
    with pytest.raises(ValueError, match='do not match the configured'):
        RKGNNModel.load(path, joint_names=['shoulder', 'wrist', 'elbow'])


def test_stale_temp_files_of_a_killed_save_are_removed(tmp_path):
    path = tmp_path / 'model.yaml'
    make_model('torque').save(path)
    for name in ('.model.yaml.abc123.tmp', '.model.yaml.x.tmp'):
        (tmp_path / name).write_text('half a model')
    keep = [tmp_path / '.other.yaml.abc.tmp', tmp_path / 'model.yaml.tmp']
    for other in keep:
        other.write_text('not ours')
    assert files.remove_stale_temp_files(path) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        ['model.yaml'] + [p.name for p in keep])
    assert RKGNNModel.load(path).case == 'torque'

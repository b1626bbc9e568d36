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
The model loader under fuzz: mutated and adversarial YAML, no middleware.

Whatever a file holds, :func:`~rkgnn_ros.identification.model_file.read_model` returns a
model the node can run with or raises :class:`ModelFileError`, and nothing else. Its work
is bounded, counted rather than timed (a timed test fails on a loaded machine): at most
``MAX_MODEL_BYTES + 1`` bytes read, and YAML events at most linear in those bytes and
below ``MAX_NODES``, all scanned before anything is built. Its memory is measured with
tracemalloc against a bound (64 MB, where the largest file a parameter allows, 200,000
scalars, builds in about 100 MB; these files are below 100 kB).
"""

import copy
import math
import os
import tracemalloc

from hypothesis import event, given, HealthCheck, settings, strategies as st
import numpy as np
import pytest
from rkgnn_ros.core.fitting.identify import Evolution
from rkgnn_ros.core.fitting.online import model_update
from rkgnn_ros.core.model.network import NetworkSpec
from rkgnn_ros.core.sim.plant import PDController, PlanarArm
from rkgnn_ros.core.sim.simulate import simulate
from rkgnn_ros.core.sim.trajectories import paper_reference
from rkgnn_ros.identification.model_file import (LoadWork, MAX_DEPTH, MAX_MODEL_BYTES,
                                                 MAX_NODES, ModelFileError, read_model,
                                                 save_model_file, to_plain_yaml)
import yaml

JOINTS = ('j1', 'j2', 'j3')
MEMORY_BOUND_MB = 64.0

#: Pieces an adversary splices into a model file.
TOKENS = ['&a ', '*a', '&b [*a, *a, *a]', '!!python/object/apply:os.system ["true"] ', '!foo ',
          '!!binary aGk= ', '!!set {a}', '.nan', '.inf', '-.inf', '1e308', '-1e308', '1e999',
          '5e-324', '0x7fffffff', '9' * 60, '-1', '[', ']', '{', '}', ':', ': ', '- ', '\n',
          '  ', '"', "'", '#', '|', '>', '---\n', '...\n', '? ', '<<: {a: 1}', '2001-12-14',
          'null', 'true', '\t', '\\x00', '\u2028', '\ufeff', '%YAML 1.1\n', ',', '~', '=',
          '1:20:30', "'x' ", '[' * 40, ']' * 40, 'é', '\\', '@']


@pytest.fixture(scope='module')
def model():
    data = simulate(PlanarArm.paper(), PDController.paper(), paper_reference(3), 1.0,
                    rate=100.0, joint_names=JOINTS)
    model = Evolution(NetworkSpec.recommended(3, 'torque'), [data], seed=0).best_model(JOINTS)
    model.info.update(cost=0.5, validation_nrmse=math.nan,
                      controller_law={'kp': [1.0, 2.0, 3.0], 'fit_ratio': 0.01})
    return model


@pytest.fixture(scope='module')
def text(model):
    return to_plain_yaml(model)


def _leaves(d, path=()):
    """Yield the paths of every value in nested dicts and lists."""
    if isinstance(d, dict):
        for key, value in d.items():
            yield path + (key,)
            yield from _leaves(value, path + (key,))
    elif isinstance(d, list):
        for k, value in enumerate(d):
            yield path + (k,)
            yield from _leaves(value, path + (k,))


_VALUES = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True, allow_subnormal=True),
    st.sampled_from([0, -1, 1e308, -1e308, 5e-324, 2 ** 63, 10 ** 30, 10 ** 9, True, None, '',
                     'x' * 300, [], {}, [1.0] * 70, {'a': {'b': {'c': 1}}}, math.nan]),
    st.integers(), st.text(max_size=20), st.lists(st.floats(), max_size=5),
    st.dictionaries(st.text(max_size=5), st.integers(), max_size=3))


@st.composite
def mutated_text(draw, text):
    """Return the model's YAML with a few tokens inserted, replaced or deleted."""
    for _ in range(draw(st.integers(1, 4))):
        at = draw(st.integers(0, len(text)))
        span = draw(st.integers(0, 12))
        token = draw(st.sampled_from(TOKENS + ['']))
        text = text[:at] + token + text[at + span:]
    return text


@st.composite
def mutated_values(draw, model):
    """Return the model's data with a few values replaced by adversarial ones, as YAML."""
    d = model.to_dict()
    for _ in range(draw(st.integers(1, 3))):
        paths = list(_leaves(d))
        *parent, last = draw(st.sampled_from(paths))
        node = d
        for key in parent:
            node = node[key]
        node[last] = copy.deepcopy(draw(_VALUES))  # sampled constants are shared
    return yaml.safe_dump(d, sort_keys=False)


@st.composite
def adversarial(draw):
    """Return a document built to exhaust a parser: alias bombs, nesting, tags, ..."""
    kind = draw(st.sampled_from(['bomb', 'nesting', 'tags', 'documents', 'anchor_only',
                                 'long_scalar', 'keys']))
    if kind == 'bomb':
        width, depth = draw(st.integers(2, 12)), draw(st.integers(2, 12))
        lines = ['a0: &a0 [x]'] + [f'a{k}: &a{k} [' + ', '.join([f'*a{k - 1}'] * width) + ']'
                                   for k in range(1, depth)]
        return '\n'.join(lines)
    if kind == 'nesting':
        depth = draw(st.integers(MAX_DEPTH - 2, 200))
        return draw(st.sampled_from(['[', '{a: ', '- '])) * depth + '1'
    if kind == 'tags':
        tag = draw(st.sampled_from(['!!python/name:os.system', '!!python/object/new:list',
                                    '!custom', '!!float', '!!str', '!<tag:x,2000:y>']))
        return f'format: {tag} rkgnn_ros/model\n'
    if kind == 'documents':
        return '---\na: 1\n' * draw(st.integers(2, 50))
    if kind == 'anchor_only':
        return 'format: &f rkgnn_ros/model\n'
    if kind == 'long_scalar':
        return 'info: {note: "' + 'x' * draw(st.integers(1000, 50_000)) + '"}\n'
    return '{' + ', '.join(f'k{k}: {k}' for k in range(draw(st.integers(1, 5000)))) + '}'


def _load(tmp_path, text):
    """Load ``text`` from a file: ``(model or ModelFileError, LoadWork, peak MB)``."""
    path = tmp_path / 'fuzz.yaml'
    path.write_text(text, encoding='utf-8', errors='surrogatepass')
    work = LoadWork()
    tracemalloc.start()
    try:
        try:
            result = read_model(str(path), JOINTS, work)
        except ModelFileError as exc:  # the one documented error
            result = exc
        peak = tracemalloc.get_traced_memory()[1] / 1e6
    finally:
        tracemalloc.stop()
    return result, work, peak


def _bounded(result, work, peak, size):
    assert peak < MEMORY_BOUND_MB, peak
    assert work.bytes <= min(size, MAX_MODEL_BYTES + 1)
    assert work.events <= min(MAX_NODES + 8, 2 * work.bytes + 8), (work.events, work.bytes)
    if isinstance(result, ModelFileError):
        assert str(result)  # says why
        return
    # a model that loads is one the node can run with
    assert 1e-3 <= result.dt <= 0.1 and 1 <= result.substeps <= 64
    assert np.isfinite(result.genome).all() and np.abs(result.genome).max() <= 1e6
    update = model_update(result)  # what crashed the node on a NaN generation
    assert update.generation >= 0


@settings(max_examples=600, deadline=None, suppress_health_check=list(HealthCheck))
@given(data=st.data())
def test_fuzzed_model_files_load_or_raise_the_documented_error(model, text,
                                                               tmp_path_factory, data):
    kind = data.draw(st.sampled_from(['text', 'values', 'adversarial']))
    if kind == 'text':
        fuzzed = data.draw(mutated_text(text))
    elif kind == 'values':
        fuzzed = data.draw(mutated_values(model))
    else:
        fuzzed = data.draw(adversarial())
    tmp_path = tmp_path_factory.mktemp('fuzz', numbered=True)
    result, work, peak = _load(tmp_path, fuzzed)
    _bounded(result, work, peak, len(fuzzed.encode('utf-8', 'surrogatepass')))
    outcome = 'loaded' if not isinstance(result, ModelFileError) else ' '.join(
        str(result).split()[:3])
    event(f'{kind}: {outcome}')  # pytest --hypothesis-show-statistics shows the mix


def test_the_node_reads_back_what_it_writes(model, tmp_path):
    path = tmp_path / 'model.yaml'
    ok, message = save_model_file(str(path), model)
    assert ok, message
    loaded, work, peak = _load(tmp_path, path.read_text())
    assert not isinstance(loaded, ModelFileError), loaded
    np.testing.assert_array_equal(loaded.genome, model.genome)
    assert loaded.info['controller_law'] == model.info['controller_law']
    _bounded(loaded, work, peak, os.path.getsize(path))


def test_a_file_over_the_limits_is_refused_before_it_is_parsed(tmp_path):
    big = tmp_path / 'big.yaml'
    big.write_text('a: "' + 'x' * MAX_MODEL_BYTES + '"\n')
    work = LoadWork()
    with pytest.raises(ModelFileError, match='more than the limit'):
        read_model(str(big), work=work)
    assert work.bytes == 0 and work.events == 0
    many = tmp_path / 'many.yaml'
    many.write_text('[' + '1,' * MAX_NODES + '1]\n')
    with pytest.raises(ModelFileError, match=f'more than {MAX_NODES} YAML nodes'):
        read_model(str(many), work=work)
    assert work.events <= MAX_NODES + 8

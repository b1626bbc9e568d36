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

"""The online policy's one table, its shared rules, and the node's defaults declared once."""

import os

import pytest
from repo_paths import REPO_ROOT
from rkgnn_ros.core.fitting import policy
from rkgnn_ros.core.fitting.policy import retry_wait, still_holds, table
from rkgnn_ros.identification.parameters import PARAMETERS
import yaml

ROOT = REPO_ROOT

#: What config/identifier.yaml sets to other than the default, and why (its comment says so).
CONFIGURED = {'feedforward.max_effort': 'the paper arm of sim_arm.yaml'}


def test_every_row_is_the_module_name_with_its_value_unit_and_why():
    rows = table()
    names = [row.name for row in rows]
    assert len(names) == len(set(names))
    assert set(names) == {name for name in dir(policy) if name.isupper()}
    for row in rows:
        assert getattr(policy, row.name) == row.value, row.name
        assert row.unit.strip() and row.why.strip(), row.name
        assert isinstance(row.value, (int, float)), row.name


def test_the_two_integral_zeros_and_agreements_keep_their_values_under_their_own_names():
    assert (policy.LAW_KI_ZERO, policy.LOOP_KI_ZERO) == (1e-3, 0.01)
    assert (policy.LAW_AGREEMENT_RTOL, policy.GAIN_AGREEMENT_RTOL) == (0.1, 0.15)


@pytest.mark.parametrize('failures, young, wait', [(0, True, 1.0), (5, True, 1.0), (0, False, 1.0),
                                                   (1, False, 1.0), (2, False, 2.0),
                                                   (4, False, 8.0), (9, False, 30.0)])
def test_a_fit_that_does_not_hold_waits_longer_each_time_once_the_data_are_not_young(
        failures, young, wait):
    assert retry_wait(failures, young, 1.0, 30.0) == wait


def test_a_model_in_use_stays_while_it_meets_the_bar_a_new_fit_must():
    assert still_holds(0.1, 0.1) and not still_holds(0.1000001, 0.1)
    assert not still_holds(float('nan'), 0.1)


def _flat(tree, prefix=''):
    for key, value in tree.items():
        if isinstance(value, dict):
            yield from _flat(value, f'{prefix}{key}.')
        else:
            yield prefix + key, value


def test_the_identifier_yaml_holds_every_parameter_at_its_table_default():
    with open(os.path.join(ROOT, 'config', 'identifier.yaml'), encoding='utf-8') as f:
        values = dict(_flat(yaml.safe_load(f)['/**/identifier']['ros__parameters']))
    table = {spec.name: spec.default for spec in PARAMETERS}
    assert set(values) == set(table)
    for name, default in table.items():
        if name in CONFIGURED:
            assert values[name] != list(default), name
            continue
        value = values[name]
        if isinstance(default, (list, tuple)):
            assert list(value) == list(default), name
        else:
            assert value == default and type(value) is type(default), name


def test_the_parameters_that_set_the_policys_settings_default_to_its_own():
    from rkgnn_ros.core.fitting.online_records import OnlineSettings
    table, settings = {spec.name: spec.default for spec in PARAMETERS}, OnlineSettings()
    for name, field in (('min_window', 'min_window'), ('substeps', 'substeps'),
                        ('validation_fraction', 'validation_fraction'),
                        ('stale_timeout', 'stale_timeout'),
                        ('model_publish_period', 'model_publish_period'),
                        ('es.algorithm', 'optimizer'), ('es.seed', 'seed'),
                        ('es.max_generations', 'max_generations')):
        assert table[name] == getattr(settings, field), name

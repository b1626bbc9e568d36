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

"""sim_arm's parameter rules on plain dictionaries of values (no node)."""

import numpy as np
import pytest
from rkgnn_ros.core.sim.trajectories import hanging_pose, Switched
from rkgnn_ros.sim_node.parameters import build_config, ConfigurationError, PARAMETERS


def values(**overrides):
    """Return sim_arm's parameter values: the defaults with ``overrides`` (dots as __)."""
    out = {spec.name: spec.default for spec in PARAMETERS}
    out.update({name.replace('__', '.'): value for name, value in overrides.items()})
    return out


def test_no_switch_by_default():
    config, _ = build_config(values())
    assert not isinstance(config.reference, Switched)


def test_a_task_change_moves_the_pose_and_changes_the_frequencies():
    plain, _ = build_config(values())
    config, _ = build_config(values(reference__switch_at=60.0, reference__switch_shift=0.3))
    assert isinstance(config.reference, Switched)
    t_before = np.linspace(0.0, 59.9, 600)
    np.testing.assert_array_equal(config.reference.evaluate(t_before)[0],
                                  plain.reference.evaluate(t_before)[0])
    theta, _ = config.reference.evaluate(np.linspace(62.0, 162.0, 10001))
    # the new task swings about the moved pose, within reference.amplitude (0.5 rad)
    assert np.all(np.abs(theta - (hanging_pose(3) + 0.3)) <= 0.5 + 1e-9)
    assert np.all(np.abs(theta.mean(axis=0) - (hanging_pose(3) + 0.3)) < 0.2)
    second = config.reference.second
    assert np.all((second.frequencies_hz >= 0.1) & (second.frequencies_hz <= 0.8))
    assert not np.allclose(np.sort(second.frequencies_hz, axis=None),
                           np.sort(plain.reference.frequencies_hz, axis=None))


def test_a_switch_with_an_inverted_frequency_band_is_refused():
    with pytest.raises(ConfigurationError, match='min_frequency'):
        build_config(values(reference__switch_at=10.0, reference__min_frequency=0.9,
                            reference__max_frequency=0.5))

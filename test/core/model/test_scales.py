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

"""The physical scales of the data: validation, measurement, YAML round trip."""

from model_helpers import unit_scales
import numpy as np
import pytest
from rkgnn_ros.core.data import Dataset
from rkgnn_ros.core.model.scales import Scales


def test_scales_validation_and_dict_round_trip():
    scales = unit_scales(2, torque=[2.0, 3.0])
    assert Scales.from_dict(scales.to_dict()).torque.tolist() == [2.0, 3.0]
    np.testing.assert_allclose(scales.inertia, [2.0, 3.0])
    with pytest.raises(ValueError, match='theta_spread must be positive'):
        unit_scales(2, theta_spread=[0.1, -0.1])
    with pytest.raises(ValueError, match='must be 2 finite values'):
        unit_scales(2, velocity=[1.0, np.nan])
    d = scales.to_dict()
    del d['error']
    with pytest.raises(ValueError, match='missing'):
        Scales.from_dict(d)


def test_scales_from_datasets():
    t = np.arange(200) * 0.01
    theta = np.column_stack([0.3 * np.sin(t), 0.1 * np.cos(2 * t)])
    theta_dot = np.column_stack([0.3 * np.cos(t), -0.2 * np.sin(2 * t)])
    data = Dataset(t, theta, theta_dot, tau=np.column_stack([2.0 * np.ones_like(t), -t]),
                   theta_d=theta + 0.1, theta_d_dot=theta_dot)
    s1 = Scales.from_datasets([data], 'torque')
    np.testing.assert_allclose(s1.theta_center, theta.mean(axis=0))
    np.testing.assert_allclose(s1.torque, np.sqrt(np.mean(data.tau ** 2, axis=0)))
    s2 = Scales.from_datasets([data], 'pd_gains', kp=[10.0, 20.0], kd=[1.0, 1.0])
    np.testing.assert_allclose(s2.torque, [1.0, 2.0])  # kp * 0.1, derr = 0
    np.testing.assert_allclose(s2.error, [0.1, 0.1])
    s3 = Scales.from_datasets([data], 'unknown')
    np.testing.assert_array_equal(s3.torque, [1.0, 1.0])  # the gauge of case 3

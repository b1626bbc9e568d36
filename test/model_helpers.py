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

"""Helpers shared by the tests of the model: unit scales and genome blocks by name."""

import numpy as np
from rkgnn_ros.core.model.scales import Scales


def unit_scales(n, **overrides):
    """Scales of 1 everywhere (θ centred on 0): genome values are then physical values."""
    values = {name: np.ones(n) for name in ('theta_spread', 'velocity', 'acceleration',
                                            'torque', 'error', 'error_rate')}
    values['theta_center'] = np.zeros(n)
    values.update({k: np.asarray(v, dtype=float) for k, v in overrides.items()})
    return Scales(**values)


def set_block(spec, genome, name, values):
    """Write ``values`` (reshaped to the block's shape) into ``genome`` in place."""
    block = next(b for b in spec.blocks() if b.name == name)
    genome[block.start:block.stop] = np.asarray(values, dtype=float).reshape(block.shape).ravel()

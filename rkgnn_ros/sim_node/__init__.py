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
The parts of the ``sim_arm`` node; :mod:`rkgnn_ros.sim_arm` wires them.

- :mod:`.parameters`: the parameter table and the simulated system it defines.
- :mod:`.arm_model`: which arm is simulated, the paper's planar one or a URDF arm.

The simulation itself is the core's (:mod:`rkgnn_ros.core.sim`): only this folder and
the node import it in the product.
"""

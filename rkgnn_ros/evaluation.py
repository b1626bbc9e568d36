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
Scoring predictions against the motion that followed (used by the demo and the benchmarks).

The scoring lives in the ROS-free core, beside the identifier's online self-check that uses
it (:mod:`rkgnn_ros.core.selfcheck`); this module keeps the names the tools import.
"""

from .core.selfcheck import ahead_errors, range_normalised_rmse

__all__ = ['ahead_errors', 'range_normalised_rmse']

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
What every node is built from: the parameter table's form, SIGINT, teardown.

- :mod:`.parameters`: one row per node parameter (its type, default, range and what a
  change does), declared and described from the table.
- :mod:`.sigint`: SIGINT that ends a node's spin cleanly.
- :mod:`.stacks`: where a node's threads wait, and an end to a teardown that hangs.
"""

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
The ROS wire formats: messages to numpy arrays and back, and the CDR bytes themselves.

- :mod:`.conversions`: the one boundary between incoming messages and arrays, with the
  rules that reject a message (size budgets, names, NaN).
- :mod:`.messages`: outgoing messages built from arrays; stamps and durations.
- :mod:`.cdr`: the CDR form of the messages the 1 kHz paths read and write directly.
- :mod:`.controller_state`: a joint_trajectory_controller's state as a command stream.
"""

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
Online RKGNN identification of robot arm dynamics for ROS 2.

The modules here are the entry points (``setup.py``'s console scripts); each has a folder
of parts, and the folders below them hold what more than one node uses:

- :mod:`.identifier` and :mod:`.identification`: the identifier node and its parts.
- :mod:`.sim_arm` and :mod:`.sim_node`: the simulated arm node and its parts.
- :mod:`.identify_bag` and :mod:`.offline`: identification of a recording, and its parts.
- :mod:`.node`: what every node is built from (parameter tables, SIGINT, teardown).
- :mod:`.wire`: the ROS wire formats (messages to arrays and back, CDR).
- :mod:`.streams`: the buffered joint streams between the messages and the fits.
- :mod:`.recordings`: rosbag2 recordings read and replayed.
- :mod:`.core`: the numerical core, no ROS; everything above may import it, it imports
  nothing above it.
"""

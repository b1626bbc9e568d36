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
The parts of the ``identifier`` node, one job each; :mod:`rkgnn_ros.identifier` wires them.

- :mod:`.parameters`: the parameter table, its checks and the consistent snapshots.
- :mod:`.ingest`: joint streams in (the raw-CDR ingest thread).
- :mod:`.drops`: the node's drop accounting: a counter per reason, throttled warnings.
- :mod:`.worker`: the thread that runs the online policy
  (:mod:`rkgnn_ros.core.fitting.online`) and queues its events.
- :mod:`.prediction`: the prediction thread (:mod:`.candidates`: which model predicts;
  :mod:`.horizon`: what a prediction covers; :mod:`.replay`: a candidate after a change
  predicts again from the starts since it).
- :mod:`.publishing`: the outbox and everything the executor thread publishes.
- :mod:`.model_file`: loading and saving ``model_file``.
"""

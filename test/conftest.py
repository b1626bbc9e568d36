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
The suite's marks: the tests of the slow files are marked ``slow``.

``make test`` runs every test; ``make test-fast`` (``pytest -m 'not slow'``) leaves out the
files of :data:`SLOW_FILES`: each takes more than 15 s in all on the 2-core machine the
suite is timed on (the nodes run end to end, the searches, the linters). The golden outputs
stay in the fast run.
"""

import os

import pytest

#: Test files whose tests are marked ``slow``.
SLOW_FILES = frozenset({
    'test_basis.py', 'test_case_three.py', 'test_chain.py', 'test_controller.py',
    'test_e2e.py', 'test_e2e_urdf.py', 'test_fit_budget.py', 'test_fit_segments.py',
    'test_fitness.py', 'test_flake8.py', 'test_global_fit.py', 'test_hostile_identify_bag.py',
    'test_hostile_parameters.py', 'test_identifier.py', 'test_identifier_feedforward.py',
    'test_identify.py', 'test_identify_bag.py', 'test_namespaces.py', 'test_online.py',
    'test_reliability.py', 'test_sim_time.py',
})


def pytest_collection_modifyitems(config, items):
    """Mark the tests of :data:`SLOW_FILES` ``slow``."""
    for item in items:
        if os.path.basename(str(item.fspath)) in SLOW_FILES:
            item.add_marker(pytest.mark.slow)

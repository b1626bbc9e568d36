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
sim_arm against what the third adversarial probe (issue 31) found.

- ``robot_description`` naming a FIFO (it used to wait for a writer forever) or a 1 GB
  file (read whole, 2.3 GB, before it was refused): refused from ``stat``, at once.
- URDFs with NaN or inf mass or NaN inertia (urdfdom dropped the body with a line on
  stderr and the arm diverged, or was simulated without it): refused naming the link.
"""

import math
import os
from pathlib import Path
import subprocess
import sys
import threading
import tracemalloc

import pytest

pytest.importorskip('pinocchio')

from rkgnn_ros.core.sim.urdf_arm import MAX_URDF_BYTES, UrdfArm, UrdfError  # noqa: E402
from rkgnn_ros.sim_arm_parameters import build_config, ConfigurationError  # noqa: E402
from rkgnn_ros.sim_arm_parameters import PARAMETERS  # noqa: E402
from urdf_helpers import planar_urdf  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
PATIENCE = 60.0


def values(**overrides):
    """Return sim_arm's parameter values: the defaults with ``overrides`` (dots as __)."""
    out = {spec.name: spec.default for spec in PARAMETERS}
    out.update({name.replace('__', '.'): value for name, value in overrides.items()})
    return out


def bounded(function, *args, timeout=PATIENCE):
    """Call ``function(*args)`` in a thread; return ('raised', exc), ('value', v) or None."""
    outcome = []

    def run():
        try:
            outcome.append(('value', function(*args)))
        except Exception as exc:  # noqa: B902 - handed to the test
            outcome.append(('raised', exc))
    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(timeout)
    return outcome[0] if outcome else None


def test_a_fifo_robot_description_is_refused_without_waiting(tmp_path):
    fifo = tmp_path / 'arm.urdf'
    os.mkfifo(fifo)
    outcome = bounded(build_config, values(robot_description=str(fifo)))
    assert outcome is not None, 'build_config waited on the FIFO'
    kind, error = outcome
    assert kind == 'raised' and isinstance(error, ConfigurationError)
    assert 'a FIFO, not a regular file' in str(error) and str(fifo) in str(error)


def test_a_huge_robot_description_is_refused_before_it_is_read(tmp_path):
    huge = tmp_path / 'arm.urdf'
    with open(huge, 'wb') as f:
        f.truncate(1024 ** 3)  # 1 GB, sparse: no disk
    tracemalloc.start()
    try:
        with pytest.raises(ConfigurationError, match='more than the limit'):
            build_config(values(robot_description=str(huge)))
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < MAX_URDF_BYTES, f'{peak / 2 ** 20:.1f} MiB allocated to refuse it'
    with pytest.raises(UrdfError, match='more than the limit'):
        UrdfArm('<robot>' + ' ' * MAX_URDF_BYTES + '</robot>')


@pytest.mark.parametrize('mass', ['nan', 'inf', '-inf', '-2.0'])
def test_a_urdf_mass_that_no_body_has_is_refused_naming_the_link(mass, capfd):
    with pytest.raises(ConfigurationError) as raised:
        build_config(values(robot_description=planar_urdf([2.0, mass, 0.5], [0.3, 0.2, 0.1])))
    assert "link 'link2'" in str(raised.value) and '<mass value>' in str(raised.value)
    assert 'Error' not in capfd.readouterr().err  # refused before urdfdom prints


@pytest.mark.parametrize('key', ['ixx', 'iyz', 'izz'])
@pytest.mark.parametrize('value', ['nan', 'inf'])
def test_a_urdf_inertia_that_is_not_finite_is_refused_naming_the_link(key, value):
    xml = planar_urdf([2.0, 1.0, 0.5], [0.3, 0.2, 0.1])
    xml = xml.replace(f'{key}="0"', f'{key}="{value}"', 1)
    with pytest.raises(UrdfError) as raised:
        UrdfArm(xml)
    assert "link 'link1'" in str(raised.value) and f'<inertia {key}>' in str(raised.value)


def test_a_urdf_with_finite_inertials_is_still_taken():
    arm = UrdfArm(planar_urdf([2.0, 1.0, 0.5], [0.3, 0.2, 0.1]))
    assert arm.n_joints == 3 and math.isfinite(float(arm.mass_matrix(arm.home).sum()))


def test_the_node_refuses_a_fifo_robot_description_at_start(tmp_path):
    fifo = tmp_path / 'arm.urdf'
    os.mkfifo(fifo)
    env = dict(os.environ, PYTHONPATH=str(REPO))
    process = subprocess.run(
        [sys.executable, '-m', 'rkgnn_ros.sim_arm', '--ros-args', '-p',
         f'robot_description:={fifo}'], env=env, cwd=str(REPO), capture_output=True,
        text=True, timeout=2 * PATIENCE)
    output = process.stdout + process.stderr
    assert process.returncode == 1, output
    assert 'a FIFO, not a regular file' in output and 'Traceback' not in output, output

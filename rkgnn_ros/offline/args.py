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
The command line of ``identify_bag``: every value checked where it is parsed.

A number of seconds must be finite and within its range (``--budget nan``, ``--heldout
1e308`` or ``inf`` are refused with argparse's one-line usage error, exit code 2), a
generation count an integer >= 0.
"""

import argparse
import math

__all__ = ['MAX_SECONDS', 'parser']

#: Longest --budget and --heldout (s): a day.
MAX_SECONDS = 86400.0


def _seconds(low: float, low_open: bool):
    """Return an argparse type: a finite number of seconds above ``low``, at most a day."""
    def seconds(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f'{text!r} is not a number') from None
        if not (math.isfinite(value) and (value > low if low_open else value >= low)
                and value <= MAX_SECONDS):
            raise argparse.ArgumentTypeError(
                f'{text} s: must be a finite number of seconds in {"(" if low_open else "["}'
                f'{low:g}, {MAX_SECONDS:g}]')
        return value
    return seconds


def _count(text: str) -> int:
    """Return a generation count: an integer >= 0."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'{text!r} is not an integer') from None
    if value < 0:
        raise argparse.ArgumentTypeError(f'{value}: must be >= 0')
    return value


def parser(node_name: str = 'identifier') -> argparse.ArgumentParser:
    """Return the command line parser."""
    p = argparse.ArgumentParser(
        prog='identify_bag', description='Identify an arm from a rosbag2 recording (MCAP or '
        "sqlite3) with the identifier node's pipeline and parameters.")
    p.add_argument('bag', help='the recording: a rosbag2 folder, an .mcap or a .db3 file')
    p.add_argument('--params-file', default='',
                   help="the identifier's parameters file (default: its defaults)")
    p.add_argument('--node-name', default=node_name,
                   help='the node whose entry of the parameters file applies')
    p.add_argument('--out', default='', help='output folder (default: <bag>_identified)')
    p.add_argument('--heldout', type=_seconds(0.0, False), default=10.0,
                   help='seconds at the end kept out of the fit and predicted (0: none)')
    p.add_argument('--budget', type=_seconds(0.0, False), default=90.0,
                   help='wall-time budget of the whole run (s); exit code 3: the model is '
                   'written but predicts the held-out part worse than a baseline')
    p.add_argument('--max-generations', type=_count, default=0,
                   help='stop after this many generations (0: the budget decides)')
    p.add_argument('--namespace', default='', help='take the topics under this namespace')
    p.add_argument('--joint-states', default='', help='joint states topic')
    p.add_argument('--joint-commands', default='', help='joint commands topic')
    p.add_argument('--controller-state', default='',
                   help="a joint_trajectory_controller's controller_state topic")
    p.add_argument('--model-topic', default='',
                   help="the online identifier's ~/model topic (compared on the held-out part)")
    p.add_argument('--robot-description', default='',
                   help="the arm's URDF (a path, example-robot-data:<path> or the XML): its "
                   'rigid body is fitted in closed form (default: robot_description of the '
                   'parameters file, else none)')
    p.add_argument('--learn-chain', action='store_true',
                   help="case torque (or pd_gains), 3 to 7 joints: learn the arm's chain "
                   'from the training part first (minutes, outside --budget); without a robot '
                   'description its rigid body is fitted when it predicts held-out torque, '
                   "with one the description is checked against it (the report's "
                   'description_check) and still fitted')
    p.add_argument('--quiet', action='store_true', help='no progress lines')
    return p

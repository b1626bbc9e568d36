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

"""The PlotJuggler layout overlays measurement and prediction by header stamp."""

import os
import xml.etree.ElementTree as ElementTree

from repo_paths import REPO_ROOT

LAYOUT = os.path.join(REPO_ROOT, 'config', 'plotjuggler_prediction.xml')


def test_layout_plots_each_joint_measured_and_predicted_on_header_stamps():
    root = ElementTree.parse(LAYOUT).getroot()
    curves = [c.get('name') for c in root.iter('curve')]
    for joint in ('joint1', 'joint2', 'joint3'):
        assert f'/joint_states/{joint}/position' in curves
        assert f'/identifier/predicted_state/{joint}/position' in curves
    plugin = next(p for p in root.iter('plugin') if p.get('ID') == 'ROS2 Topic Subscriber')
    assert plugin.find('use_header_stamp').get('value') == 'true'
    topics = plugin.find('selected_topics').get('value').split(';')
    assert {'/joint_states', '/identifier/predicted_state'} <= set(topics)

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

"""A change of the dynamics without a robot description: the planar arm's residual judged."""

from types import SimpleNamespace

import numpy as np
import pytest
from rkgnn_ros.core.fitting.online_records import DynamicsChange
from rkgnn_ros.core.fitting.trig_change import TrigChangeMonitor
from rkgnn_ros.core.sim.payload import with_payload
from rkgnn_ros.core.sim.plant import PDController, PlanarArm
from rkgnn_ros.core.sim.sensors import SensorModel
from rkgnn_ros.core.sim.simulate import simulate
from rkgnn_ros.core.sim.trajectories import paper_reference
from rkgnn_ros.streams.buffer import StreamBuffer

JOINTS = ('j1', 'j2', 'j3')
AT, T0 = 12.0, 1000.0


@pytest.fixture(scope='module')
def released():
    """Return the paper's arm carrying 2 kg at its tip for 12 s, then 6 s without it."""
    arm, pd, ref = PlanarArm.paper(), PDController.paper(), paper_reference(3)
    loaded = with_payload(arm, 2.0)
    before = simulate(loaded, pd, ref, AT, rate=100.0, joint_names=JOINTS)
    x0 = np.concatenate([before.theta[-1], before.theta_dot[-1]])
    after = simulate(arm, pd, ref, 6.0, rate=100.0, x0=x0, t0=AT, joint_names=JOINTS)
    return loaded, before, after


def changes_said(before, after, loop_at, every=0.25, monitor=None):
    """
    Feed ``before`` then ``after`` at ``every`` s steps; return (step time, change) said.

    ``loop_at(now, step)`` gives the keeper's loop at each step (None: dropped).
    """
    buffer = StreamBuffer(JOINTS, 0.01, 20.0, 0.1, need_tau=True, need_desired=True)
    monitor = monitor or TrigChangeMonitor()
    said = []
    samples = [(d, k) for d in (before, after) for k in range(d.n_samples - (d is before))]
    fed = 0
    for step in range(int(17.9 / every)):
        now = step * every
        while fed < len(samples) and samples[fed][0].t[samples[fed][1]] <= now:
            d, k = samples[fed]
            buffer.add_state(T0 + d.t[k], d.theta[k], d.theta_dot[k], d.tau[k])
            buffer.add_command(T0 + d.t[k], d.theta_d[k], d.theta_d_dot[k])
            fed += 1
        events = monitor.observe(buffer.capture(), loop_at(now, step), 0.2, 100.0 + now,
                                 JOINTS)
        said += [(now, e) for e in events if isinstance(e, DynamicsChange)]
    return said


def test_a_change_is_said_with_the_arm_it_was_armed_on_after_the_loop_is_dropped(released):
    loaded, before, after = released
    loop = SimpleNamespace(arm=loaded)       # the trigonometric arm the keeper predicted with
    # the keeper drops its loop as soon as it stops explaining the newest data
    said = changes_said(before, after, lambda now, step: loop if now < AT else None)
    assert len(said) == 1, said                     # none before the release, one after
    now, change = said[0]
    # the change time within the centred derivative's half window before it, or after
    assert AT - 0.15 <= change.time - T0 <= AT + 0.5 and now - AT <= 1.0


@pytest.fixture(scope='module')
def picked_up():
    """Return the paper's arm without a payload for 12 s, then 6 s carrying 2 kg at its tip."""
    arm, pd, ref = PlanarArm.paper(), PDController.paper(), paper_reference(3)
    loaded = with_payload(arm, 2.0)
    before = simulate(arm, pd, ref, AT, rate=100.0, joint_names=JOINTS)
    x0 = np.concatenate([before.theta[-1], before.theta_dot[-1]])
    after = simulate(loaded, pd, ref, 6.0, rate=100.0, x0=x0, t0=AT, joint_names=JOINTS)
    return arm, loaded, before, after


def test_a_loop_refitted_on_the_changed_data_does_not_hide_the_change(picked_up):
    arm, loaded, before, after = picked_up
    first, refits = SimpleNamespace(arm=arm), {}

    def loop_at(now, step):
        if now > AT:                 # the keeper's refit each second, on the new data
            refits.setdefault((step - 1) // 4, SimpleNamespace(arm=loaded))
            return refits[(step - 1) // 4]
        return first

    said = changes_said(before, after, loop_at)
    assert len(said) == 1, said
    now, change = said[0]
    assert AT - 0.15 <= change.time - T0 <= AT + 0.5 and now - AT <= 1.0


def test_a_check_that_comes_late_finds_the_change_where_it_began(released):
    # the worker checks only between the search's generations: here every 1.5 s, the last
    # check before the release at 12.0 s and the next at 13.5 s; what came between is judged
    # (a check of the newest second alone put the onset at 12.5 s)
    loaded, before, after = released
    loop = SimpleNamespace(arm=loaded)
    said = changes_said(before, after, lambda now, step: loop, every=1.5)
    assert len(said) == 1, said
    now, change = said[0]
    assert now == pytest.approx(13.5) and AT - 0.15 <= change.time - T0 <= AT + 0.1


def test_the_data_after_a_change_hold_no_sample_of_the_arm_before_it():
    # noisy encoders: the onset is found on rows whose θ̈ is a centred derivative, which rise
    # before the change; a refit that takes in one sample of the arm before is far off
    arm, pd, ref = PlanarArm.paper(), PDController.paper(), paper_reference(3)
    noisy = SensorModel.differenced(1e-4)
    before = simulate(arm, pd, ref, AT, rate=100.0, joint_names=JOINTS, noise=noisy, rng=5)
    x0 = np.concatenate([before.theta[-1], before.theta_dot[-1]])
    after = simulate(with_payload(arm, 2.0), pd, ref, 6.0, rate=100.0, x0=x0, t0=AT,
                     joint_names=JOINTS, noise=noisy, rng=6)
    monitor, first = TrigChangeMonitor(), SimpleNamespace(arm=arm)
    said = changes_said(before, after, lambda now, step: first if now < AT else None,
                        monitor=monitor)
    assert len(said) == 1, said
    assert said[0][1].time - T0 < AT - 0.05          # found early, as such rows make it
    assert monitor.since - T0 >= AT

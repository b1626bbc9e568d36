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
The online policy fed a stream with random drops and bursts: no step fails.

A driver that drops joint_states or publishes them in bursts leaves the buffer with many
short segments; every refresh of the data then hands the policy's fits (the servo law, the
gains, the closed loop on the trigonometric basis, the warm starts) segments cut anywhere.
The clock is a fake one moved 0.1 s per step, and the stream is fed up to it.
"""

import numpy as np
import pytest
from rkgnn_ros.core.fitting.online import Observation, OnlineIdentification, OnlineSettings, Status
from rkgnn_ros.core.sim.plant import PDController, PlanarArm
from rkgnn_ros.core.sim.simulate import simulate
from rkgnn_ros.core.sim.trajectories import paper_reference
from rkgnn_ros.streams.buffer import StreamBuffer

JOINTS = ('j1', 'j2', 'j3')
T0 = 1000.0
SECONDS = 8.0
KP, KD = (32.84, 42.05, 42.31), (42.44, 0.19, 4.86)


@pytest.fixture(scope='module')
def arm():
    """8 s of the paper's arm under its PD, sampled at 1 kHz (the bursts' rate)."""
    return simulate(PlanarArm.paper(), PDController.paper(), paper_reference(3), SECONDS,
                    rate=1000.0, joint_names=JOINTS)


def delivered(n_samples: int, seed: int) -> np.ndarray:
    """
    Return the indices of the 1 kHz samples a bursty, lossy driver publishes.

    Mostly every 10th (100 Hz); with probability 0.05 a drop of 20-600 ms, with 0.05 a
    burst of 5-60 consecutive samples (1 kHz).
    """
    rng = np.random.default_rng(seed)
    keep = np.zeros(n_samples, bool)
    k = 0
    while k < n_samples:
        draw = rng.random()
        if draw < 0.05:
            k += int(rng.uniform(20, 600))
        elif draw < 0.10:
            m = int(rng.integers(5, 60))
            keep[k:k + m] = True
            k += m
        else:
            keep[k] = True
            k += 10
    return np.flatnonzero(keep)


@pytest.mark.parametrize('case', ['torque', 'unknown'])
def test_a_stream_with_random_drops_and_bursts_never_fails_a_step(arm, case):
    # seed 9: its stream made both the servo law's and the gains' newest-half cuts fall
    # half a step from a gap (a one-sample segment) and into 2-4 sample pieces
    settings = OnlineSettings(case=case, min_window=2.0, validation_fraction=0.25,
                              stale_timeout=5.0, model_publish_period=0.5,
                              optimizer_settings={'population_size': 8}, seed=3)
    buffer = StreamBuffer(JOINTS, 0.01, 20.0, 0.1, need_tau=case == 'torque',
                          need_desired=case != 'torque')
    statuses = []
    now = [0.0]
    policy = OnlineIdentification(lambda: now[0], on_status=statuses.append,
                                  warm_start_seconds=1.0, warm_start_nfev=5)
    index = delivered(arm.n_samples, seed=9)
    fed, generations, most_segments, errors = 0, 0, 0, []
    while fed < index.size:
        now[0] += 0.1
        while fed < index.size and arm.t[index[fed]] <= now[0]:
            k = index[fed]
            buffer.add_state(T0 + arm.t[k], arm.theta[k], arm.theta_dot[k], arm.tau[k])
            buffer.add_command(T0 + arm.t[k], arm.theta_d[k], arm.theta_d_dot[k])
            fed += 1
        obs = Observation(settings, JOINTS, {'state': now[0], 'command': now[0]})
        if policy.data_due(obs):
            capture = buffer.capture()
            most_segments = max(most_segments, len(capture.segments(2, True)))
            obs = obs._replace(data=capture)
        try:
            generations += policy.step(obs).ran
        except Exception as error:  # noqa: B902 - what the node's worker would report
            errors.append(f'{now[0]:.1f} s: {type(error).__name__}: {error}')
    assert not errors, errors
    assert not [s for s in statuses if isinstance(s, Status) and s.state == 'error']
    assert most_segments >= 5     # the stream is as gappy as it says
    assert generations > 0        # and the search ran on it

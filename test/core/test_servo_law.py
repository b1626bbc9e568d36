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

"""The servo laws: their compiled twins agree to the bit, and a velocity feed-forward pays."""

from numba import njit
import numpy as np
import pytest
from rkgnn_ros.core.integration.rkg import rkg_step
from rkgnn_ros.core.servo_law import (compiled_pd_torque,
                                      compiled_pd_velocity_feedforward_torque, pd_torque,
                                      pd_torque_coupled, pd_velocity_feedforward_torque)

RNG = np.random.default_rng(11)
KP, KD, KV = RNG.uniform(5.0, 50.0, 4), RNG.uniform(0.1, 5.0, 4), RNG.uniform(0.0, 3.0, 4)
E, E_DOT, V_D = RNG.normal(size=(3, 100, 4))


@njit(cache=True)
def _compiled(kp, kd, kv, e, e_dot, v_d):
    out = np.empty((2,) + e.shape)
    for k in range(e.shape[0]):
        for i in range(e.shape[1]):
            out[0, k, i] = compiled_pd_torque(kp[i], kd[i], e[k, i], e_dot[k, i])
            out[1, k, i] = compiled_pd_velocity_feedforward_torque(
                kp[i], kd[i], kv[i], e[k, i], e_dot[k, i], v_d[k, i])
    return out


def test_the_compiled_twins_give_the_functions_bit_for_bit():
    compiled = _compiled(KP, KD, KV, E, E_DOT, V_D)
    assert compiled[0].tobytes() == pd_torque(KP, KD, E, E_DOT).tobytes()
    assert compiled[1].tobytes() == pd_velocity_feedforward_torque(
        KP, KD, KV, E, E_DOT, V_D).tobytes()


def test_without_feed_forward_the_law_is_the_pd_and_diagonal_gains_couple_nothing():
    assert pd_velocity_feedforward_torque(KP, KD, 0.0, E, E_DOT, V_D).tobytes() == \
        pd_torque(KP, KD, E, E_DOT).tobytes()
    assert pd_torque_coupled(np.diag(KP), np.diag(KD), E, E_DOT).tobytes() == \
        pd_torque(KP, KD, E, E_DOT).tobytes()
    np.testing.assert_allclose(pd_velocity_feedforward_torque(KP, KD, KV, E, E_DOT, V_D),
                               KP * E + KD * E_DOT + KV * V_D, rtol=1e-15, atol=1e-13)


def _ramp_lag(kv, kp=40.0, kd=8.0, viscous=2.0, inertia=0.5, speed=0.8, seconds=20.0,
              h=0.002):
    """Return θd − θ at the end of a ramp θd = speed·t tracked by one damped joint (rad)."""
    def rate(state, t):
        e, e_dot = speed * t - state[0], speed - state[1]
        tau = pd_velocity_feedforward_torque(kp, kd, kv, e, e_dot, speed)
        return np.array([state[1], (tau - viscous * state[1]) / inertia])

    x = np.zeros(2)
    for k in range(int(round(seconds / h))):
        t = k * h
        x = rkg_step(rate, x, h, t, t + 0.5 * h, t + h)
    return speed * seconds - x[0]


def test_a_velocity_feed_forward_that_pays_the_friction_removes_the_ramp_lag():
    lag_pd = _ramp_lag(kv=0.0)
    assert lag_pd == pytest.approx(2.0 * 0.8 / 40.0, rel=1e-6)  # b θ̇d / Kp
    assert abs(_ramp_lag(kv=2.0)) < 1e-9

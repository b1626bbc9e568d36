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
Servo laws, each written once: the torque a joint servo applies for its tracking error.

The paper's servo is a PD on the joint error, eq. (9)::

    τ = Kp e + Kd ė,    e = θd − θ,    ė = θ̇d − θ̇        (N m; Kp in N m/rad, Kd in N m s/rad)

:func:`pd_torque` is that law, and everything that evaluates a servo calls it: the
simulated servos (:mod:`.sim.servo`, :mod:`.sim.plant`), the tuning costs, the network's
controller in cases 2 and 3 (:mod:`.model`), the fitted laws and closed loops of
:mod:`.fitting` (trigonometric and rigid-body), and the held-out torque check. What a site
adds (an integral term, gravity compensation, a bias, a feed-forward) it adds to this
torque, in its own order.

As :func:`~.integration.rkg.gill_update` for the Runge–Kutta–Gill step, a law is a plain
function of its gains and errors that works element by element on floats and on numpy
arrays of any shape (gains broadcast against errors), and its compiled twin
(``compiled_...``, inlined into numba kernels, which then compute exactly what the function
computes) serves the kernels. Gains given as (n, n) matrices (a coupled servo; the
stability analysis takes them so) go through :func:`pd_torque_coupled`: row i of the
torque is Σ_j of the law on Kp_ij, e_j, which for diagonal gains is the law per joint to
the last bit.

A new law is a function here and its twin, built on the ones before it, as
:func:`pd_velocity_feedforward_torque` is: a PD with a velocity feed-forward.
"""

from numba import njit
import numpy as np

__all__ = ['compiled_pd_torque', 'compiled_pd_velocity_feedforward_torque', 'pd_torque',
           'pd_torque_coupled', 'pd_velocity_feedforward_torque']


def pd_torque(kp, kd, error, error_rate):
    """
    Return the PD servo's torque Kp e + Kd ė (N m).

    Parameters
    ----------
    kp, kd : float or ndarray
        Proportional (N m/rad) and derivative (N m s/rad) gains, broadcast against the
        errors (per joint: shape (n,)).
    error, error_rate : float or ndarray
        e = θd − θ (rad) and ė = θ̇d − θ̇ (rad/s).

    """
    return kp * error + kd * error_rate


compiled_pd_torque = njit(cache=True, nogil=True, inline='always')(pd_torque)


def pd_torque_coupled(kp, kd, error, error_rate):
    """
    Return the PD torque with (n, n) gain matrices: Σ_j (Kp_ij e_j + Kd_ij ė_j), (..., n).

    ``error``, ``error_rate`` have shape (..., n). Off the diagonal the products are exact
    zeros, so diagonal gains give :func:`pd_torque` per joint exactly.
    """
    error = np.asarray(error, dtype=float)[..., None, :]
    error_rate = np.asarray(error_rate, dtype=float)[..., None, :]
    return pd_torque(kp, kd, error, error_rate).sum(axis=-1)


def pd_velocity_feedforward_torque(kp, kd, kv, error, error_rate, theta_d_dot):
    """
    Return a PD with velocity feed-forward: Kp e + Kd ė + Kv θ̇d (N m).

    Kv (N m s/rad) times the planned velocity θ̇d pays the viscous friction of the planned
    motion, so a joint tracking a ramp needs no steady error to push it (a PD alone lags
    by b θ̇d / Kp behind a ramp against viscous friction b). Kv = 0 is :func:`pd_torque`.
    """
    return pd_torque(kp, kd, error, error_rate) + kv * theta_d_dot


@njit(cache=True, nogil=True, inline='always')
def compiled_pd_velocity_feedforward_torque(kp, kd, kv, error, error_rate, theta_d_dot):
    """Compiled twin of :func:`pd_velocity_feedforward_torque` (on the PD's twin)."""
    return compiled_pd_torque(kp, kd, error, error_rate) + kv * theta_d_dot

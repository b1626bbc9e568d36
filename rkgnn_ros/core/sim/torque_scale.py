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
The torque scale of an arm on its task: what its drives need, and so what they may give.

A simulated drive without a limit applies any torque it is handed (a feed-forward of 1e300
N m made the simulation diverge). A real drive is sized for its arm; :func:`torque_scale`
gives that size per joint from the arm itself and the reference it follows:

    S_j = max_θ |G_j(θ)| + Σ_k max_θ |M_jk(θ)| (a_k + v_k²) + viscous_j v_j + coulomb_j

over :data:`POSES` poses drawn in the joint range (the planar arm: every angle; the
stretched pose too) and the reference sampled every 1 ms (at most
:data:`MAX_REFERENCE_SAMPLES` samples) over ``span`` seconds: v_k and a_k are its largest
speed and acceleration, at least :data:`FLOOR_SPEED` and :data:`FLOOR_ACCELERATION` (an
arm that barely moves may still be pushed). ``v²`` stands for the Coriolis and centrifugal
terms (of order M v²). :data:`DEFAULT_LIMIT_FACTOR` times S is ``sim_arm``'s default drive
limit: well above what tracking the reference takes, never unbounded.
"""

import numpy as np

__all__ = ['DEFAULT_LIMIT_FACTOR', 'FLOOR_ACCELERATION', 'FLOOR_SPEED', 'POSES',
           'default_torque_limit', 'torque_scale']

#: The default limit is this many times the torque scale.
DEFAULT_LIMIT_FACTOR = 2.0
#: Least acceleration (rad/s^2) and speed (rad/s) the scale allows for.
FLOOR_ACCELERATION = 10.0
FLOOR_SPEED = 3.0
#: Poses drawn for the largest gravity and inertia terms.
POSES = 64
#: Most reference samples taken (1 ms apart, or sparser over a long span).
MAX_REFERENCE_SAMPLES = 200_000


def _poses(arm, rng: np.random.Generator) -> np.ndarray:
    """Return (POSES + 2, n) poses in the arm's joint range, the zero pose clipped into it."""
    n = arm.n_joints
    lower = np.asarray(getattr(arm, 'lower', np.full(n, -np.pi)), dtype=float)
    upper = np.asarray(getattr(arm, 'upper', np.full(n, np.pi)), dtype=float)
    lower = np.where(np.isfinite(lower), lower, -np.pi)
    upper = np.where(np.isfinite(upper), upper, np.pi)
    drawn = rng.uniform(lower, upper, size=(POSES, n))
    return np.vstack([drawn, np.clip(np.zeros(n), lower, upper), 0.5 * (lower + upper)])


def _reference_extremes(reference, span: float, n: int):
    """Return the largest |θ̇d| and |θ̈d| per joint over ``[0, span]`` s of the reference."""
    count = int(min(MAX_REFERENCE_SAMPLES, max(3, np.ceil(span / 1e-3) + 1)))
    t = np.linspace(0.0, max(span, 1e-3), count)
    _, theta_d_dot = reference.evaluate(t)
    theta_d_dot = np.asarray(theta_d_dot, dtype=float).reshape(count, n)
    theta_d_ddot = np.gradient(theta_d_dot, t, axis=0)
    speed = np.nanmax(np.abs(theta_d_dot), axis=0)
    acceleration = np.nanmax(np.abs(theta_d_ddot), axis=0)
    return speed, acceleration


def torque_scale(arm, reference, span: float, seed: int = 0) -> np.ndarray:
    """
    Return the torque scale S (N m) per joint of ``arm`` following ``reference``.

    Parameters
    ----------
    arm : PlanarArm or UrdfArm
        ``gravity_terms``, ``mass_matrix``, ``friction_terms`` over leading batch axes;
        ``lower`` / ``upper`` joint limits when it has them.
    reference : Reference
        ``evaluate(t) -> (θd, θ̇d)``.
    span : float
        Seconds of the reference sampled from 0.
    seed : int
        Seed of the drawn poses (the scale is deterministic).

    Returns
    -------
    ndarray, shape (n,)
        Finite and positive.

    """
    n = arm.n_joints
    poses = _poses(arm, np.random.default_rng(seed))
    gravity = np.max(np.abs(np.asarray(arm.gravity_terms(poses), dtype=float)), axis=0)
    inertia = np.max(np.abs(np.asarray(arm.mass_matrix(poses), dtype=float)), axis=0)
    speed, acceleration = _reference_extremes(reference, span, n)
    speed = np.maximum(np.nan_to_num(speed, nan=0.0), FLOOR_SPEED)
    acceleration = np.maximum(np.nan_to_num(acceleration, nan=0.0), FLOOR_ACCELERATION)
    friction = np.abs(np.asarray(arm.friction_terms(speed), dtype=float))
    scale = gravity + inertia @ (acceleration + speed ** 2) + friction
    if not np.all(np.isfinite(scale)) or np.any(scale <= 0.0):
        raise ValueError(f'the torque scale of the arm is not finite and positive: '
                         f'{scale.tolist()}')
    return scale


def default_torque_limit(arm, reference, span: float) -> np.ndarray:
    """Return :data:`DEFAULT_LIMIT_FACTOR` times :func:`torque_scale` (N m), shape (n,)."""
    return DEFAULT_LIMIT_FACTOR * torque_scale(arm, reference, span)

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
The ``sim_arm`` node's parameters: their table, and the simulated system they define.

:data:`PARAMETERS` lists every parameter as a :class:`~rkgnn_ros.node.parameters.ParameterSpec`
row (name, default, description, range, what a change does); :func:`build_config` checks
what rclpy's descriptors cannot (array lengths and elements, choices, cross-parameter
rules, a stable integration step) and builds the arm, its servo settings, the sensors and
the reference into one :class:`SimConfig`. The arm is the planar arm of ``masses``,
``lengths``, ... or, with ``robot_description``, a URDF arm (:mod:`rkgnn_ros.sim_node.arm_model`).
Nothing here touches a node, so the rules are tested on plain dictionaries of values.
"""

from functools import partial
import math
from typing import List, NamedTuple, Tuple

import numpy as np
from rkgnn_ros.core.integration.rkg import STABILITY_LIMIT as RK4_REAL_STABILITY_LIMIT
from rkgnn_ros.core.sim.parameters import ArmParameters, MASS_MODELS
from rkgnn_ros.core.sim.plant import PlanarArm
from rkgnn_ros.core.sim.sensors import SensorModel, VELOCITY_SOURCES
from rkgnn_ros.core.sim.servo import DEFAULT_WINDUP_TIME, GRAVITY_MODES
from rkgnn_ros.core.sim.stability import max_stable_rkg_step
from rkgnn_ros.core.sim.torque_scale import DEFAULT_LIMIT_FACTOR, default_torque_limit
from rkgnn_ros.core.sim.trajectories import (Chirp, hanging_pose, paper_reference,
                                             Reference, SumOfSines, Switched)
from rkgnn_ros.node.parameters import Change, ParameterSpec
from rkgnn_ros.sim_node.arm_model import build_urdf_arm, reference_limit_warning, URDF_PARAMETERS

__all__ = ['BY_NAME', 'build_config', 'ConfigurationError', 'MAX_REFERENCE_POINTS',
           'PARAMETERS', 'REFERENCE_TYPES', 'SimConfig']

#: Reference kinds of the ``reference.type`` parameter.
REFERENCE_TYPES = ('paper', 'sines', 'chirp')

#: Most points in one reference_trajectory message.
MAX_REFERENCE_POINTS = 100_000

#: Longest span of the reference (s) the default torque limit is taken over.
MAX_REFERENCE_SPAN = 3600.0


class ConfigurationError(ValueError):
    """An invalid parameter at start; the message names the parameter."""


#: A row of the table below: set at start unless it says ``change=Change.LIVE``.
_Spec = partial(ParameterSpec, change=Change.START)

_MAX_INT = 2 ** 31 - 1

#: Every parameter: name, default (also in config/sim_arm.yaml), description, range.
PARAMETERS = (
    _Spec('joint_names', ['joint1', 'joint2', 'joint3'],
          'Names of the n joints, base to tip; n is their count.',
          constraints='at least one; unique, non-empty names'),
    _Spec('masses', [6.0, 4.0, 3.0], 'Link masses m_i (kg).',
          constraints='n values, each > 0'),
    _Spec('lengths', [0.2, 0.3, 0.1], 'Link lengths l_i (m).',
          constraints='n values, each > 0'),
    _Spec('mass_model', 'point',
          "'point': each mass at the tip of its link; 'rod': uniform slender rods.",
          constraints="'point' or 'rod'"),
    _Spec('gravity', 9.81, 'Gravitational acceleration along -y (m/s^2).', 0.0, 100.0),
    _Spec('viscous', [0.5, 0.3, 0.1], 'Viscous friction coefficients (N m s/rad).',
          constraints='n values, each >= 0'),
    _Spec('coulomb', [0.3, 0.2, 0.1],
          'Coulomb friction levels (N m), smoothed as coulomb * tanh(v / coulomb_velocity).',
          constraints='n values, each >= 0'),
    _Spec('coulomb_velocity', 0.05, 'Smoothing velocity of the Coulomb friction (rad/s).',
          1e-6, 100.0),
    _Spec('kp', [32.84, 42.05, 42.31], 'Proportional gains, diagonal (N m/rad).',
          constraints='n values, each >= 0'),
    _Spec('kd', [42.44, 0.19, 4.86], 'Derivative gains, diagonal (N m s/rad).',
          constraints='n values, each >= 0'),
    _Spec('ki', [0.0],
          'Integral gains, diagonal (N m/(rad s)); 0 = no integral term (a PD servo).',
          constraints='n values or one for every joint, each >= 0'),
    _Spec('gravity_compensation', 'none',
          "Gravity torque the servo adds from the arm's own model: 'none', 'measured' "
          "(at the measured position) or 'desired' (at the commanded position).",
          constraints="'none', 'measured' or 'desired'"),
    _Spec('tau_limit', [0.0],
          'Torque limits of the drives (N m); the applied, published torque is clipped to '
          '+-limit and a feed-forward beyond it is refused; 0 = the default: twice the '
          "arm's torque scale on its reference (gravity, inertia, friction).",
          constraints='n values or one for every joint, each >= 0'),
    _Spec('windup_time', DEFAULT_WINDUP_TIME,
          'Back-calculation anti-windup time constant of the integral term (s).',
          1e-4, 1e4),
    _Spec('reference.type', 'paper',
          "Desired trajectory: 'paper' (fixed sums of sines about the hanging pose), "
          "'sines' (random sums of sines, reference.seed), 'chirp' (linear chirp).",
          constraints="'paper', 'sines' or 'chirp'"),
    _Spec('reference.seed', 1, "Seed of the random sines of reference.type 'sines'.",
          0, _MAX_INT),
    _Spec('reference.amplitude', 0.5,
          "Amplitude per joint (rad) of 'sines' (sum of the sines' amplitudes) and 'chirp'; "
          "'paper' has fixed amplitudes.", 0.0, math.pi),
    _Spec('reference.n_terms', 3, "Sines per joint of 'sines'.", 1, 20),
    _Spec('reference.min_frequency', 0.1, "Lowest frequency of 'sines' (Hz).", 0.001, 50.0),
    _Spec('reference.max_frequency', 0.8,
          "Highest frequency of 'sines' (Hz), >= reference.min_frequency.", 0.001, 50.0),
    _Spec('reference.chirp_start_frequency', 0.05, "Start frequency of 'chirp' (Hz).",
          0.0, 50.0),
    _Spec('reference.chirp_end_frequency', 1.0,
          "Frequency of 'chirp' at the end of its sweep, held afterwards (Hz).", 0.0, 50.0),
    _Spec('reference.chirp_duration', 60.0, "Sweep time of 'chirp' (s).", 0.01, 1e9),
    _Spec('reference.switch_at', 0.0,
          'Simulation time (s) at which the arm switches to another task: random sines '
          '(reference.switch_seed, the amplitude and frequency band of reference.*) about '
          'the pose moved by reference.switch_shift, joined over reference.switch_blend; '
          '0 = never.', 0.0, 1e9),
    _Spec('reference.switch_seed', 2, 'Seed of the sines after the switch.', 0, _MAX_INT),
    _Spec('reference.switch_shift', 0.4,
          "Added to every joint's centre pose after the switch (rad).", -math.pi, math.pi),
    _Spec('reference.switch_blend', 2.0,
          'Time over which the old reference turns into the new one (s).', 0.01, 60.0),
    _Spec('noise.theta_std', 0.0,
          'Standard deviation of the white noise on the published positions (rad); '
          'may be changed at run time.', 0.0, 1.0, change=Change.LIVE),
    _Spec('noise.theta_dot_std', 0.0,
          'Standard deviation of the white noise on the published velocities (rad/s) when '
          "sensors.velocity is 'sensor'; may be changed at run time.", 0.0, 100.0,
          change=Change.LIVE),
    _Spec('sensors.velocity', 'sensor',
          "What the driver publishes as velocity: 'sensor' (true velocity plus "
          "noise.theta_dot_std), 'difference' (backward difference of the published "
          "positions), 'filtered' (that difference through a first-order low-pass at "
          "sensors.velocity_cutoff) or 'none' (an empty velocity field).",
          constraints="'sensor', 'difference', 'filtered' or 'none'"),
    _Spec('sensors.velocity_cutoff', 20.0,
          "Cut-off of the low-pass of sensors.velocity 'filtered' (Hz).", 0.01, 1e4),
    _Spec('sensors.effort', True,
          'Publish the applied torque as effort; false: an empty effort field (a driver '
          'without torque sensing).'),
    _Spec('sensors.stamp_jitter', 0.0,
          'Error of the joint_states stamps (s): each is off the sampling instant by a '
          'uniform draw in [-jitter, +jitter], at most a quarter period.', 0.0, 0.1),
    _Spec('sensors.drop_fraction', 0.0,
          'Share of joint_states messages not published (drawn per message).', 0.0, 0.5),
    _Spec('sensors.commands', True,
          'Publish joint_commands (θd, θ̇d); false: as a real driver, only the plan on '
          'reference_trajectory.'),
    _Spec('payload.mass', 0.0,
          'A payload picked up (kg): a point mass on the last link at payload.com, attached '
          'at payload.attach_at or by ~/payload; the servo is not told.', 0.0, 1000.0),
    _Spec('payload.com', [0.0, 0.0, 0.0],
          "The payload's centre of mass (m) in the last moving joint's frame (URDF arm); the "
          'planar arm carries it at the last link tip.', constraints='3 values'),
    _Spec('payload.attach_at', 0.0,
          'Simulation time (s) at which the payload is attached; 0: only by ~/payload.',
          0.0, 1e9),
    _Spec('payload.detach_at', 0.0,
          'Simulation time (s) at which it is released; 0: never.', 0.0, 1e9),
    _Spec('seed', 0, 'Seed of the measurement noise generator.', 0, _MAX_INT),
    _Spec('publish_rate', 100.0, 'Rate of joint_states and joint_commands (Hz).',
          1.0, 10000.0),
    _Spec('control_rate', 0.0,
          'Rate of a digital PD with zero-order hold (Hz); 0 = continuous-time PD.',
          0.0, 1e6),
    _Spec('integration_step', 0.0005,
          'Largest fixed Runge-Kutta step (s); must be stable for the closed loop.',
          1e-6, 0.1),
    _Spec('max_speed', 100.0,
          'A joint speed above this (rad/s) means the simulation diverged: the node stops '
          'with an error.', 1e-3, 1e6),
    _Spec('reference_horizon', 3.0, 'Time covered by each reference_trajectory (s).',
          0.0, 3600.0),
    _Spec('reference_dt', 0.02, 'Spacing of the reference_trajectory points (s).',
          1e-4, 10.0),
    _Spec('reference_rate', 2.0,
          'Rate of reference_trajectory (Hz): it goes out with every k-th state, '
          'k = floor(publish_rate / reference_rate), so never less often than asked.',
          1.0, 10000.0),
    _Spec('duration', 0.0,
          'Seconds of clock time from the start of the simulation after which the node exits '
          'cleanly (exit code 0); 0 = run forever.',
          0.0, 1e9),
) + URDF_PARAMETERS

#: The rows of :data:`PARAMETERS` by name.
BY_NAME = {spec.name: spec for spec in PARAMETERS}


class SimConfig(NamedTuple):
    """The validated settings of a :class:`SimArm`."""

    joint_names: Tuple[str, ...]
    arm: PlanarArm                   # or a UrdfArm (robot_description)
    robot_description: str           # the URDF arm's (reduced) URDF, '' for the planar arm
    kp: np.ndarray
    kd: np.ndarray
    ki: np.ndarray
    gravity_compensation: str
    tau_limit: np.ndarray            # (n,) N m, finite: given, or the arm's default
    tau_limit_note: str              # how it was chosen, for the start log
    windup_time: float
    sensors: SensorModel
    reference: Reference
    reference_type: str
    seed: int
    theta_std: float
    theta_dot_std: float
    publish_rate: float
    control_rate: float
    integration_step: float
    stable_step: float
    max_speed: float
    reference_horizon: float
    reference_dt: float
    reference_rate: float
    duration: float
    payload: tuple = (0.0, (0.0, 0.0, 0.0), 0.0, 0.0)   # mass, com, attach_at, detach_at
    stamp_jitter: float = 0.0        # s, uniform error of the joint_states stamps
    drop_fraction: float = 0.0       # share of joint_states not published
    publish_commands: bool = True    # joint_commands published


def _joint_vector(values: dict, name: str, n: int, *, positive: bool,
                  broadcast: bool = False) -> np.ndarray:
    arr = np.asarray(values[name], dtype=float)
    if broadcast and arr.shape == (1,):
        arr = np.full(n, arr[0])
    if arr.shape != (n,):
        raise ConfigurationError(
            f'{name} has {arr.size} values but the arm has {n} joints; give one per joint'
            + (' or one for every joint' if broadcast else ''))
    if not np.all(np.isfinite(arr)):
        raise ConfigurationError(f'{name} must be finite, got {arr.tolist()}')
    bad = arr <= 0.0 if positive else arr < 0.0
    if np.any(bad):
        bound = '> 0' if positive else '>= 0'
        raise ConfigurationError(f'{name} must all be {bound}, got {arr.tolist()}')
    return arr


def _build_reference(values: dict, n: int, offsets=None) -> Reference:
    kind = values['reference.type']
    if kind not in REFERENCE_TYPES:
        raise ConfigurationError(
            f'reference.type must be one of {list(REFERENCE_TYPES)}, got {kind!r}')
    offsets = hanging_pose(n) if offsets is None else offsets
    if kind == 'paper':
        paper = paper_reference(n)
        return SumOfSines(offsets, paper.amplitudes, paper.frequencies_hz, paper.phases)
    amplitude = values['reference.amplitude']
    if kind == 'sines':
        low, high = values['reference.min_frequency'], values['reference.max_frequency']
        if low > high:
            raise ConfigurationError(
                f'reference.min_frequency ({low} Hz) must not exceed reference.max_frequency '
                f'({high} Hz)')
        rng = np.random.default_rng(values['reference.seed'])
        return SumOfSines.random(n, rng, n_terms=values['reference.n_terms'],
                                 amplitude=amplitude, max_frequency_hz=high,
                                 min_frequency_hz=low, offsets=offsets)
    return Chirp(offsets, np.full(n, amplitude),
                 values['reference.chirp_start_frequency'],
                 values['reference.chirp_end_frequency'], values['reference.chirp_duration'])


def _switched_reference(values: dict, first: Reference, n: int, offsets=None) -> Reference:
    """Return ``first``, or it switching to another task at ``reference.switch_at``."""
    at = values['reference.switch_at']
    if not at:
        return first
    low, high = values['reference.min_frequency'], values['reference.max_frequency']
    if low > high:
        raise ConfigurationError(
            f'reference.min_frequency ({low} Hz) must not exceed reference.max_frequency '
            f'({high} Hz)')
    offsets = hanging_pose(n) if offsets is None else np.asarray(offsets, dtype=float)
    rng = np.random.default_rng(values['reference.switch_seed'])
    second = SumOfSines.random(n, rng, n_terms=values['reference.n_terms'],
                               amplitude=values['reference.amplitude'], max_frequency_hz=high,
                               min_frequency_hz=low,
                               offsets=offsets + values['reference.switch_shift'])
    return Switched(first, second, at, values['reference.switch_blend'])


def build_config(values: dict) -> Tuple[SimConfig, List[str]]:
    """
    Validate parameter values (name -> value) and build the simulated system.

    Returns the configuration and a list of warnings. Raises :class:`ConfigurationError`
    naming the offending parameter. Ranges of scalar parameters are enforced by rclpy
    through their descriptors before this runs; they are checked here only where the
    array parameters or cross-parameter rules need it.
    """
    warnings = []
    urdf = build_urdf_arm(values, ConfigurationError)
    names = (urdf.joint_names if urdf is not None
             else tuple(str(name) for name in values['joint_names']))
    if not names or any(not name for name in names):
        raise ConfigurationError(
            f'joint_names must list at least one non-empty name, got {list(names)}')
    if len(set(names)) != len(names):
        raise ConfigurationError(f'joint_names must be unique, got {list(names)}')
    n = len(names)
    viscous = _joint_vector(values, 'viscous', n, positive=False)
    coulomb = _joint_vector(values, 'coulomb', n, positive=False)
    kp = _joint_vector(values, 'kp', n, positive=False)
    kd = _joint_vector(values, 'kd', n, positive=False)
    ki = _joint_vector(values, 'ki', n, positive=False, broadcast=True)
    tau_limit = _joint_vector(values, 'tau_limit', n, positive=False, broadcast=True)
    if values['gravity_compensation'] not in GRAVITY_MODES:
        raise ConfigurationError(
            f'gravity_compensation must be one of {list(GRAVITY_MODES)}, got '
            f'{values["gravity_compensation"]!r}')
    if values['sensors.velocity'] not in VELOCITY_SOURCES:
        raise ConfigurationError(
            f'sensors.velocity must be one of {list(VELOCITY_SOURCES)}, got '
            f'{values["sensors.velocity"]!r}')
    if values['sensors.velocity'] != 'sensor' and values['noise.theta_dot_std'] > 0.0:
        raise ConfigurationError(
            f'noise.theta_dot_std must be 0 with sensors.velocity '
            f'{values["sensors.velocity"]!r}: only a sensed velocity has noise of its own')
    sensors = SensorModel(theta_std=values['noise.theta_std'],
                          theta_dot_std=values['noise.theta_dot_std'],
                          velocity=values['sensors.velocity'],
                          velocity_cutoff=values['sensors.velocity_cutoff'],
                          effort=values['sensors.effort'])
    try:
        if urdf is None:
            arm = _planar_arm(values, n, viscous, coulomb)
        else:
            arm = urdf.arm
            arm.set_friction(viscous, coulomb)
    except ValueError as error:     # messages name the field, e.g. 'gravity must be finite'
        if isinstance(error, ConfigurationError):
            raise
        raise ConfigurationError(str(error)) from None
    try:
        home = None if urdf is None else urdf.home
        reference = _switched_reference(values, _build_reference(values, n, home), n, home)
    except ValueError as error:
        if isinstance(error, ConfigurationError):
            raise
        raise ConfigurationError(f'reference.*: {error}') from None
    if urdf is not None:
        warnings.append(reference_limit_warning(arm, reference) or '')
    try:
        default_limit = default_torque_limit(arm, reference, _reference_span(values))
    except ValueError as error:     # an arm whose torque scale is not finite
        raise ConfigurationError(f'tau_limit: no default: {error}') from None

    reference_dt = values['reference_dt']
    horizon = values['reference_horizon']
    if horizon / reference_dt > MAX_REFERENCE_POINTS:
        raise ConfigurationError(
            f'reference_horizon / reference_dt = {horizon / reference_dt:.0f} points; at most '
            f'{MAX_REFERENCE_POINTS} (increase reference_dt)')

    # the step must be stable for the closed loop at the start state (on the reference)
    h = values['integration_step']
    theta0, theta_dot0 = reference.evaluate(0.0)
    stiffness = arm.closed_loop_stiffness(theta0, theta_dot0, kp, kd)
    limit = arm.stable_step(kp, kd, theta0, theta_dot0, safety=1.0)
    if not h < limit:
        raise ConfigurationError(
            f'integration_step = {h} s is unstable: at the start state the fastest eigenvalue '
            f'of the closed loop has |lambda| = {stiffness:.4g} 1/s and the Runge-Kutta step '
            f'is stable only below {limit:.4g} s (h |lambda| < {RK4_REAL_STABILITY_LIMIT:.3f}'
            f' on the real axis); use integration_step <= {0.5 * limit:.3g} s')
    along = max_stable_rkg_step(arm, kp, kd, reference, duration=10.0, samples=100,
                                safety=0.5)
    if h > along:
        warnings.append(
            f'integration_step = {h} s is more than half the stability limit somewhere on the '
            f'first 10 s of the reference (half-limit {along:.3g} s); the simulation may '
            'become inaccurate or diverge')
    control_rate = values['control_rate']
    if control_rate > 0.0 and control_rate < 0.5 * stiffness:
        warnings.append(
            f'control_rate = {control_rate} Hz is below about |lambda| / 2 = '
            f'{0.5 * stiffness:.0f} Hz for the fastest eigenvalue of the closed loop: the '
            'digital PD may chatter or diverge')
    config = SimConfig(
        joint_names=names, arm=arm,
        robot_description='' if urdf is None else urdf.description, kp=kp, kd=kd, ki=ki,
        gravity_compensation=values['gravity_compensation'],
        tau_limit=np.where(tau_limit > 0.0, tau_limit, default_limit),
        tau_limit_note=_limit_note(tau_limit, default_limit),
        windup_time=float(values['windup_time']), sensors=sensors, reference=reference,
        reference_type=values['reference.type'], seed=int(values['seed']),
        theta_std=float(values['noise.theta_std']),
        theta_dot_std=float(values['noise.theta_dot_std']),
        publish_rate=float(values['publish_rate']), control_rate=float(control_rate),
        integration_step=float(h), stable_step=float(limit),
        max_speed=float(values['max_speed']), reference_horizon=float(horizon),
        reference_dt=float(reference_dt), reference_rate=float(values['reference_rate']),
        duration=float(values['duration']),
        stamp_jitter=min(float(values['sensors.stamp_jitter']),
                         0.25 / float(values['publish_rate'])),
        drop_fraction=float(values['sensors.drop_fraction']),
        payload=_payload(values, arm),
        publish_commands=bool(values['sensors.commands']))
    return config, [warning for warning in warnings if warning]


def _reference_span(values: dict) -> float:
    """Return the seconds of the reference its default torque limit is taken over."""
    span = 60.0
    if values['reference.type'] == 'chirp':
        span = max(span, values['reference.chirp_duration'] + 10.0)
    if values['reference.switch_at']:
        span = max(span, values['reference.switch_at'] + values['reference.switch_blend']
                   + 60.0)
    return min(span, MAX_REFERENCE_SPAN)


def _limit_note(given: np.ndarray, default: np.ndarray) -> str:
    """Return how the drive limits were chosen, e.g. 'default 247, 136, 19.2 N m'."""
    values = np.where(given > 0.0, given, default)
    text = ', '.join(f'{v:.3g}' for v in values)
    if np.all(given > 0.0):
        return f'{text} N m (tau_limit)'
    return (f"{text} N m ({'default' if not np.any(given > 0.0) else 'tau_limit, 0: default'}"
            f" = {DEFAULT_LIMIT_FACTOR:g}x the arm's torque scale on its reference)")


def _payload(values: dict, arm) -> tuple:
    """Return (mass, com, attach_at, detach_at) of the payload parameters, checked."""
    from rkgnn_ros.core.sim.payload import with_payload
    mass, com = float(values['payload.mass']), tuple(values['payload.com'])
    if len(com) != 3:
        raise ConfigurationError(f'payload.com must hold 3 values (m), got {list(com)}')
    if mass > 0.0:
        try:
            with_payload(arm, mass, com)
        except ValueError as error:
            raise ConfigurationError(f'payload: {error}') from None
    attach, detach = float(values['payload.attach_at']), float(values['payload.detach_at'])
    if detach and attach and detach <= attach:
        raise ConfigurationError(f'payload.detach_at ({detach} s) must come after '
                                 f'payload.attach_at ({attach} s)')
    return mass, com, attach, detach


def _planar_arm(values: dict, n: int, viscous, coulomb) -> PlanarArm:
    """Return the planar arm of the parameters (n joints)."""
    masses = _joint_vector(values, 'masses', n, positive=True)
    lengths = _joint_vector(values, 'lengths', n, positive=True)
    if values['mass_model'] not in MASS_MODELS:
        raise ConfigurationError(
            f'mass_model must be one of {list(MASS_MODELS)}, got {values["mass_model"]!r}')
    return PlanarArm(ArmParameters(
        masses=masses, lengths=lengths, mass_model=values['mass_model'],
        gravity=values['gravity'], viscous=viscous, coulomb=coulomb,
        coulomb_velocity=values['coulomb_velocity']))

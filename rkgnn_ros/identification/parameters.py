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
The identifier's parameters: the table, the checks, and one consistent snapshot per change.

:data:`PARAMETERS` and :data:`OUTPUTS` are the node's rows (:class:`~rkgnn_ros.node.parameters.
ParameterSpec`), each saying what a change does. :func:`check_parameters` is the on-set
validation rclpy cannot do (open bounds, cross-parameter rules, the optimizer's own rules);
its reasons name the parameter and its bound. :class:`IdentifierParameters` holds the
accepted values; every accepted change replaces its :class:`Config`, an immutable snapshot
the other parts read whole (one reference), so a generation, a message or a prediction
never sees a change half applied.
"""

from dataclasses import dataclass, replace
import math
import re
import threading
from types import MappingProxyType
from typing import Dict, Mapping, Optional, Sequence, Tuple

from rcl_interfaces.msg import SetParametersResult
from rclpy.exceptions import InvalidTopicNameException
from rclpy.expand_topic_name import expand_topic_name
from rclpy.parameter import Parameter
from rclpy.validate_full_topic_name import validate_full_topic_name
from rkgnn_ros.core.fitting.identify import normalize_case
from rkgnn_ros.core.fitting.online import AUTO_BASIS, OnlineSettings
from rkgnn_ros.core.fitting.optimizers import CMAES, OPTIMIZERS, PaperEA
from rkgnn_ros.core.model.spec import CASES, INERTIA_MODES, NetworkSpec, VELOCITY_MODES
from rkgnn_ros.identification.description import MAX_DESCRIPTION_BYTES
from rkgnn_ros.identification.ros2_control import declare_controller_gains
from rkgnn_ros.node.parameters import Change, ParameterSpec
from rkgnn_ros.wire.conversions import MAX_NAME_BYTES

__all__ = ['PARAMETERS', 'OUTPUTS', 'PARAMETER_CASES', 'Config', 'ConfigurationError',
           'IdentifierParameters', 'auto_case', 'check_parameters', 'make_config',
           'network_spec', 'network_specs', 'optimizer_settings', 'online_settings']

#: What an accepted value may be, beyond the rows' own ranges (README, *Reliability*).
MAX_JOINTS = 64              # joints (and gains per joint) a parameter may list
MAX_GAIN = 1e6               # kp, kd: N m/rad and N m s/rad; larger overflow the rollouts
MAX_POPULATION = 10_000      # candidates per generation (and tournament size)
MIN_SIGMA = CMAES.SIGMA_FLOOR  # es.sigma, genome units
MIN_PREDICTION_RATE = 0.1    # Hz, when prediction.rate is not 0 (off)
MAX_PREDICTION_POINTS = 10_000  # prediction.horizon / model_step
MAX_PATH_BYTES = 4096        # model_file (PATH_MAX on Linux)
MAX_EFFORT = 1e6             # feedforward.max_effort, N m

_T = Parameter.Type
_RESTART = Change.RESTART
_REBUILD = Change.RESTART | Change.BUFFER  # a new timeline or layout: data and search anew
_REC = NetworkSpec.recommended(1, 'torque')
#: Values of the ``case`` parameter: the three cases and 'auto' (chosen from the streams).
PARAMETER_CASES = ('auto',) + CASES
_RESTARTS = 'Changing it restarts the search.'
_ES_NOTE = 'Applied between generations.'
BEYOND_PLAN = ('stop', 'hold')
VELOCITY_ESTIMATES = ('buffered', 'missing', 'always')

#: The online policy's own defaults (:class:`OnlineSettings`): the parameters that set the
#: policy's settings take theirs from it, so each default is declared once (the core cannot
#: read this table: its layers point down).
_POLICY = OnlineSettings()

PARAMETERS = (
    ParameterSpec('case', 'auto',
                  "Identification case: 'auto' (from the streams: effort in joint_states -> "
                  "'torque'; else kp and kd given -> 'pd_gains'; else 'unknown'; switching "
                  "when the streams change), 'torque' (1, measured torque), 'pd_gains' (2, "
                  "known PD gains kp, kd) or 'unknown' (3, the controller is identified "
                  'too); 1/2/3 accepted. Changing it clears the buffer and restarts the '
                  'search.',
                  choices=PARAMETER_CASES, change=_REBUILD),
    ParameterSpec('kp', (), "Known proportional gains per joint (case 'pd_gains'). "
                  + _RESTARTS, low=0.0, high=MAX_GAIN, ptype=_T.DOUBLE_ARRAY,
                  max_items=MAX_JOINTS, change=_RESTART),
    ParameterSpec('kd', (), "Known derivative gains per joint (case 'pd_gains'). "
                  + _RESTARTS, low=0.0, high=MAX_GAIN, ptype=_T.DOUBLE_ARRAY,
                  max_items=MAX_JOINTS, change=_RESTART),
    ParameterSpec('joints', (),
                  'Joint names, in model column order; empty: the names of the first '
                  'joint_states message (or of the loaded model_file). Changing it clears the '
                  'buffer and restarts the search.', ptype=_T.STRING_ARRAY,
                  max_items=MAX_JOINTS, max_bytes=MAX_NAME_BYTES, change=_REBUILD),
    ParameterSpec('window', 20.0,
                  'Seconds of newest data the search uses (training plus validation). '
                  'Changing it rebuilds the buffer.', 1.0, 600.0, change=Change.BUFFER),
    ParameterSpec('min_window', _POLICY.min_window,
                  'Seconds of buffered data needed before generations run.',
                  0.1, 600.0, constraints='<= window'),
    ParameterSpec('model_step', 0.01,
                  'Grid step (s) of the resampled data, the model and ~/prediction. Changing '
                  'it clears the buffer and restarts the search.', 0.001, 0.1, change=_REBUILD),
    ParameterSpec('substeps', _POLICY.substeps,
                  'RKG steps per model_step (0: automatic). ' + _RESTARTS, 0, 64,
                  change=_RESTART),
    ParameterSpec('gap_threshold', 0.1,
                  'Longer intervals (s) between samples split the data into segments. '
                  'Changing it rebuilds the buffer.', 0.001, 10.0, change=Change.BUFFER),
    ParameterSpec('max_rate_hz', 2000.0,
                  'Highest sample rate (Hz) kept per stream: samples closer than 1/max_rate_hz '
                  'are decimated (counted as rate_limited), which bounds the buffer memory '
                  'whatever the input rate. Read-only: set it at start (params file or '
                  '--ros-args -p).', 1.0, 100000.0, change=Change.START),
    ParameterSpec('validation_fraction', _POLICY.validation_fraction,
                  'Newest fraction of the window held out for the validation NRMSE (0: none).',
                  0.0, 0.5),
    ParameterSpec('stale_timeout', _POLICY.stale_timeout,
                  'Seconds without an accepted joint_states (and, in cases pd_gains/unknown, '
                  'joint_commands) sample after which the search pauses (state stale).',
                  0.05, 60.0),
    ParameterSpec('model_publish_period', _POLICY.model_publish_period,
                  'Minimum seconds between two ~/model messages.', 0.0, 3600.0),
    ParameterSpec('network.theta_units', _REC.theta_units,
                  'Gaussian RBF units over theta (inertia, Coriolis, gravity). ' + _RESTARTS,
                  0, 32, change=_RESTART),
    ParameterSpec('network.torque_units', _REC.torque_units,
                  "RBF units of each P and D torque sub-network (case 'unknown'). " + _RESTARTS,
                  0, 32, change=_RESTART),
    ParameterSpec('network.basis', AUTO_BASIS,
                  "Features of the theta-dependent outputs: 'auto' (the global network on "
                  'the planar trigonometric basis, started from its closed-form fit, where '
                  "that arm explains held-out data; else 'rbf' with the other network.* "
                  "settings, which the global network does not use), 'rbf' (the paper's "
                  "Gaussian units, local), 'trig' (the Fourier modes of an arm with parallel "
                  "axes, global), 'trig3d' (those of a spatial serial chain), 'poly', 'imq' "
                  "(inverse multiquadric units, wider reach than 'rbf'), or a sum such as "
                  "'trig+rbf' (rigid-body terms with local corrections). "
                  + _RESTARTS, change=_RESTART),
    ParameterSpec('network.inertia', _REC.inertia,
                  "'cholesky' (M = L L^T + eps I, positive definite) or 'penalty' (the "
                  "paper's). " + _RESTARTS, choices=INERTIA_MODES, change=_RESTART),
    ParameterSpec('network.velocity', _REC.velocity,
                  "'christoffel' (Coriolis and centrifugal terms from M, energy-consistent) or "
                  "'learned' (the paper's own RBF outputs). " + _RESTARTS,
                  choices=VELOCITY_MODES, change=_RESTART),
    ParameterSpec('network.bias', _REC.bias,
                  'Constant term on every theta-dependent output. ' + _RESTARTS,
                  change=_RESTART),
    ParameterSpec('network.friction', _REC.friction,
                  'Viscous and Coulomb friction per joint. ' + _RESTARTS, change=_RESTART),
    ParameterSpec('network.torque_linear', _REC.torque_linear,
                  "Linear P and D gains beside the torque RBF networks (case 'unknown'). "
                  + _RESTARTS, change=_RESTART),
    ParameterSpec('es.algorithm', _POLICY.optimizer,
                  "Optimizer: 'cmaes', 'sep-cmaes' or 'paper' (the paper's EA). A change swaps "
                  'the optimizer between generations, warm-started from the best genome.',
                  choices=OPTIMIZERS, change=Change.ES),
    ParameterSpec('es.population_size', 0,
                  "Candidates per generation; 0 (at start only): the algorithm's default "
                  '(cmaes: 4 + 3 ln N, paper: 100). ' + _ES_NOTE, 0, MAX_POPULATION,
                  constraints='0 (at start) or >= 2; >= es.tournament_size (paper)',
                  change=Change.ES),
    ParameterSpec('es.tournament_size', PaperEA.DEFAULTS['tournament_size'],
                  'paper: contestants per tournament.', 1, MAX_POPULATION,
                  constraints='<= es.population_size (paper)', change=Change.ES),
    ParameterSpec('es.crossover_rate', PaperEA.DEFAULTS['crossover_rate'],
                  'paper: probability that a parent pair is replaced by BLX-alpha children.',
                  0.0, 1.0, change=Change.ES),
    ParameterSpec('es.mutation_rate', PaperEA.DEFAULTS['mutation_rate'],
                  'paper: fraction of offspring mutated.', 0.0, 1.0, change=Change.ES),
    ParameterSpec('es.sigma', CMAES.DEFAULTS['sigma'],
                  'Step size (cmaes) or initial mutation spread (paper), in genome units '
                  '(elements of order 1): a step below 1e-6 moves no weight measurably, and '
                  'subnormal steps break CMA-ES.', MIN_SIGMA, 10.0, change=Change.ES),
    ParameterSpec('es.sigma_min', PaperEA.DEFAULTS['sigma_min'],
                  'paper: floor of the mutation spread.', 0.0, 10.0,
                  constraints='<= es.sigma (paper)', change=Change.ES),
    ParameterSpec('es.max_generations', _POLICY.max_generations,
                  'Generations per search before it stops (0: forever).', 0, 1_000_000_000),
    ParameterSpec('es.seed', _POLICY.seed,
                  "Seed of the optimizer's random generator, used when a search (re)starts.",
                  0, 2 ** 31 - 1),
    ParameterSpec('prediction.horizon', 2.0,
                  'Seconds predicted on ~/prediction (less where the plan ends first, see '
                  'prediction.beyond_plan).', 0.01, 60.0,
                  constraints=f'>= model_step; at most {MAX_PREDICTION_POINTS} model_steps'),
    ParameterSpec('prediction.rate', 10.0,
                  'Rate (Hz) of ~/prediction (0: only on_state; otherwise at least '
                  f'{MIN_PREDICTION_RATE} Hz, one prediction every 10 s).', 0.0, 1000.0,
                  off_below=MIN_PREDICTION_RATE),
    ParameterSpec('prediction.lookahead', 0.5,
                  'Seconds ahead of the newest state that ~/predicted_state shows (a JointState '
                  'stamped at the time it predicts, for plotting against joint_states); 0: '
                  'not published.', 0.0, 60.0, constraints='<= prediction.horizon'),
    ParameterSpec('prediction.on_state', False,
                  'Also predict on every accepted joint_states sample (at most once per '
                  'model_step).'),
    ParameterSpec('prediction.beyond_plan', 'stop',
                  "Past the end of the plan on reference_trajectory: 'stop' (the prediction "
                  "ends where the plan ends; no plan, no prediction) or 'hold' (the arm is "
                  "taken to hold the plan's last point, or the newest command; such points "
                  "are marked in header.frame_id, ';beyond_plan_from=<s>').",
                  choices=BEYOND_PLAN),
    ParameterSpec('selfcheck.window', 10.0,
                  'Seconds of recent predictions scored against the motion that followed '
                  '(the model, following the reference, holding the last state).',
                  1.0, 600.0),
    ParameterSpec('selfcheck.margin', 0.2,
                  'How much better than each baseline (a share of its error, over the window '
                  'and the last 2 s) the model must be to be published; it is set aside as '
                  'soon as it is worse than one, and the better baseline published, marked.',
                  0.0, 0.9),
    ParameterSpec('velocity.estimate', 'buffered',
                  "Where theta-dot is estimated from theta: 'buffered' (the search's data "
                  'always, by the lag-free centred derivative; the state a prediction starts '
                  "from only when joint_states has no velocity), 'missing' (only when it has "
                  "none) or 'always' (the start state too, by the causal fit: a driver that "
                  'differences noisy encoders). ' + _RESTARTS, choices=VELOCITY_ESTIMATES,
                  change=_RESTART),
    ParameterSpec('feedforward.enabled', False,
                  'Publish the learned feed-forward on ~/feedforward (cases torque and '
                  'pd_gains) whenever the model passes the gate; false: never (and stop '
                  'at once).'),
    ParameterSpec('feedforward.max_error', 0.05,
                  "Gate: the largest held-out torque error (RMSE / std of the joint's torque, "
                  'worst joint) on the newest validation samples.', 0.0, 10.0, low_open=True),
    ParameterSpec('feedforward.max_effort', (),
                  'Clip of the feed-forward per joint (N m): one value per joint or one for '
                  'all; empty: the feed-forward stays off.', low=0.0, high=MAX_EFFORT,
                  ptype=_T.DOUBLE_ARRAY, max_items=MAX_JOINTS, constraints='each > 0'),
    ParameterSpec('feedforward.forward_topic', '',
                  'Also publish the feed-forward here (e.g. a controller trajectory topic or '
                  '/sim_arm/feedforward); empty: only ~/feedforward. Read-only.',
                  max_bytes=MAX_NAME_BYTES, change=Change.START),
    ParameterSpec('model_file', '',
                  'Model YAML: loaded at start if present (published, start genome), written '
                  'atomically on ~/save_model and at shutdown; empty: no file. Only a regular '
                  'file (or a new path) is read or written: a directory, a device or a FIFO '
                  'is refused with the reason.', max_bytes=MAX_PATH_BYTES),
    ParameterSpec('robot_description', '',
                  "The arm's URDF (its XML, a file path, or example-robot-data:<path under "
                  'robots/>); empty: the newest message on the robot_description topic. With '
                  'one, the rigid body of its kinematics is identified in every case (no '
                  'search runs); without, the network is searched. ' + _RESTARTS,
                  max_bytes=MAX_DESCRIPTION_BYTES),
    ParameterSpec('identified_urdf_file', '',
                  'Where ~/save_urdf writes the identified URDF (the robot description with '
                  'the identified inertials and friction); empty: nowhere.',
                  max_bytes=MAX_PATH_BYTES),
    ParameterSpec('urdf.locked_joints', (),
                  'Movable URDF joints not identified, held at urdf.locked_positions (any '
                  'other one at 0 clipped into its limits).', ptype=_T.STRING_ARRAY,
                  max_items=MAX_JOINTS, max_bytes=MAX_NAME_BYTES, change=_RESTART),
    ParameterSpec('urdf.locked_positions', (),
                  'One position (rad) per urdf.locked_joints.', ptype=_T.DOUBLE_ARRAY,
                  max_items=MAX_JOINTS, change=_RESTART),
    ParameterSpec('gravity', 9.81,
                  'Gravitational acceleration (m/s^2) along -z of the root link of the robot '
                  'description.', 0.0, 100.0, change=_RESTART),
    ParameterSpec('controller_state', '',
                  "A joint_trajectory_controller's controller_state topic: its reference "
                  '(θd, θ̇d) joins the command stream (needs control_msgs); empty: none.',
                  change=Change.START, max_bytes=MAX_PATH_BYTES),
)

OUTPUTS = (
    ParameterSpec('identified.generation', 0, 'Output: generation of the published model.',
                  change=Change.OUTPUT),
    ParameterSpec('identified.cost', math.nan, 'Output: training cost of the published model.',
                  change=Change.OUTPUT),
    ParameterSpec('identified.validation_nrmse', math.nan,
                  'Output: validation theta-NRMSE of the published model.',
                  change=Change.OUTPUT),
    ParameterSpec('identified.kp', (),
                  "Output: the model's PD gains linearised at zero error (cases 2-3); case 1: "
                  'the gains of the controller law fitted from effort and joint_commands.',
                  ptype=_T.DOUBLE_ARRAY, change=Change.OUTPUT),
    ParameterSpec('identified.kd', (),
                  "Output: the model's derivative gains linearised at zero error (cases 2-3); "
                  'case 1: the fitted law.', ptype=_T.DOUBLE_ARRAY, change=Change.OUTPUT),
)

_BY_NAME = {spec.name: spec for spec in PARAMETERS}
_OUTPUT_NAMES = frozenset(spec.name for spec in OUTPUTS)
_ES_NAMES = ('population_size', 'tournament_size', 'crossover_rate', 'mutation_rate',
             'sigma_min', 'sigma', 'n_elite')
_NETWORK_NAMES = ('theta_units', 'torque_units', 'basis', 'inertia', 'velocity', 'bias',
                  'friction', 'torque_linear')


def optimizer_settings(values: Mapping) -> Tuple[str, dict]:
    """Return ``(algorithm, settings)`` for ``make_optimizer`` from parameter values."""
    algorithm = values['es.algorithm']
    size = values['es.population_size']
    if algorithm == 'paper':
        return algorithm, {
            'population_size': size or PaperEA.DEFAULTS['population_size'],
            'tournament_size': values['es.tournament_size'],
            'crossover_rate': values['es.crossover_rate'],
            'mutation_rate': values['es.mutation_rate'],
            'sigma': values['es.sigma'],
            'sigma_min': values['es.sigma_min'],
        }
    return algorithm, {'population_size': size or None, 'sigma': values['es.sigma']}


def online_settings(values: Mapping, version: int = 0) -> OnlineSettings:
    """Return the policy's settings the parameter values describe."""
    algorithm, settings = optimizer_settings(values)
    return OnlineSettings(
        case=_case(values['case']), kp=tuple(values['kp']), kd=tuple(values['kd']),
        network=MappingProxyType({name: values[f'network.{name}'] for name in _NETWORK_NAMES}),
        optimizer=algorithm, optimizer_settings=MappingProxyType(settings),
        seed=values['es.seed'], substeps=values['substeps'], min_window=values['min_window'],
        validation_fraction=values['validation_fraction'],
        stale_timeout=values['stale_timeout'],
        model_publish_period=values['model_publish_period'],
        max_generations=values['es.max_generations'], version=version)


def network_spec(values: Mapping, n_joints: int, case: Optional[str] = None) -> NetworkSpec:
    """
    Return the NetworkSpec the parameters describe for ``n_joints`` joints.

    ``case`` replaces the parameter's (needed when it is 'auto': the case the streams
    chose, or any case to check the other settings). Settings without a parameter (e.g.
    the inertia floor) keep their values of ``NetworkSpec.recommended``.
    """
    return _settings_for(values, case).spec(n_joints)


def _settings_for(values: Mapping, case: Optional[str]) -> OnlineSettings:
    """Return the online settings with ``case`` (or the parameter's) resolved ('auto': 3)."""
    settings = online_settings(values)
    case = case or settings.case
    return replace(settings, case='unknown' if case == 'auto' else case)


def network_specs(values: Mapping, n_joints: int, case: Optional[str] = None) -> list:
    """
    Return the networks the parameters allow (a loaded model must be one of them).

    :func:`network_spec`'s, and with ``network.basis: auto`` the global network too (what the
    search runs where the planar trigonometric arm holds).
    """
    settings = _settings_for(values, case)
    specs = [settings.spec(n_joints)]
    if settings.network.get('basis') == AUTO_BASIS:
        specs.append(settings.spec(n_joints, trig_holds=True))
    return specs


def _case(value) -> str:
    """Return the ``case`` parameter normalized: 'auto' or a case of ``normalize_case``."""
    return 'auto' if str(value).strip().lower() == 'auto' else normalize_case(value)


def auto_case(effort: bool, values: Mapping) -> str:
    """Return the case ``case: auto`` takes: 'torque' with effort, else by the gains given."""
    if effort:
        return 'torque'
    kp, kd = values['kp'], values['kd']
    return 'pd_gains' if kp and len(kp) == len(kd) else 'unknown'


def _prefixed(text: str, prefix: str, names: Sequence[str]) -> str:
    """Prefix the setting names in a core error message with their parameter group."""
    for name in sorted(names, key=len, reverse=True):
        text = re.sub(rf'(?<![\w.]){re.escape(name)}\b', prefix + name, text)
    return text


def _check_one(spec: ParameterSpec, value, at_start: bool, previous) -> Optional[str]:
    """Return why ``value`` is invalid for ``spec`` (None if valid)."""
    if spec.name == 'case' and isinstance(value, str):
        try:
            _case(value)
        except ValueError:
            return (f'case must be one of {", ".join(PARAMETER_CASES)} (or 1, 2, 3), got '
                    f'{value!r}')
        return None
    if spec.name == 'es.population_size' and type(value) is int and (
            value == 1 or (value == 0 and not at_start and previous != 0)):
        return (f"es.population_size must be >= 2 (0, the algorithm's default, is "
                f'accepted only at start), got {value}')
    return spec.check(value)


def check_parameters(values: Mapping, changed: Sequence[str], at_start: bool = False,
                     previous: Optional[Mapping] = None) -> Optional[str]:
    """
    Return why a set of parameter values is invalid, or None.

    ``values`` holds every parameter (the proposed ones merged into the current ones);
    ``changed`` names those to check one by one (cross-parameter rules are always checked).
    The reason names the parameter and its bound.
    """
    previous = previous or {}
    for name in changed:
        reason = _check_one(_BY_NAME[name], values[name], at_start, previous.get(name))
        if reason:
            return reason
    if values['min_window'] > values['window']:
        return (f"min_window ({values['min_window']}) must be <= window "
                f"({values['window']})")
    if values['prediction.lookahead'] > values['prediction.horizon']:
        return (f"prediction.lookahead ({values['prediction.lookahead']}) must be <= "
                f"prediction.horizon ({values['prediction.horizon']})")
    if values['prediction.horizon'] < values['model_step']:
        return (f"prediction.horizon ({values['prediction.horizon']}) must be >= model_step "
                f"({values['model_step']})")
    if values['prediction.horizon'] > MAX_PREDICTION_POINTS * values['model_step']:
        return (f"prediction.horizon ({values['prediction.horizon']}) must be at most "
                f"{MAX_PREDICTION_POINTS} model_steps ({values['model_step']} s each): a "
                'longer prediction is too large a message')
    joints = values['joints']
    try:
        network_spec(values, max(1, len(joints)))
    except ValueError as exc:
        return _prefixed(str(exc), 'network.', _NETWORK_NAMES)
    if _case(values['case']) == 'pd_gains':
        kp, kd = values['kp'], values['kd']
        if not kp or len(kp) != len(kd):
            return (f"case 'pd_gains' needs kp and kd with one value per joint, got "
                    f'{len(kp)} and {len(kd)} values')
        if joints and len(kp) != len(joints):
            return f'kp and kd have {len(kp)} values for {len(joints)} joints'
    if len(values['urdf.locked_joints']) != len(values['urdf.locked_positions']):
        return (f"urdf.locked_positions has {len(values['urdf.locked_positions'])} values for "
                f"the {len(values['urdf.locked_joints'])} urdf.locked_joints; give one per "
                'joint')
    clip = values['feedforward.max_effort']
    if any(v <= 0.0 for v in clip) or (joints and len(clip) not in (0, 1, len(joints))):
        return (f'feedforward.max_effort must hold one value > 0 per joint, one for all or '
                f'none, got {list(clip)}')
    topic = values['feedforward.forward_topic']
    if topic:
        try:  # as create_publisher will expand it (any node name and namespace will do)
            validate_full_topic_name(expand_topic_name(topic, 'identifier', '/'))
        except (InvalidTopicNameException, ValueError, RuntimeError) as exc:
            return f'feedforward.forward_topic is not a topic name: {exc}'
    algorithm, settings = optimizer_settings(values)
    cls = PaperEA if algorithm == 'paper' else CMAES
    try:
        cls.validate_settings(**settings)
    except ValueError as exc:
        return _prefixed(str(exc), 'es.', _ES_NAMES)
    return None


@dataclass(frozen=True)
class Config:
    """One consistent snapshot of the parameters and the policy settings they describe."""

    values: Mapping
    settings: OnlineSettings

    def __getitem__(self, name):
        return self.values[name]

    @property
    def case(self) -> str:
        """Return the case the settings say: torque, pd_gains, unknown (or auto, undecided)."""
        return self.settings.case


def make_config(**values) -> Config:
    """
    Return the snapshot of the table's defaults with ``values`` replacing some (by name).

    What the parts get from a node, built without one (tools and tests). Raises
    ConfigurationError if the values are invalid.
    """
    merged = {spec.name: spec.plain(spec.default) for spec in PARAMETERS}
    merged.update({name: _BY_NAME[name].plain(value) for name, value in values.items()})
    reason = check_parameters(merged, list(values), at_start=True)
    if reason:
        raise ConfigurationError(reason)
    return Config(MappingProxyType(merged), online_settings(merged))


class ConfigurationError(ValueError):
    """The parameters given at start are invalid: the node refuses to start."""


class IdentifierParameters:
    """
    The node's parameters: declared from the table, validated, applied as snapshots.

    Parameters
    ----------
    node : rclpy.node.Node
        The node to declare on.

    Raises
    ------
    ConfigurationError
        A value given at start is invalid (the message names the parameter).

    """

    def __init__(self, node):
        values = {spec.name: spec.plain(spec.declare(node)) for spec in PARAMETERS}
        if _check_one(_BY_NAME['joints'], values['joints'], True, None) is None:
            # gains.<joint>.p / .d: declared only for a joint list within its budget
            values = declare_controller_gains(node, values, ConfigurationError)
        for spec in OUTPUTS:
            spec.declare(node)
        reason = check_parameters(values, list(values), at_start=True)
        if reason:
            raise ConfigurationError(reason)
        self._lock = threading.Lock()
        self._internal = threading.local()
        self._config = Config(MappingProxyType(values), online_settings(values))

    @property
    def config(self) -> Config:
        """Return the current snapshot."""
        return self._config

    def validate(self, params) -> SetParametersResult:
        """Check a set of parameters (the on-set callback); never raises."""
        try:
            internal = getattr(self._internal, 'active', False)
            current = dict(self._config.values)
            values = dict(current)
            changed = []
            for param in params:
                name = param.name
                if not isinstance(name, str) or not name:
                    # rclpy's check of undeclared names lets '' through (any() of the names)
                    return SetParametersResult(
                        successful=False,
                        reason=f'parameter name {name!r} is not a parameter of the identifier')
                if name in _OUTPUT_NAMES:
                    if not internal:
                        return SetParametersResult(
                            successful=False,
                            reason=f'{name} is an output of the identifier, set by the node '
                                   'as the model improves; it cannot be set')
                    continue
                if name not in _BY_NAME:
                    continue  # use_sim_time and other parameters rclpy owns
                values[name] = param.value
                changed.append(name)
            if not changed:
                return SetParametersResult(successful=True)
            reason = check_parameters(values, changed, at_start=False, previous=current)
            return SetParametersResult(successful=reason is None, reason=reason or '')
        except Exception as exc:  # noqa: B902 - a callback must never raise
            return SetParametersResult(
                successful=False, reason=f'cannot validate the parameters: {exc!r}')

    def apply(self, params) -> Tuple[Tuple[str, ...], Change]:
        """
        Take accepted parameters (the post-set callback): ``(changed names, their changes)``.

        A change with ``Change.RESTART`` increments the settings' version, which restarts
        the search before its next generation.
        """
        changed = {p.name: _BY_NAME[p.name].plain(p.value)
                   for p in params if p.name in _BY_NAME}
        with self._lock:
            old = self._config
            diff = tuple(sorted(k for k, v in changed.items() if old.values.get(k) != v))
            if not diff:
                return (), Change(0)
            effects = Change(0)
            for name in diff:
                effects |= _BY_NAME[name].change
            values = dict(old.values, **{name: changed[name] for name in diff})
            version = old.settings.version + (1 if effects & Change.RESTART else 0)
            self._config = Config(MappingProxyType(values), online_settings(values, version))
        return diff, effects

    def set_outputs(self, node, generation: int, cost: float, validation_nrmse: float, kp,
                    kd) -> Dict[str, str]:
        """Set the ``identified.*`` outputs on ``node``; return the reasons of refused ones."""
        params = [
            Parameter('identified.generation', _T.INTEGER, int(generation)),
            Parameter('identified.cost', _T.DOUBLE, float(cost)),
            Parameter('identified.validation_nrmse', _T.DOUBLE, float(validation_nrmse)),
            Parameter('identified.kp', _T.DOUBLE_ARRAY, [float(v) for v in kp]),
            Parameter('identified.kd', _T.DOUBLE_ARRAY, [float(v) for v in kd]),
        ]
        self._internal.active = True
        try:
            results = node.set_parameters(params)
        finally:
            self._internal.active = False
        return {param.name: result.reason for param, result in zip(params, results)
                if not result.successful}

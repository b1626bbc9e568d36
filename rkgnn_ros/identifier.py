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
The ``identifier`` node: evolve an RKGNN model of the arm online while it moves.

Interface
---------
Subscribed (best effort, depth 100: matches best-effort and reliable publishers alike)
    ``joint_states`` (sensor_msgs/JointState): θ, θ̇ and, in case 'torque', τ (effort).
    ``joint_commands`` (sensor_msgs/JointState): θd (position), θ̇d (velocity).
    ``reference_trajectory`` (trajectory_msgs/JointTrajectory, optional): the plan.
Published
    ``~/model`` (std_msgs/String, reliable, transient local, depth 1): the model YAML
    (``RKGNNModel.to_yaml``) when the best improves, at most every
    ``model_publish_period`` s; at start too when ``model_file`` held a usable model.
    ``~/prediction`` (trajectory_msgs/JointTrajectory): see *Prediction* below.
    ``~/evolution`` (std_msgs/Float64MultiArray, layout label
    ``generation,best_cost,mean_cost,spread,evaluations,validation_nrmse,population_size``):
    once per generation, at most 20 Hz.
    ``/diagnostics`` (diagnostic_msgs/DiagnosticArray, 1 Hz): one status named after the
    node (``identifier``) with the state and one ``drops.<reason>`` entry per reason.
Services
    ``~/reset`` (std_srvs/Trigger): clear the buffer and restart the search.
    ``~/save_model`` (std_srvs/Trigger): write the published model to ``model_file``.
    ``~/pause`` (std_srvs/SetBool): True pauses the search, False resumes it.
Node parameters
    See ``config/identifier.yaml`` and the descriptors below (``ros2 param describe``).
    ``identified.*`` are outputs, set by the node as the model improves; sets from outside
    are rejected.

Input policy
------------
Every message is converted by :mod:`rkgnn_ros.conversions` and added to a
:class:`~rkgnn_ros.stream_buffer.StreamBuffer`; a rejection is counted per reason (see
``/diagnostics``) and logged at most once a second per topic and reason. A joint_states or
joint_commands sample without velocity (empty or NaN) is dropped as ``missing_velocity``:
velocities are never estimated here. In case 'torque' a state without effort is dropped as
``missing_effort``. Messages that arrive before the joints are known count as
``no_joints``. No callback raises: an unexpected exception counts as ``internal_error``.

Parameter policy
----------------
Types are static: a value of another type (an integer for a double, as ``ros2 param set
... es.sigma 1`` sends) is rejected by rclpy with its "Wrong parameter type" reason, and at
start (``--params-file``) the node refuses to start; write doubles with a decimal point.
Ranges are in the descriptors; open bounds and cross-parameter rules (``min_window <=
window``, ``prediction.horizon >= model_step``, the optimizer's own rules such as
``es.tournament_size <= es.population_size``) are checked by the on-set callback, whose
reasons name the parameter and its bound. ``es.population_size = 0`` (the algorithm's
default) is accepted at start only. An invalid value at start makes the node refuse to
start (exit code 1).

Changing ``case``, ``kp``, ``kd``, ``joints``, ``model_step``, ``substeps`` or
``network.*`` restarts the search (and, for ``joints``, ``case`` and ``model_step``,
clears the buffer); ``window`` and ``gap_threshold`` rebuild the buffer and keep the
search. ES settings are handed to the running optimizer between generations
(``update_settings``; a new population size keeps the best genome), ``es.algorithm`` swaps
the optimizer warm-started from the best genome, ``es.seed`` is used at the next (re)start.

Threads
-------
ROS callbacks run in the executor thread and only convert, buffer and publish; the two
streams, ``joint_states`` and ``joint_commands``, are the exception: their subscriptions are
in a callback group the executor never waits on, and an ingest thread takes what is queued
on them every millisecond (raw CDR, read by ``conversions.joint_state_cdr_to_arrays``),
under a lock that parameter changes and joint changes also take. A prediction
thread rolls the model out from the newest state when a prediction is due (the compiled
rollout releases the GIL; requests that arrive meanwhile collapse into one) and publishes
the JointTrajectory serialized directly (``conversions.serialize_joint_trajectory``). The
latency from the middleware's receipt of a state to the publish of its prediction is
reported in ``/diagnostics`` (``prediction_latency_p50_ms`` / ``_p99_ms`` over the newest
1000 predictions). Objects alive at start are frozen out of the cyclic garbage collector
(``gc.freeze``) and no QoS-event handlers are created, both to keep the executor thread
cheap. One worker thread (nice 19, stopped by an Event, joined before the node is
destroyed) owns the
:class:`~rkgnn_ros.core.fitting.identify.Evolution`. Before each generation it takes, under the
node's lock, one snapshot of the settings (an immutable mapping with version counters) and
of the flags (pause, reset), so a generation runs with one consistent configuration. The
training data is refreshed from the buffer at most once a second (``set_data``, a warm
start: the optimizer is kept). Validation (the newest ``validation_fraction`` of the
window, predicted open loop from its first state, θ-NRMSE) runs in the worker every few
generations and for every published model. An exception in the worker is logged with its
traceback, counted (``worker_error``), shown as state 'error', and the worker retries after
a back-off (0.5 s doubling to 10 s); after three in a row the search restarts.

Prediction
----------
From the newest accepted joint_states sample (header stamp copied, ``points[0]`` that
state exactly), the published model is rolled out over ``prediction.horizon`` s at
``model_step``. Inputs over the horizon: cases 'pd_gains' and 'unknown' follow the newest
``reference_trajectory`` if it has not ended at the start stamp
(``StreamBuffer.reference_at``: linear inside, first/last position with zero velocity
outside), else hold the latest joint_commands position with zero velocity; case 'torque'
see below. Published at ``prediction.rate`` Hz, and with ``prediction.on_state`` also on
each accepted joint_states sample (at most once per ``model_step``). A prediction with a
non-finite value is not published (counted as ``prediction_non_finite``).

Case 'torque' (measured effort): the future torque is the arm controller's answer to the
future state, so the node fits the controller's law τ = Kp (θd − θ) + Kd (θ̇d − θ̇) + c per
joint by least squares on the buffered effort paired with joint_commands
(:mod:`rkgnn_ros.core.fitting.controller`), at every data refresh. While that law explains the
torque (RMS residual below 10 % of the RMS torque, Kp > 0, Kd >= 0), the search runs in
closed loop (exactly a case-2 search with the fitted gains: the same genome, the rollout
driven by the commands) and predictions follow the reference in closed loop, like case 2;
``identified.kp`` / ``identified.kd`` are the fitted gains and the published model (still
case 'torque', the arm alone) records the law in its ``info``. The search restarts when
the law appears, stops explaining the torque, or its gains move by more than 10 %. Without
joint_commands, or with a controller that is not a PD law, the search fits the open-loop
rollout driven by the measured torque and predictions hold the latest measured torque.
"""

from collections import deque
from dataclasses import dataclass, replace
import gc
import math
import os
import re
import sys
import threading
import time
import traceback
from types import MappingProxyType
from typing import Dict, List, Mapping, Optional, Sequence, Tuple

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
import numpy as np
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                SetParametersResult)
import rclpy
from rclpy.callback_groups import CallbackGroup
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.exceptions import InvalidHandle, ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from rkgnn_ros.conversions import (joint_state_cdr_to_arrays, joint_state_to_arrays,
                                   joint_trajectory_to_arrays, make_float64_multiarray,
                                   parse_joint_state_cdr, Rejection, REJECTION_REASONS,
                                   serialize_joint_trajectory)
from rkgnn_ros.core.data import Dataset
from rkgnn_ros.core.fitting.controller import closed_loop_model, fit_pd_law, open_loop_model, PDLaw
from rkgnn_ros.core.fitting.identify import Evolution, normalize_case, nrmse, precompile
from rkgnn_ros.core.fitting.optimizers import CMAES, make_optimizer, OPTIMIZERS, PaperEA
from rkgnn_ros.core.model.files import remove_stale_temp_files
from rkgnn_ros.core.model.model import RKGNNModel
from rkgnn_ros.core.model.spec import CASES, INERTIA_MODES, NetworkSpec, VELOCITY_MODES
from rkgnn_ros.stream_buffer import DROP_REASONS, StreamBuffer
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, String
from std_srvs.srv import SetBool, Trigger
from trajectory_msgs.msg import JointTrajectory

__all__ = ['EVOLUTION_LABELS', 'ConfigurationError', 'IdentifierNode', 'main',
           'split_validation']

#: Field names of ``~/evolution`` (the layout label of its one dimension).
EVOLUTION_LABELS = ('generation', 'best_cost', 'mean_cost', 'spread', 'evaluations',
                    'validation_nrmse', 'population_size')

#: Drop reasons the node adds to the buffer's and the conversions' own.
NODE_REASONS = ('no_joints', 'internal_error', 'prediction_non_finite', 'worker_error')

DATA_REFRESH_S = 1.0        # at most one set_data per second
WAITING_REFRESH_S = 0.25    # while too little data is buffered, look again this often
MIN_SEGMENT_SAMPLES = 10    # shorter segments (training or validation) are left out
MIN_LAW_SAMPLES = 50        # case 'torque': paired samples before a controller law is fitted
MAX_LAW_FIT_RATIO = 0.1     # ... and its RMS residual must stay below this share of RMS τ
LAW_GAIN_RTOL = 0.1         # a refit moving the gains more than this restarts the search
VALIDATION_EVERY = 5        # generations between two validations of a changed best
EVOLUTION_MIN_PERIOD = 0.05  # ~/evolution at most 20 Hz
IDLE_WAIT_S = 0.05
# Equation-error warm start of a new search (see _warm_start).
WARM_START_S = 5.0
WARM_START_NFEV = 300
WARM_START_SIGMA = 0.05     # search spread around the warm start (genome units)
LATENCY_WINDOW = 1000       # predictions whose latency the diagnostics summarise
REWARM_GROWTH = 1.5         # the equation-error fit runs again when the data grew this much
# The worker yields the CPU to the executor (see _yield_to_callbacks).
WORKER_NICE = 19
GIL_SWITCH_INTERVAL_S = 0.0001
DRAIN_LIMIT = 100  # queued stream messages taken per callback without the executor
INGEST_PERIOD_S = 0.001  # the ingest thread takes the queued stream messages this often
BACKOFF_MIN_S = 0.5
BACKOFF_MAX_S = 10.0
MAX_CONSECUTIVE_ERRORS = 3
JOIN_TIMEOUT_S = 10.0
LOG_THROTTLE_S = 1.0

_T = Parameter.Type


class ConfigurationError(ValueError):
    """The parameters given at start are invalid: the node refuses to start."""


@dataclass(frozen=True)
class _Param:
    """One declared parameter: default, type, description and bounds."""

    name: str
    default: object
    ptype: Parameter.Type
    description: str
    lo: Optional[float] = None
    hi: Optional[float] = None
    lo_open: bool = False
    choices: Tuple[str, ...] = ()
    constraints: str = ''
    read_only: bool = False

    def bound_text(self) -> str:
        """Return the bound as text, e.g. ``in (0.0, 10.0]``."""
        if self.lo is None and self.hi is None:
            return ''
        if self.hi is None:
            return f'{">" if self.lo_open else ">="} {self.lo}'
        return f'in {"(" if self.lo_open else "["}{self.lo}, {self.hi}]'

    def descriptor(self) -> ParameterDescriptor:
        """Return the ParameterDescriptor rclpy enforces (type, closed range)."""
        extra = [self.constraints] if self.constraints else []
        if self.lo_open:
            extra.insert(0, f'> {self.lo}')
        if self.choices:
            extra.insert(0, 'one of ' + ', '.join(self.choices))
        desc = ParameterDescriptor(description=self.description,
                                   additional_constraints='; '.join(extra),
                                   read_only=self.read_only)
        if self.ptype == _T.DOUBLE and self.lo is not None and self.hi is not None:
            desc.floating_point_range = [FloatingPointRange(
                from_value=float(self.lo), to_value=float(self.hi), step=0.0)]
        elif self.ptype == _T.INTEGER and self.lo is not None and self.hi is not None:
            desc.integer_range = [IntegerRange(
                from_value=int(self.lo), to_value=int(self.hi), step=1)]
        return desc


_REC = NetworkSpec.recommended(1, 'torque')
_RESTARTS = 'Changing it restarts the search.'
PARAMETERS = (
    _Param('case', 'torque', _T.STRING,
           "Identification case: 'torque' (1, measured torque), 'pd_gains' (2, known PD "
           "gains kp, kd) or 'unknown' (3, the controller is identified too); 1/2/3 "
           'accepted. ' + _RESTARTS, choices=CASES),
    _Param('kp', (), _T.DOUBLE_ARRAY,
           "Known proportional gains per joint (case 'pd_gains'). " + _RESTARTS, lo=0.0),
    _Param('kd', (), _T.DOUBLE_ARRAY,
           "Known derivative gains per joint (case 'pd_gains'). " + _RESTARTS, lo=0.0),
    _Param('joints', (), _T.STRING_ARRAY,
           'Joint names, in model column order; empty: the names of the first joint_states '
           'message (or of the loaded model_file). ' + _RESTARTS),
    _Param('window', 20.0, _T.DOUBLE,
           'Seconds of newest data the search uses (training plus validation).', 1.0, 600.0),
    _Param('min_window', 5.0, _T.DOUBLE,
           'Seconds of buffered data needed before generations run.', 0.1, 600.0,
           constraints='<= window'),
    _Param('model_step', 0.01, _T.DOUBLE,
           'Grid step (s) of the resampled data, the model and ~/prediction. ' + _RESTARTS,
           0.001, 0.1),
    _Param('substeps', 0, _T.INTEGER,
           'RKG steps per model_step (0: automatic). ' + _RESTARTS, 0, 64),
    _Param('gap_threshold', 0.1, _T.DOUBLE,
           'Longer intervals (s) between samples split the data into segments.',
           0.001, 10.0),
    _Param('max_rate_hz', 2000.0, _T.DOUBLE,
           'Highest sample rate (Hz) kept per stream: samples closer than 1/max_rate_hz are '
           'decimated (counted as rate_limited), which bounds the buffer memory whatever '
           'the input rate. Read-only: set it at start (params file or --ros-args -p).',
           1.0, 100000.0, read_only=True),
    _Param('validation_fraction', 0.2, _T.DOUBLE,
           'Newest fraction of the window held out for the validation NRMSE (0: none).',
           0.0, 0.5),
    _Param('stale_timeout', 1.0, _T.DOUBLE,
           'Seconds without an accepted joint_states (and, in cases pd_gains/unknown, '
           'joint_commands) sample after which the search pauses (state stale).',
           0.05, 60.0),
    _Param('model_publish_period', 2.0, _T.DOUBLE,
           'Minimum seconds between two ~/model messages.', 0.0, 3600.0),
    _Param('network.theta_units', _REC.theta_units, _T.INTEGER,
           'Gaussian RBF units over theta (inertia, Coriolis, gravity). ' + _RESTARTS, 0, 32),
    _Param('network.torque_units', _REC.torque_units, _T.INTEGER,
           "RBF units of each P and D torque sub-network (case 'unknown'). " + _RESTARTS,
           0, 32),
    _Param('network.inertia', _REC.inertia, _T.STRING,
           "'cholesky' (M = L L^T + eps I, positive definite) or 'penalty' (the paper's). "
           + _RESTARTS, choices=INERTIA_MODES),
    _Param('network.velocity', _REC.velocity, _T.STRING,
           "'christoffel' (Coriolis and centrifugal terms from M, energy-consistent) or "
           "'learned' (the paper's own RBF outputs). " + _RESTARTS, choices=VELOCITY_MODES),
    _Param('network.bias', _REC.bias, _T.BOOL,
           'Constant term on every theta-dependent output. ' + _RESTARTS),
    _Param('network.friction', _REC.friction, _T.BOOL,
           'Viscous and Coulomb friction per joint. ' + _RESTARTS),
    _Param('network.torque_linear', _REC.torque_linear, _T.BOOL,
           "Linear P and D gains beside the torque RBF networks (case 'unknown'). "
           + _RESTARTS),
    _Param('es.algorithm', 'cmaes', _T.STRING,
           "Optimizer: 'cmaes', 'sep-cmaes' or 'paper' (the paper's EA). A change swaps the "
           'optimizer between generations, warm-started from the best genome.',
           choices=OPTIMIZERS),
    _Param('es.population_size', 0, _T.INTEGER,
           "Candidates per generation; 0 (at start only): the algorithm's default "
           '(cmaes: 4 + 3 ln N, paper: 100). Applied between generations.', 0, 100000,
           constraints='0 (at start) or >= 2; >= es.tournament_size (paper)'),
    _Param('es.tournament_size', PaperEA.DEFAULTS['tournament_size'], _T.INTEGER,
           'paper: contestants per tournament.', 1, 100000,
           constraints='<= es.population_size (paper)'),
    _Param('es.crossover_rate', PaperEA.DEFAULTS['crossover_rate'], _T.DOUBLE,
           'paper: probability that a parent pair is replaced by BLX-alpha children.',
           0.0, 1.0),
    _Param('es.mutation_rate', PaperEA.DEFAULTS['mutation_rate'], _T.DOUBLE,
           'paper: fraction of offspring mutated.', 0.0, 1.0),
    _Param('es.sigma', CMAES.DEFAULTS['sigma'], _T.DOUBLE,
           'Step size (cmaes) or initial mutation spread (paper), in genome units.',
           0.0, 10.0, lo_open=True),
    _Param('es.sigma_min', PaperEA.DEFAULTS['sigma_min'], _T.DOUBLE,
           'paper: floor of the mutation spread.', 0.0, 10.0,
           constraints='<= es.sigma (paper)'),
    _Param('es.max_generations', 0, _T.INTEGER,
           'Generations per search before it stops (0: forever).', 0, 1_000_000_000),
    _Param('es.seed', 0, _T.INTEGER,
           "Seed of the optimizer's random generator, used when a search (re)starts.",
           0, 2 ** 31 - 1),
    _Param('prediction.horizon', 2.0, _T.DOUBLE,
           'Seconds predicted on ~/prediction.', 0.01, 60.0, constraints='>= model_step'),
    _Param('prediction.rate', 10.0, _T.DOUBLE,
           'Rate (Hz) of ~/prediction (0: only on_state).', 0.0, 1000.0),
    _Param('prediction.on_state', False, _T.BOOL,
           'Also predict on every accepted joint_states sample (at most once per '
           'model_step).'),
    _Param('model_file', '', _T.STRING,
           'Model YAML: loaded at start if present (published, start genome), written '
           'atomically on ~/save_model and at shutdown; empty: no file.'),
)
OUTPUTS = (
    _Param('identified.generation', 0, _T.INTEGER,
           'Output: generation of the published model.'),
    _Param('identified.cost', math.nan, _T.DOUBLE,
           'Output: training cost of the published model.'),
    _Param('identified.validation_nrmse', math.nan, _T.DOUBLE,
           'Output: validation theta-NRMSE of the published model.'),
    _Param('identified.kp', (), _T.DOUBLE_ARRAY,
           "Output: the model's PD gains linearised at zero error (cases 2-3); case 1: the "
           'gains of the controller law fitted from effort and joint_commands.'),
    _Param('identified.kd', (), _T.DOUBLE_ARRAY,
           "Output: the model's derivative gains linearised at zero error (cases 2-3); "
           'case 1: the fitted law.'),
)
_BY_NAME = {p.name: p for p in PARAMETERS}
_OUTPUT_NAMES = frozenset(p.name for p in OUTPUTS)
STRUCTURAL = frozenset({'case', 'kp', 'kd', 'joints', 'model_step', 'substeps'} |
                       {p.name for p in PARAMETERS if p.name.startswith('network.')})
BUFFER_KEYS = frozenset({'case', 'joints', 'model_step', 'window', 'gap_threshold'})
ES_KEYS = frozenset({'es.population_size', 'es.tournament_size', 'es.crossover_rate',
                     'es.mutation_rate', 'es.sigma', 'es.sigma_min'})
_ES_NAMES = ('population_size', 'tournament_size', 'crossover_rate', 'mutation_rate',
             'sigma_min', 'sigma', 'n_elite')
_NETWORK_NAMES = ('theta_units', 'torque_units', 'inertia', 'velocity', 'bias', 'friction',
                  'torque_linear')


# ---------------------------------------------------------------------- pure helpers


def _plain(ptype, value):
    """Return a parameter value as plain immutable Python (tuples for arrays)."""
    if ptype == _T.DOUBLE:
        return float(value)
    if ptype == _T.INTEGER:
        return int(value)
    if ptype == _T.BOOL:
        return bool(value)
    if ptype == _T.STRING:
        return str(value)
    if ptype == _T.DOUBLE_ARRAY:
        return tuple(float(v) for v in value)
    if ptype == _T.STRING_ARRAY:
        return tuple(str(v) for v in value)
    return value


def _prefixed(text: str, prefix: str, names: Sequence[str]) -> str:
    """Prefix the setting names in a core error message with their parameter group."""
    for name in sorted(names, key=len, reverse=True):
        text = re.sub(rf'(?<![\w.]){re.escape(name)}\b', prefix + name, text)
    return text


def optimizer_settings(values: Mapping) -> Tuple[str, dict]:
    """Return ``(algorithm, settings)`` for :func:`make_optimizer` from parameter values."""
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


def network_spec(values: Mapping, n_joints: int) -> NetworkSpec:
    """
    Return the NetworkSpec the parameters describe for ``n_joints`` joints.

    Settings without a parameter (e.g. the inertia floor) keep their values of
    ``NetworkSpec.recommended``.
    """
    return replace(
        NetworkSpec.recommended(int(n_joints), normalize_case(values['case'])),
        theta_units=values['network.theta_units'],
        torque_units=values['network.torque_units'], inertia=values['network.inertia'],
        velocity=values['network.velocity'], bias=values['network.bias'],
        friction=values['network.friction'], torque_linear=values['network.torque_linear'])


_TYPE_NAMES = {_T.DOUBLE: 'double', _T.INTEGER: 'integer', _T.BOOL: 'bool',
               _T.STRING: 'string', _T.DOUBLE_ARRAY: 'double array',
               _T.STRING_ARRAY: 'string array'}


def _type_ok(ptype, value) -> bool:
    if ptype == _T.DOUBLE:
        return isinstance(value, float)
    if ptype == _T.INTEGER:
        return isinstance(value, int) and not isinstance(value, bool)
    if ptype == _T.BOOL:
        return isinstance(value, bool)
    if ptype == _T.STRING:
        return isinstance(value, str)
    if ptype == _T.DOUBLE_ARRAY:
        return not isinstance(value, (str, bytes)) and all(
            isinstance(v, float) for v in value)
    if ptype == _T.STRING_ARRAY:
        return not isinstance(value, (str, bytes)) and all(isinstance(v, str) for v in value)
    return False


def _check_one(spec: _Param, value, at_start: bool, previous) -> Optional[str]:
    """Return why ``value`` is invalid for ``spec`` (None if valid)."""
    name = spec.name
    if not _type_ok(spec.ptype, value):
        return (f'{name} must be a {_TYPE_NAMES.get(spec.ptype, spec.ptype)}, got '
                f'{value!r} ({type(value).__name__})')
    if spec.ptype == _T.DOUBLE:
        lo_bad = spec.lo is not None and (value <= spec.lo if spec.lo_open else value < spec.lo)
        hi_bad = spec.hi is not None and value > spec.hi
        if not math.isfinite(value) or lo_bad or hi_bad:
            return f'{name} must be a finite number {spec.bound_text()}, got {value!r}'
    elif spec.ptype == _T.INTEGER:
        if name == 'es.population_size' and (
                value == 1 or (value == 0 and not at_start and previous != 0)):
            return (f"es.population_size must be >= 2 (0, the algorithm's default, is "
                    f'accepted only at start), got {value}')
        if (spec.lo is not None and value < spec.lo) or (spec.hi is not None
                                                         and value > spec.hi):
            return f'{name} must be an integer {spec.bound_text()}, got {value}'
    elif spec.ptype == _T.STRING and spec.choices:
        if name == 'case':
            try:
                normalize_case(value)
            except ValueError:
                return f'case must be one of {", ".join(CASES)} (or 1, 2, 3), got {value!r}'
        elif value not in spec.choices:
            return f'{name} must be one of {", ".join(spec.choices)}, got {value!r}'
    elif spec.ptype == _T.DOUBLE_ARRAY:
        if not all(math.isfinite(v) and v >= spec.lo for v in value):
            return f'{name} must hold finite values >= {spec.lo}, got {list(value)}'
    elif spec.ptype == _T.STRING_ARRAY:
        if any(not v for v in value) or len(set(value)) != len(value):
            return f'{name} must hold non-empty, distinct names, got {list(value)}'
    return None


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
    if values['prediction.horizon'] < values['model_step']:
        return (f"prediction.horizon ({values['prediction.horizon']}) must be >= model_step "
                f"({values['model_step']})")
    joints = values['joints']
    try:
        network_spec(values, max(1, len(joints)))
    except ValueError as exc:
        return _prefixed(str(exc), 'network.', _NETWORK_NAMES)
    if normalize_case(values['case']) == 'pd_gains':
        kp, kd = values['kp'], values['kd']
        if not kp or len(kp) != len(kd):
            return (f"case 'pd_gains' needs kp and kd with one value per joint, got "
                    f'{len(kp)} and {len(kd)} values')
        if joints and len(kp) != len(joints):
            return f'kp and kd have {len(kp)} values for {len(joints)} joints'
    algorithm, settings = optimizer_settings(values)
    cls = PaperEA if algorithm == 'paper' else CMAES
    try:
        cls.validate_settings(**settings)
    except ValueError as exc:
        return _prefixed(str(exc), 'es.', _ES_NAMES)
    return None


def split_validation(segments: Sequence[Dataset], fraction: float,
                     min_samples: int = MIN_SEGMENT_SAMPLES
                     ) -> Tuple[List[Dataset], List[Dataset], float]:
    """
    Hold out the newest ``fraction`` of the data for validation.

    Parameters
    ----------
    segments : sequence of Dataset
        Gap-free segments, oldest first, on one grid.
    fraction : float
        Share of the total duration to hold out (0: none).
    min_samples : int
        A segment is split only if both parts keep this many samples; otherwise it stays
        whole in the training set.

    Returns
    -------
    (train, validation, seconds)
        Both lists oldest first; ``seconds`` is the total duration of ``segments``. A
        split segment's parts share the boundary sample.

    """
    seconds = float(sum(seg.duration for seg in segments))
    hold = fraction * seconds
    train: List[Dataset] = []
    validation: List[Dataset] = []
    for seg in reversed(segments):
        if hold <= 1e-9:
            train.append(seg)
        elif seg.duration <= hold + 1e-9:
            validation.append(seg)
            hold -= seg.duration
        else:
            k = seg.n_samples - 1 - int(round(hold / seg.dt))  # first validation sample
            hold = 0.0
            if seg.n_samples - k >= min_samples and k + 1 >= min_samples:
                train.append(seg.slice(0, k + 1))
                validation.append(seg.slice(k, seg.n_samples))
            else:
                train.append(seg)
    return train[::-1], validation[::-1], seconds


@dataclass(frozen=True)
class _Config:
    """One consistent snapshot of the parameters, with change counters."""

    values: Mapping
    structural_version: int = 0
    es_version: int = 0

    def __getitem__(self, name):
        return self.values[name]

    @property
    def case(self) -> str:
        return normalize_case(self.values['case'])


def _finite_or_nan(value) -> float:
    value = float(value)
    return value if math.isfinite(value) else math.nan


# ---------------------------------------------------------------------- the node


class IdentifierNode(Node):
    """
    Online RKGNN identification: buffers joint streams, evolves a model, publishes it.

    Parameters
    ----------
    node_name : str
        Node name (default ``identifier``).
    **kwargs
        Passed to :class:`rclpy.node.Node` (``context``, ``parameter_overrides``, ...).

    Raises
    ------
    ConfigurationError, rclpy.exceptions.ParameterException
        An invalid parameter given at start (the message names it).

    """

    def __init__(self, node_name: str = 'identifier', **kwargs):
        super().__init__(node_name, **kwargs)
        # compile every kernel now (numba holds the GIL while compiling): never in the worker
        seconds = precompile()
        self.get_logger().info(f'compiled kernels ready in {seconds:.1f} s'
                               + (' (first run: compiled and cached)' if seconds > 5 else ''))
        self._lock = threading.RLock()
        # held while a stream message is handled, and while the joints, the buffer or the
        # settings they depend on change (executor thread): the ingest thread never sees
        # them half changed
        self._ingest_lock = threading.RLock()
        self._tls = threading.local()
        self._values = self._declare_parameters()
        reason = check_parameters(self._values, list(self._values), at_start=True)
        if reason:
            raise ConfigurationError(reason)
        self._cfg = _Config(MappingProxyType(dict(self._values)))

        # state shared with the callbacks (guarded by _lock where not a single reference)
        self._joints: Optional[Tuple[str, ...]] = None
        self._buffer: Optional[StreamBuffer] = None
        self._retired_drops: Dict[str, int] = {}
        self._extra_drops: Dict[str, int] = {}
        self._latest_state = None    # ((sec, nanosec), t, θ, θ̇, τ or None, receipt ns)
        self._latest_command = None  # θd (n,)
        self._reference_end: Optional[float] = None
        self._last_rx: Dict[str, float] = {}
        self._log_times: Dict[Tuple[str, str], float] = {}
        self._last_state_prediction = -math.inf
        self._paused = False
        self._reset_request = False
        self._model: Optional[RKGNNModel] = None
        # case 'torque': the arm's controller law fitted from torque + commands, and the
        # published model closed with it (prediction along the reference)
        self._law: Optional[PDLaw] = None
        self._closed = None  # (model, closed-loop model, θd shift (n,))
        self._start_model: Optional[RKGNNModel] = None
        self._outputs: Optional[dict] = None
        self._status = {'state': 'waiting for data', 'detail': 'no joint_states yet',
                        'generation': 0, 'best_cost': math.nan, 'validation_nrmse': math.nan,
                        'generations_per_s': 0.0, 'population_size': 0}
        self._stop = threading.Event()
        self._kernels_ready = threading.Event()
        self._prediction_wanted = threading.Event()
        self._latencies: deque = deque(maxlen=LATENCY_WINDOW)  # ms, newest predictions
        self._last_predicted_ns = None  # receipt time of the state last predicted from

        # worker-owned search state
        self._evo: Optional[Evolution] = None
        self._evo_version = -1
        self._evo_law: Optional[PDLaw] = None  # case 'torque': the law a closed-loop search uses
        self._warm_seconds = math.inf  # seconds of data at the last equation-error fit
        self._algorithm = ''
        self._generation = 0
        self._evaluations = 0
        self._gen_times: deque = deque(maxlen=20)
        self._validation: List[Dataset] = []
        self._data_version = 0
        self._last_refresh = -math.inf
        self._val_nrmse = math.nan
        self._val_key = None
        self._last_val_generation = -VALIDATION_EVERY
        self._published_genome = None
        self._last_model_pub = -math.inf
        self._last_evolution_pub = -math.inf
        self._stale_warned = False
        self._had_finite = False

        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.add_post_set_parameters_callback(self._after_set_parameters)

        stream_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                                reliability=ReliabilityPolicy.BEST_EFFORT,
                                durability=DurabilityPolicy.VOLATILE)
        model_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                               reliability=ReliabilityPolicy.RELIABLE,
                               durability=DurabilityPolicy.TRANSIENT_LOCAL)
        # No QoS-event handlers: rclpy adds each one to the wait set of every spin, and at
        # 2000 callbacks/s that Python work dominated the executor thread. Our subscriptions
        # are best effort and our publishers volatile or transient-local reliable, so the
        # incompatible-QoS events they would log cannot arise with usual peers.
        pub_events = PublisherEventCallbacks(use_default_callbacks=False)
        sub_events = SubscriptionEventCallbacks(use_default_callbacks=False)
        self._model_pub = self.create_publisher(String, '~/model', model_qos,
                                                event_callbacks=pub_events)
        self._prediction_pub = self.create_publisher(JointTrajectory, '~/prediction', 10,
                                                     event_callbacks=pub_events)
        self._evolution_pub = self.create_publisher(Float64MultiArray, '~/evolution', 10,
                                                    event_callbacks=pub_events)
        self._diagnostics_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10,
                                                      event_callbacks=pub_events)
        # the two 1 kHz-capable streams: taken as CDR bytes and read without building
        # message objects (conversions.joint_state_cdr_to_arrays), by the ingest thread
        # (_run_ingest), never by the executor (_PolledGroup)
        polled = _PolledGroup()
        self._state_sub = self.create_subscription(
            JointState, 'joint_states', self._on_state, stream_qos, callback_group=polled,
            event_callbacks=sub_events, raw=True)
        self._command_sub = self.create_subscription(
            JointState, 'joint_commands', self._on_command, stream_qos, callback_group=polled,
            event_callbacks=sub_events, raw=True)
        self.create_subscription(JointTrajectory, 'reference_trajectory', self._on_reference,
                                 stream_qos, event_callbacks=sub_events)
        self.create_service(Trigger, '~/reset', self._on_reset)
        self.create_service(Trigger, '~/save_model', self._on_save_model)
        self.create_service(SetBool, '~/pause', self._on_pause)
        self._prediction_timer = None
        self._make_prediction_timer()
        self.create_timer(1.0, self._publish_diagnostics)
        self.create_timer(0.5, self._apply_outputs)

        if self._values['joints']:
            self._set_joints(self._values['joints'], 'the joints parameter')
        self._load_model_file()
        self._worker = threading.Thread(target=self._run, name='rkgnn_identifier',
                                        daemon=True)
        self._worker.start()
        self._predictor = threading.Thread(target=self._run_predictions,
                                           name='rkgnn_prediction', daemon=True)
        self._predictor.start()
        self._ingest = threading.Thread(target=self._run_ingest, name='rkgnn_ingest',
                                        daemon=True)
        self._ingest.start()
        # everything built so far (modules, compiled kernels, rclpy) lives as long as the
        # node: keep it out of the cyclic garbage collector, whose full passes over it held
        # the GIL for tens of milliseconds and stalled the 1 kHz callbacks
        gc.collect()
        gc.freeze()

    # ------------------------------------------------------------------ parameters

    def _declare_parameters(self) -> Dict[str, object]:
        values = {}
        for spec in PARAMETERS + OUTPUTS:
            output = spec.name in _OUTPUT_NAMES
            if spec.ptype in (_T.DOUBLE_ARRAY, _T.STRING_ARRAY):
                param = self.declare_parameter(spec.name, spec.ptype, spec.descriptor(),
                                               ignore_override=output)
                if param.type_ == _T.NOT_SET:  # no value given, or `[]` in a params file
                    self.set_parameters([Parameter(spec.name, spec.ptype, [])])
            else:
                self.declare_parameter(spec.name, spec.default, spec.descriptor(),
                                       ignore_override=output)
            if not output:
                values[spec.name] = _plain(spec.ptype, self.get_parameter(spec.name).value)
        return values

    def _on_set_parameters(self, params) -> SetParametersResult:
        """Validate a set of parameters; never raises (reasons name the parameter)."""
        try:
            internal = getattr(self._tls, 'internal', False)
            with self._lock:
                current = dict(self._values)
            values = dict(current)
            changed = []
            for param in params:
                name = param.name
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

    def _after_set_parameters(self, params) -> None:
        """Hand accepted parameters to the worker and rebuild what depends on them."""
        with self._ingest_lock:  # a stream message is handled before or after, not during
            self._apply_parameters(params)

    def _apply_parameters(self, params) -> None:
        try:
            changed = {p.name: _plain(_BY_NAME[p.name].ptype, p.value)
                       for p in params if p.name in _BY_NAME}
            with self._lock:
                diff = {k for k, v in changed.items() if self._values.get(k) != v}
                if not diff:
                    return
                self._values.update(changed)
                old = self._cfg
                self._cfg = _Config(
                    MappingProxyType(dict(self._values)),
                    old.structural_version + (1 if diff & STRUCTURAL else 0),
                    old.es_version + (1 if diff & ES_KEYS else 0))
            notes = []
            if diff & STRUCTURAL:
                notes.append('structural: the search restarts before the next generation')
            if diff & ES_KEYS or 'es.algorithm' in diff:
                notes.append('applied between generations')
            self.get_logger().info(
                f'parameters changed: {", ".join(sorted(diff))}'
                + (f' ({"; ".join(notes)})' if notes else ''))
            if diff & BUFFER_KEYS:
                joints = self._values['joints']
                if 'joints' in diff:
                    self._set_joints(joints or None, 'the joints parameter')
                else:
                    self._set_joints(self._joints, 'a parameter change')
            if 'prediction.rate' in diff:
                self._make_prediction_timer()
        except Exception:  # noqa: B902 - a callback must never raise
            self._internal_error('parameters')

    def _apply_outputs(self) -> None:
        """Timer: copy the worker's results into the identified.* parameters."""
        try:
            with self._lock:
                outputs, self._outputs = self._outputs, None
            if outputs is None:
                return
            params = [
                Parameter('identified.generation', _T.INTEGER, int(outputs['generation'])),
                Parameter('identified.cost', _T.DOUBLE, float(outputs['cost'])),
                Parameter('identified.validation_nrmse', _T.DOUBLE,
                          float(outputs['validation_nrmse'])),
                Parameter('identified.kp', _T.DOUBLE_ARRAY, list(outputs['kp'])),
                Parameter('identified.kd', _T.DOUBLE_ARRAY, list(outputs['kd'])),
            ]
            self._tls.internal = True
            try:
                results = self.set_parameters(params)
            finally:
                self._tls.internal = False
            for param, result in zip(params, results):
                if not result.successful:
                    self.get_logger().warning(
                        f'cannot update {param.name}: {result.reason}',
                        throttle_duration_sec=LOG_THROTTLE_S)
        except Exception:  # noqa: B902 - a callback must never raise
            self._internal_error('parameters')

    # ------------------------------------------------------------------ buffer, counters

    def _set_joints(self, joints, source: str) -> None:
        """Adopt ``joints`` (None: learn them from joint_states) and rebuild the buffer."""
        with self._ingest_lock:
            self._set_joints_locked(joints, source)

    def _set_joints_locked(self, joints, source: str) -> None:
        cfg = self._cfg
        buffer = None
        joints = tuple(joints) if joints else None
        if joints is not None:
            buffer = StreamBuffer(joints, cfg['model_step'], cfg['window'],
                                  cfg['gap_threshold'], need_tau=cfg.case == 'torque',
                                  need_desired=cfg.case != 'torque',
                                  max_rate_hz=cfg['max_rate_hz'])
        with self._lock:
            old = self._buffer
            if old is not None:
                for reason, count in old.counters.items():
                    self._retired_drops[reason] = self._retired_drops.get(reason, 0) + count
            changed = joints != self._joints
            self._joints = joints
            self._buffer = buffer
            self._latest_state = None
            self._latest_command = None
            self._reference_end = None
            self._last_rx = {}
        if changed:
            if joints is None:
                self.get_logger().info('joints: taken from the next joint_states message')
            else:
                self.get_logger().info(f'joints from {source}: {list(joints)}')

    def _count(self, stream: str, reason: str) -> None:
        buffer = self._buffer
        if buffer is not None:
            buffer.count_drop(stream, reason)
        else:
            with self._lock:
                self._extra_drops[reason] = self._extra_drops.get(reason, 0) + 1

    def drop_counts(self) -> Dict[str, int]:
        """Return the drops per reason since start (every stream, every buffer)."""
        counts = dict.fromkeys(REJECTION_REASONS + DROP_REASONS + NODE_REASONS, 0)
        buffer = self._buffer
        live = buffer.counters if buffer is not None else {}
        with self._lock:
            for source in (self._retired_drops, self._extra_drops, live):
                for reason, count in source.items():
                    counts[reason] = counts.get(reason, 0) + count
        return counts

    def _log_drop(self, topic: str, reason: str, text: str) -> None:
        """
        Log a drop at most once a second per topic and reason.

        rclpy's ``throttle_duration_sec`` throttles per call site, which would hide every
        reason but the first one seen.
        """
        now = time.monotonic()
        key = (topic, reason)
        if now - self._log_times.get(key, -math.inf) >= LOG_THROTTLE_S:
            self._log_times[key] = now
            self.get_logger().warning(f'{topic}: dropped a message ({reason}): {text}')

    def _reject(self, topic: str, stream: str, reason: str, text: str) -> None:
        self._count(stream, reason)
        self._log_drop(topic, reason, text)

    def _internal_error(self, where: str) -> None:
        if not self.context.ok():
            return  # shutting down (SIGINT): a publish that fails now is not an error
        self._count('node', 'internal_error')
        self._log_drop(where, 'internal_error',
                       f'unexpected error (counted as internal_error)\n{traceback.format_exc()}')

    # ------------------------------------------------------------------ subscriptions

    def _run_ingest(self) -> None:
        """
        Ingest thread: every INGEST_PERIOD_S, take what is queued on the two streams.

        Waking rclpy's executor for every message cost more than handling the message: at
        2 x 1 kHz the executor thread used about 55 % of a core, 58 % of it outside the
        message handlers, in the executor's own Python work for each wake (building the
        wait set; measured with thread CPU clocks).
        The streams' subscriptions are in a callback group the executor never waits on;
        this thread takes their messages (the DDS history keeps up to 100 per stream in
        between), at the cost of at most INGEST_PERIOD_S added to a state's latency.
        """
        while not self._stop.wait(INGEST_PERIOD_S):
            for sub, handle, topic in ((self._state_sub, self._handle_state, 'joint_states'),
                                       (self._command_sub, self._handle_command,
                                        'joint_commands')):
                try:
                    self._handle_queued(sub, handle)
                except Exception:  # noqa: B902 - the thread must survive
                    if self._stop.is_set() or not self.context.ok():
                        return
                    self._internal_error(topic)

    def _handle_queued(self, sub, handle) -> None:
        """Pass every message queued on ``sub`` (at most DRAIN_LIMIT) to ``handle``."""
        for raw, info in self._drain(sub):
            handle(raw, _received_ns(info))

    def _on_state(self, raw: bytes, info) -> None:
        """
        Handle one joint_states message as rclpy would deliver it, and those queued behind.

        Not called by the executor (the ingest thread takes this stream); the entry point
        for feeding the node directly.
        """
        try:
            self._handle_state(raw, _received_ns(info))
            self._handle_queued(self._state_sub, self._handle_state)
        except Exception:  # noqa: B902 - a callback must never raise
            self._internal_error('joint_states')

    @staticmethod
    def _drain(sub):
        """
        Yield the ``(message, info)`` pairs already queued on ``sub``, at most DRAIN_LIMIT.

        Taken straight from the subscription's handle, without an executor (the ingest
        thread's way of reading the two streams).
        """
        for _ in range(DRAIN_LIMIT):
            try:
                with sub.handle:
                    taken = sub.handle.take_message(sub.msg_type, sub.raw)
            except InvalidHandle:  # destroyed at shutdown
                return
            if taken is None:
                return
            yield taken

    @staticmethod
    def _joint_sample(raw: bytes, joints, need_effort: bool):
        """Read a raw JointState: the CDR fast path, else rclpy's deserialization."""
        sample = joint_state_cdr_to_arrays(raw, joints, need_velocity=True,
                                           need_effort=need_effort)
        if sample is None:  # not plain CDR we read: let rclpy decide what it is
            try:
                msg = deserialize_message(raw, JointState)
            except Exception as error:  # noqa: B902 - bad bytes are bad input, not a fault
                return Rejection('malformed', f'cannot read JointState: {error!r}')
            sample = joint_state_to_arrays(msg, joints, need_velocity=True,
                                           need_effort=need_effort)
        return sample

    @staticmethod
    def _message_names(raw: bytes):
        """Return the joint names of a raw JointState, or None if it has none readable."""
        try:
            parsed = parse_joint_state_cdr(raw)
            if parsed is not None:
                return parsed[2]
            return tuple(deserialize_message(raw, JointState).name)
        except Exception:  # noqa: B902 - the sample's own reading reports why
            return None

    def _handle_state(self, raw: bytes, received_ns: int) -> None:
        with self._ingest_lock:
            self._handle_state_locked(raw, received_ns)

    def _handle_state_locked(self, raw: bytes, received_ns: int) -> None:
        cfg = self._cfg
        need_tau = cfg.case == 'torque'
        joints = self._joints
        if joints is None:
            names = self._message_names(raw) or ()
            sample = self._joint_sample(raw, names, need_tau)
            if not sample.ok:
                self._reject('joint_states', 'state', sample.reason, sample.message)
                return
            self._set_joints(names, 'the first joint_states message')
            joints = self._joints
        sample = self._joint_sample(raw, joints, need_tau)
        if not sample.ok:
            self._reject('joint_states', 'state', sample.reason, sample.message)
            return
        buffer = self._buffer
        result = buffer.add_state(sample.stamp, sample.position, sample.velocity,
                                  sample.effort if need_tau else None)
        if result.clock_jump:
            self.get_logger().warning(
                f'joint_states: the clock jumped (stamp {sample.stamp:.3f} s): buffered '
                'data cleared, identification continues on the new timeline',
                throttle_duration_sec=LOG_THROTTLE_S)
        if not result.accepted:
            self._log_drop('joint_states', result.reason,
                           f'stamp {sample.stamp:.6f} s rejected by the buffer')
            return
        self._latest_state = (sample.sec_nanosec, sample.stamp, sample.position,
                              sample.velocity, sample.effort, received_ns)
        self._last_rx['state'] = time.monotonic()
        if cfg['prediction.on_state']:
            now = time.monotonic()
            if now - self._last_state_prediction >= cfg['model_step']:
                self._last_state_prediction = now
                self._prediction_wanted.set()

    def _on_command(self, raw: bytes) -> None:
        """Handle one joint_commands message and those queued behind (see _on_state)."""
        try:
            self._handle_command(raw)
            self._handle_queued(self._command_sub, self._handle_command)
        except Exception:  # noqa: B902 - a callback must never raise
            self._internal_error('joint_commands')

    def _handle_command(self, raw: bytes, received_ns: int = 0) -> None:
        with self._ingest_lock:
            self._handle_command_locked(raw)

    def _handle_command_locked(self, raw: bytes) -> None:
        joints = self._joints
        if joints is None:
            self._reject('joint_commands', 'command', 'no_joints',
                         'joints not known yet (waiting for joint_states)')
            return
        sample = self._joint_sample(raw, joints, False)
        if not sample.ok:
            self._reject('joint_commands', 'command', sample.reason, sample.message)
            return
        result = self._buffer.add_command(sample.stamp, sample.position, sample.velocity)
        if not result.accepted:
            self._log_drop('joint_commands', result.reason,
                           f'stamp {sample.stamp:.6f} s rejected by the buffer')
            return
        self._latest_command = sample.position
        self._last_rx['command'] = time.monotonic()

    def _on_reference(self, msg: JointTrajectory) -> None:
        try:
            joints = self._joints
            if joints is None:
                self._reject('reference_trajectory', 'reference', 'no_joints',
                             'joints not known yet (waiting for joint_states)')
                return
            now = self.get_clock().now().nanoseconds * 1e-9
            sample = joint_trajectory_to_arrays(msg, joints, now=now)
            if not sample.ok:
                self._reject('reference_trajectory', 'reference', sample.reason,
                             sample.message)
                return
            result = self._buffer.add_reference(sample.t0, sample.times, sample.positions,
                                                sample.velocities)
            if not result.accepted:
                self._log_drop('reference_trajectory', result.reason,
                               'rejected by the buffer')
                return
            self._reference_end = sample.t0 + float(sample.times[-1])
        except Exception:  # noqa: B902 - a callback must never raise
            self._internal_error('reference_trajectory')

    # ------------------------------------------------------------------ prediction

    def _make_prediction_timer(self) -> None:
        if self._prediction_timer is not None:
            self.destroy_timer(self._prediction_timer)
            self._prediction_timer = None
        rate = self._values['prediction.rate']
        if rate > 0.0:
            self._prediction_timer = self.create_timer(1.0 / rate, self._on_prediction_timer)

    def _on_prediction_timer(self) -> None:
        self._prediction_wanted.set()

    def _run_predictions(self) -> None:
        """
        Prediction thread: one prediction from the newest state per request.

        The rollout (compiled, releases the GIL) runs here, not in the executor, so 1 kHz
        callbacks are never queued behind it; requests that arrive while a prediction runs
        collapse into one, which starts from the newest state.
        """
        wanted = self._prediction_wanted
        while not self._stop.is_set():
            if not wanted.wait(0.1):
                continue
            wanted.clear()
            if self._stop.is_set():
                break
            try:
                self._predict()
            except Exception:  # noqa: B902 - the thread must survive
                if self._stop.is_set() or not self.context.ok():
                    break
                self._internal_error('prediction')

    def _prediction_inputs(self, case: str, times: np.ndarray, tau) -> Optional[dict]:
        """Return the model inputs over absolute ``times`` (see the module docstring)."""
        m = times.size
        if case == 'torque':
            return None if tau is None else {'tau': np.tile(tau, (m, 1))}
        return self._desired_inputs(times)

    def _desired_inputs(self, times: np.ndarray, shift=None) -> Optional[dict]:
        """
        Return θd, θ̇d over absolute ``times``: the reference, else the latest command held.

        The reference is handed over as an object evaluated exactly at the RKG stage times
        (no resampling); ``shift`` (n,) is added to θd (the fitted law's constant).
        """
        buffer = self._buffer
        end = self._reference_end
        if buffer is not None and end is not None and times[0] <= end:
            if buffer.reference_at(times[:1]) is not None:
                return {'reference': _BufferReference(buffer, float(times[0]), shift)}
        command = self._latest_command
        if command is None:
            return None
        return {'reference': _HeldCommand(command if shift is None else command + shift)}

    def _predict(self) -> None:
        """Publish the model's prediction from the newest state (executor thread)."""
        if not self._kernels_ready.is_set():
            return
        model, latest, joints = self._model, self._latest_state, self._joints
        if model is None or latest is None or joints is None or model.joint_names != joints:
            return
        cfg = self._cfg
        step = cfg['model_step']
        k = max(1, int(round(cfg['prediction.horizon'] / step)))
        t = np.arange(k + 1) * step
        stamp, t0, theta, theta_dot, tau, received_ns = latest
        inputs = None
        closed = self._closed
        if model.case == 'torque' and closed is not None and closed[0] is model:
            inputs = self._desired_inputs(t0 + t, closed[2])
            if inputs is not None:  # closed loop with the fitted law, along the reference
                model = closed[1]
        if inputs is None:
            inputs = self._prediction_inputs(model.case, t0 + t, tau)
        if inputs is None:
            return
        try:
            states = model.simulate(np.concatenate([theta, theta_dot]), t, **inputs)  # (k+1, 2n)
        except _NoReference:
            return
        n = len(joints)
        positions = np.array(states[:, :n])
        velocities = np.array(states[:, n:2 * n])
        positions[0] = theta
        velocities[0] = theta_dot
        if not (np.isfinite(positions).all() and np.isfinite(velocities).all()):
            self._reject('~/prediction', 'prediction', 'prediction_non_finite',
                         'the model diverged over the horizon; prediction not published')
            return
        # serialized directly (a third of the Python time of building the message objects)
        self._prediction_pub.publish(serialize_joint_trajectory(
            Time(sec=stamp[0], nanosec=stamp[1]), joints, t, positions, velocities))
        if received_ns == self._last_predicted_ns:
            return  # predicted again from the same state (a timer, the stream stopped)
        self._last_predicted_ns = received_ns
        latency = 1e-6 * (time.time_ns() - received_ns)  # ms, receipt of the state -> publish
        with self._lock:
            self._latencies.append(latency)

    # ------------------------------------------------------------------ services

    def _on_reset(self, request, response):
        try:
            with self._lock:
                self._reset_request = True
                buffer = self._buffer
            if buffer is not None:
                buffer.clear()
            response.success = True
            response.message = ('buffer cleared; the search restarts when '
                                f"{self._cfg['min_window']} s of data are buffered")
            self.get_logger().info(f'~/reset: {response.message}')
        except Exception as exc:  # noqa: B902 - a callback must never raise
            response.success = False
            response.message = f'reset failed: {exc!r}'
        return response

    def _on_save_model(self, request, response):
        try:
            response.success, response.message = self.save_model()
        except Exception as exc:  # noqa: B902 - a callback must never raise
            response.success, response.message = False, f'cannot save the model: {exc!r}'
        return response

    def save_model(self) -> Tuple[bool, str]:
        """Write the published model atomically to ``model_file``: ``(ok, message)``."""
        path = self._values['model_file']
        model = self._model
        if not path:
            return False, 'parameter model_file is empty: set it to a file path first'
        if model is None:
            return False, 'no model identified yet: nothing to save'
        path = os.path.abspath(os.path.expanduser(path))
        try:
            model.save(path)
        except Exception as exc:  # noqa: B902 - reported to the caller
            return False, f'cannot save the model to {path}: {exc}'
        return True, (f"model saved to {path} (generation {model.info.get('generation')}, "
                      f"cost {model.info.get('cost')})")

    def _on_pause(self, request, response):
        try:
            with self._lock:
                self._paused = bool(request.data)
                generation = self._generation
            response.success = True
            response.message = (f'paused after generation {generation}' if request.data
                                else f'resumed at generation {generation}')
            self.get_logger().info(f'~/pause: {response.message}')
        except Exception as exc:  # noqa: B902 - a callback must never raise
            response.success = False
            response.message = f'pause failed: {exc!r}'
        return response

    # ------------------------------------------------------------------ model file

    def _load_model_file(self) -> None:
        """Load ``model_file`` at start: publish it and keep it as the start genome."""
        path = self._values['model_file']
        if not path:
            return
        path = os.path.abspath(os.path.expanduser(path))
        stale = remove_stale_temp_files(path)
        if stale:
            self.get_logger().warning(f'removed {stale} temp file(s) of {path} left by a save '
                                      'that was killed (the model file itself is intact)')
        if not os.path.exists(path):
            self.get_logger().info(f'model_file {path} does not exist yet: starting fresh '
                                   '(it is written on ~/save_model and at shutdown)')
            return
        try:
            model = RKGNNModel.load(path, self._joints)
            case = self._cfg.case
            if model.case != case:
                raise ValueError(f'the model is for case {model.case!r}, the configured '
                                 f'case is {case!r}')
            spec = network_spec(self._values, model.n_joints)
            if model.spec != spec:
                raise ValueError(f'the network {model.spec.to_dict()} differs from the '
                                 f'network.* parameters {spec.to_dict()}')
        except Exception as exc:  # noqa: B902 - any unusable file: start fresh
            self.get_logger().error(f'cannot use model_file {path}: {exc}; starting fresh')
            return
        if self._joints is None:
            self._set_joints(model.joint_names, f'the model file {path}')
        self._start_model = model
        self._publish_model(model, warm_up=False)
        self.get_logger().info(
            f'loaded the model from {path} (case {model.case}, joints '
            f'{list(model.joint_names)}) and published it on ~/model; it starts the search')

    # ------------------------------------------------------------------ publishing

    def _publish_model(self, model: RKGNNModel, warm_up: bool = True) -> None:
        law = self._law
        closed = None
        if model.case == 'pd_gains' and self._cfg.case == 'torque' and law is not None:
            # a closed-loop search (case 'torque' with the fitted law): publish the arm model
            closed = model
            model = open_loop_model(closed, info=dict(closed.info, controller_law=law.to_dict()))
        if warm_up:
            self._warm_up(model)
        self._model_pub.publish(String(data=model.to_yaml()))
        gains = model.implied_gains()
        if model.case == 'torque' and law is not None:
            gains = (law.kp, law.kd)
            self._close_loop(model, law, closed)
        info = model.info
        with self._lock:
            self._model = model
            self._outputs = {
                'generation': int(info.get('generation', 0)),
                'cost': float(info.get('cost', math.nan)),
                'validation_nrmse': float(info.get('validation_nrmse', math.nan)),
                'kp': [] if gains is None else [float(v) for v in gains[0]],
                'kd': [] if gains is None else [float(v) for v in gains[1]],
            }
        self._published_genome = model.genome.copy()
        self._last_model_pub = time.monotonic()

    def _warm_up(self, model: RKGNNModel) -> None:
        """Run the compiled rollout once in this thread, so predictions never compile."""
        if self._kernels_ready.is_set():
            return
        n = model.n_joints
        t = np.arange(3) * model.dt
        zeros = np.zeros((t.size, n))
        x0 = np.concatenate([model.scales.theta_center, np.zeros(n)])
        if model.case == 'torque':
            model.simulate(x0, t, tau=zeros)
        else:
            model.simulate(x0, t, theta_d=zeros, theta_d_dot=zeros)
        self._kernels_ready.set()

    def _publish_diagnostics(self) -> None:
        try:
            with self._lock:
                status = dict(self._status)
                joints = self._joints
                latencies = np.array(self._latencies)
            buffer = self._buffer
            samples = buffer.stats()['state_samples'] if buffer is not None else 0
            state = status['state']
            level = {'error': DiagnosticStatus.ERROR,
                     'stale': DiagnosticStatus.WARN}.get(state, DiagnosticStatus.OK)
            pairs = [
                ('state', state), ('detail', status['detail']),
                ('generation', status['generation']), ('best_cost', status['best_cost']),
                ('validation_nrmse', status['validation_nrmse']),
                ('generations_per_s', f"{status['generations_per_s']:.2f}"),
                ('samples_buffered', samples),
                ('population_size', status['population_size']),
                ('case', self._cfg.case), ('joints', ','.join(joints or ())),
                ('prediction_latency_p50_ms', _percentile_text(latencies, 50)),
                ('prediction_latency_p99_ms', _percentile_text(latencies, 99)),
            ]
            pairs += [(f'drops.{reason}', count) for reason, count in self.drop_counts().items()]
            diag = DiagnosticStatus(level=level, name=self.get_name(),
                                    message=f"{state}: {status['detail']}",
                                    hardware_id=self.get_fully_qualified_name(),
                                    values=[KeyValue(key=k, value=str(v)) for k, v in pairs])
            msg = DiagnosticArray(status=[diag])
            msg.header.stamp = self.get_clock().now().to_msg()
            self._diagnostics_pub.publish(msg)
        except Exception:  # noqa: B902 - a callback must never raise
            self._internal_error('diagnostics')

    # ------------------------------------------------------------------ worker

    def _set_status(self, state: str, detail: str, **numbers) -> None:
        with self._lock:
            self._status.update(state=state, detail=detail, **numbers)

    def _run(self) -> None:
        """Worker thread: one generation per iteration until the stop event."""
        _yield_to_callbacks()
        backoff = BACKOFF_MIN_S
        errors = 0
        while not self._stop.is_set():
            try:
                if self._model is not None and not self._kernels_ready.is_set():
                    self._warm_up(self._model)
                ran = self._iterate()
                backoff, errors = BACKOFF_MIN_S, 0
            except Exception as exc:  # noqa: B902 - the worker must survive (item 23)
                if self._stop.is_set() or not self.context.ok():
                    break
                errors += 1
                self._count('worker', 'worker_error')
                self.get_logger().error(
                    f'identification worker failed ({errors} in a row), retrying in '
                    f'{backoff:.1f} s: {exc!r}\n{traceback.format_exc()}')
                if errors >= MAX_CONSECUTIVE_ERRORS:
                    self._drop_search(f'{errors} errors in a row')
                self._set_status('error', f'{type(exc).__name__}: {exc}')
                self._stop.wait(backoff)
                backoff = min(2.0 * backoff, BACKOFF_MAX_S)
                continue
            if not ran:
                self._stop.wait(IDLE_WAIT_S)

    def _drop_search(self, why: str) -> None:
        if self._evo is not None:
            self.get_logger().info(
                f'restarting the search after generation {self._generation}: {why}')
        self._evo = None
        self._generation = 0
        self._evaluations = 0
        self._gen_times.clear()
        self._val_nrmse = math.nan
        self._val_key = None
        self._last_refresh = -math.inf
        self._set_status('waiting for data', f'search restarts: {why}', generation=0,
                         best_cost=math.nan, validation_nrmse=math.nan,
                         generations_per_s=0.0, population_size=0)

    def _iterate(self) -> bool:
        """Run one generation if possible; return whether one ran."""
        with self._lock:
            cfg = self._cfg
            reset, self._reset_request = self._reset_request, False
            paused = self._paused
            buffer = self._buffer
            joints = self._joints
        if reset:
            self._drop_search('~/reset')
            self._start_model = None
        if self._evo is not None and self._evo_version != cfg.structural_version:
            self._drop_search('structural parameters changed')
        if self._evo is not None:
            self._maybe_publish_model(cfg, joints)
        if paused:
            self._set_status('paused', f'paused at generation {self._generation}')
            return False
        max_generations = cfg['es.max_generations']
        if self._evo is not None and max_generations and self._generation >= max_generations:
            self._set_status('finished', f'es.max_generations ({max_generations}) reached')
            return False
        if buffer is None or joints is None:
            self._set_status('waiting for data', 'no joint_states yet (joints unknown)')
            return False
        if not self._streams_fresh(cfg):
            return False
        since = time.monotonic() - self._last_refresh
        if since >= DATA_REFRESH_S or (self._evo is None and since >= WAITING_REFRESH_S):
            if not self._refresh_data(cfg, buffer, joints):
                return False
        elif self._evo is None:  # waiting for enough data: look again in a moment
            return False
        self._apply_es_settings(cfg)
        stats = self._evo.step()
        self._after_generation(cfg, stats, joints)
        return True

    def _streams_fresh(self, cfg: _Config) -> bool:
        streams = [('state', 'joint_states')]
        if cfg.case != 'torque':
            streams.append(('command', 'joint_commands'))
        now = time.monotonic()
        for key, topic in streams:
            last = self._last_rx.get(key)
            if last is None:
                self._set_status('waiting for data', f'no {topic} accepted yet')
                return False
            age = now - last
            if age > cfg['stale_timeout']:
                if not self._stale_warned:
                    self._stale_warned = True
                    self.get_logger().warning(
                        f'{topic}: no data for {age:.1f} s: the search pauses until data '
                        'returns')
                self._set_status('stale', f'{topic} silent for {age:.1f} s')
                return False
        if self._stale_warned:
            self._stale_warned = False
            self.get_logger().info('data is flowing again: the search resumes')
        return True

    def _refresh_data(self, cfg: _Config, buffer: StreamBuffer, joints) -> bool:
        """Take a snapshot of the buffer; build the search or hand it the new data."""
        self._last_refresh = time.monotonic()
        law = self._update_law(buffer) if cfg.case == 'torque' else None
        snapshot = buffer.snapshot(min_samples=MIN_SEGMENT_SAMPLES,
                                   pair_commands=law is not None)
        segments = list(snapshot)
        if law is not None:  # fold the law's constant torque into θd (see core.controller)
            segments = [replace(seg, theta_d=seg.theta_d + law.shift()) for seg in segments]
        train, validation, seconds = split_validation(
            segments, cfg['validation_fraction'], MIN_SEGMENT_SAMPLES)
        if seconds < cfg['min_window'] or not train:
            self._set_status('waiting for data', f"{seconds:.1f} s of {cfg['min_window']} s "
                                                 'buffered')
            return False
        if self._evo is None:
            self._build_search(cfg, train, joints, seconds)
            self._warm_seconds = seconds
        else:
            self._evo.set_data(train)
            if seconds >= REWARM_GROWTH * self._warm_seconds:
                self._warm_seconds = seconds
                self._rewarm(train, seconds)
            if self._had_finite and not math.isfinite(self._evo.optimizer.best_cost):
                self.get_logger().warning(
                    'the best model diverges on the new data window: the last good model '
                    'stays published until a finite one is found',
                    throttle_duration_sec=LOG_THROTTLE_S)
        self._validation = validation
        self._data_version += 1
        return True

    def _update_law(self, buffer: StreamBuffer) -> Optional[PDLaw]:
        """
        Case 'torque': refit the controller law; return the law the search runs with.

        While a fitted PD law explains the measured torque, the search runs in closed loop
        (a case-2 search with the fitted gains, on the commands) and predictions follow the
        reference. When a fresh fit becomes usable, stops being usable, or moves its gains
        by more than LAW_GAIN_RTOL, the search restarts in the new mode. Too few paired
        samples (no commands, or just after a reset) change nothing.
        """
        pairs = buffer.controller_samples()
        fresh = None if pairs is None else fit_pd_law(**pairs, min_samples=MIN_LAW_SAMPLES)
        searching = self._evo is not None
        running = self._evo_law if searching else None
        if fresh is None:
            return running
        new = fresh if fresh.usable(MAX_LAW_FIT_RATIO) else None
        if searching:
            if running is not None and new is not None and running.close_to(new,
                                                                            LAW_GAIN_RTOL):
                return running
            if running is None and new is None:
                return None
            self._drop_search('the controller law changed')
        old = self._law
        if new is not None and not new.close_to(old, LAW_GAIN_RTOL):
            self.get_logger().info(
                'controller law fitted from effort and joint_commands: the search and the '
                'predictions run in closed loop along the reference with Kp '
                f'{np.round(new.kp, 3).tolist()}, Kd {np.round(new.kd, 3).tolist()} '
                f'(residual {np.round(100 * new.fit_ratio, 2).tolist()} % of the torque)')
        elif new is None and old is not None:
            self.get_logger().warning(
                'joint_commands no longer explain the measured torque as a PD law '
                f'(residual {np.round(100 * fresh.fit_ratio, 1).tolist()} %): the search runs '
                'on the measured torque and predictions hold the latest torque')
        self._law = new
        self._closed = None
        model = self._model
        if new is not None and model is not None and model.case == 'torque':
            self._close_loop(model, new)
        return new

    def _close_loop(self, model: RKGNNModel, law: PDLaw, closed=None) -> None:
        if law.kp.size != model.n_joints:
            self._closed = None
            return
        closed = closed_loop_model(model, law) if closed is None else closed
        self._closed = (model, closed, law.shift())

    def _build_search(self, cfg: _Config, train, joints, seconds: float) -> None:
        n = len(joints)
        spec = network_spec(cfg.values, n)
        kp = kd = None
        law = self._law
        if spec.case == 'torque' and law is not None:  # closed loop with the fitted law
            spec = replace(spec, case='pd_gains')
            kp, kd = law.kp, law.kd
        elif spec.case == 'pd_gains':
            kp, kd = np.array(cfg['kp']), np.array(cfg['kd'])
            if kp.size != n or kd.size != n:
                raise ValueError(f"case 'pd_gains': kp has {kp.size} and kd {kd.size} "
                                 f'values for the {n} joints {list(joints)}')
        algorithm, settings = optimizer_settings(cfg.values)
        x0 = scales = None
        origin = 'the default genome'
        start = self._start_model
        if (start is not None and start.joint_names == tuple(joints)
                and replace(start.spec, case=spec.case) == spec
                and (start.case == spec.case or start.case == cfg.case)):
            x0, scales, origin = start.genome, start.scales, 'the loaded model'
        self._evo_law = law if spec.case != cfg.case else None
        self._evo = Evolution(spec, train, optimizer=algorithm, settings=settings,
                              seed=cfg['es.seed'], kp=kp, kd=kd,
                              substeps=cfg['substeps'] or None, scales=scales, x0=x0)
        if x0 is None:
            origin = self._warm_start(train, kp, kd, origin)
        self._start_model = None
        self._evo_version = cfg.structural_version
        self._algorithm = algorithm
        self._generation = 0
        self._evaluations = 0
        self._had_finite = False
        self.get_logger().info(
            f'search started from {origin}: case {spec.case}, joints {list(joints)}, '
            f'{spec.genome_size} genome elements, {algorithm} with population '
            f'{self._evo.optimizer.population_size}, {self._evo.substeps} substeps, '
            f'{seconds:.1f} s of data')

    def _warm_start(self, train, kp, kd, origin: str) -> str:
        """
        Place the start genome by the equation-error fit (the offline pipeline's first stage).

        Fitting M θ̈ + V + G + F = τ on the buffered samples needs no rollout: within
        WARM_START_S it puts gravity, inertia and friction where the data put them, which a
        search from the default genome takes many generations to find. Kept only when its
        rollout on the training data does not diverge; the optimizer restarts around it.
        """
        from rkgnn_ros.core.fitting.refine import refine_equation_error
        evo = self._evo
        t0 = time.perf_counter()
        self._set_status('evolving', 'warm start: equation-error fit')
        genome, _ = refine_equation_error(
            evo.spec, train, evo.scales, evo.optimizer.best_x, kp, kd,
            max_nfev=WARM_START_NFEV, deadline=t0 + WARM_START_S)
        cost = float(evo.problem.cost(genome[None])[0])
        if not math.isfinite(cost):
            return origin
        evo.optimizer.seed_best(genome, cost)
        sigma = max(WARM_START_SIGMA, evo.optimizer.settings.get('sigma_min', 0.0))
        evo.optimizer.restart(genome, sigma)
        return f'the equation-error fit ({time.perf_counter() - t0:.1f} s, J {cost:.4g})'

    def _rewarm(self, train, seconds: float) -> None:
        """
        Run the equation-error fit again from the best genome, on the grown window.

        A search starts from the first ``min_window`` seconds; the fit on a window that has
        grown by REWARM_GROWTH sees more of the motion. Its genome replaces the best (and
        the optimizer restarts around it) only if its rollout cost on the new data is lower.
        """
        from rkgnn_ros.core.fitting.refine import refine_equation_error
        evo = self._evo
        t0 = time.perf_counter()
        before = float(evo.optimizer.best_cost)
        genome, _ = refine_equation_error(
            evo.spec, train, evo.scales, evo.optimizer.best_x, evo.kp, evo.kd,
            max_nfev=WARM_START_NFEV, deadline=t0 + WARM_START_S)
        cost = float(evo.problem.cost(genome[None])[0])
        kept = math.isfinite(cost) and not cost >= before
        if kept:
            evo.optimizer.seed_best(genome, cost)
            evo.optimizer.restart(genome, max(WARM_START_SIGMA,
                                              evo.optimizer.settings.get('sigma_min', 0.0)))
        self.get_logger().info(
            f'equation-error fit again on {seconds:.1f} s of data '
            f'({time.perf_counter() - t0:.1f} s): J {cost:.4g} vs the best {before:.4g}, '
            + ('restarting around it' if kept else 'kept the best'))

    def _apply_es_settings(self, cfg: _Config) -> None:
        """Hand changed ES settings to the optimizer (between two generations)."""
        algorithm, settings = optimizer_settings(cfg.values)
        optimizer = self._evo.optimizer
        upcoming = self._generation + 1
        if algorithm != self._algorithm:
            new = make_optimizer(algorithm, optimizer.dim, x0=optimizer.best_x,
                                 rng=self._evo.rng, **settings)
            if math.isfinite(optimizer.best_cost):
                new.rescore(optimizer.best_cost)
            self._evo.optimizer = new
            self._algorithm = algorithm
            self.get_logger().info(
                f'generation {upcoming} runs es.algorithm {algorithm!r} (population '
                f'{new.population_size}), warm-started from the best genome')
            return
        current = optimizer.settings
        diff = {k: v for k, v in settings.items() if current.get(k) != v}
        if diff:
            optimizer.update_settings(**diff)
            shown = ', '.join(f'es.{k}={v}' for k, v in sorted(diff.items()))
            self.get_logger().info(f'generation {upcoming} takes the new settings {shown} '
                                   f'(population {optimizer.population_size})')

    def _best_model(self, joints) -> RKGNNModel:
        return self._evo.best_model(joints, {
            'generation': self._generation, 'evaluations': self._evaluations,
            'algorithm': self._algorithm})

    def _validate(self, model: RKGNNModel) -> float:
        """Return the θ-NRMSE of ``model`` on the validation segments (NaN: none)."""
        if not self._validation:
            return math.nan
        self._warm_up(model)
        n = model.n_joints
        predicted = [model.predict(seg)[:, :n] for seg in self._validation]
        measured = [seg.theta for seg in self._validation]
        return nrmse(np.vstack(predicted), np.vstack(measured))

    def _after_generation(self, cfg: _Config, stats: dict, joints) -> None:
        self._generation += 1
        self._evaluations += int(stats['population'])
        now = time.monotonic()
        self._gen_times.append(now)
        span = self._gen_times[-1] - self._gen_times[0]
        rate = (len(self._gen_times) - 1) / span if span > 0 else 0.0
        optimizer = self._evo.optimizer
        if math.isfinite(optimizer.best_cost):
            self._had_finite = True
        key = (self._data_version, optimizer.best_x.tobytes())
        if (self._validation and key != self._val_key and math.isfinite(optimizer.best_cost)
                and self._generation - self._last_val_generation >= VALIDATION_EVERY):
            self._val_nrmse = self._validate(self._best_model(joints))
            self._val_key = key
            self._last_val_generation = self._generation
        self._maybe_publish_model(cfg, joints)
        if now - self._last_evolution_pub >= EVOLUTION_MIN_PERIOD:
            self._last_evolution_pub = now
            self._evolution_pub.publish(make_float64_multiarray(
                [self._generation, stats['best_cost'], stats['mean_cost'], stats['spread'],
                 self._evaluations, self._val_nrmse, stats['population']], EVOLUTION_LABELS))
        self._set_status('evolving', f'generation {self._generation}',
                         generation=self._generation, best_cost=stats['best_cost'],
                         validation_nrmse=self._val_nrmse, generations_per_s=rate,
                         population_size=int(stats['population']))

    def _maybe_publish_model(self, cfg: _Config, joints) -> None:
        """Publish the best model if it changed, at most every model_publish_period."""
        optimizer = self._evo.optimizer
        if not math.isfinite(optimizer.best_cost) or joints is None:
            return
        if self._published_genome is not None and np.array_equal(optimizer.best_x,
                                                                 self._published_genome):
            return
        if time.monotonic() - self._last_model_pub < cfg['model_publish_period']:
            return
        model = self._best_model(joints)
        key = (self._data_version, optimizer.best_x.tobytes())
        if key != self._val_key:
            self._val_nrmse = self._validate(model)
            self._val_key = key
            self._last_val_generation = self._generation
        model.info['validation_nrmse'] = _finite_or_nan(self._val_nrmse)
        if not math.isfinite(self._val_nrmse) and self._validation:
            self.get_logger().warning(
                'the new best model diverges on the validation segment; publishing it anyway '
                '(its training cost is the best)', throttle_duration_sec=LOG_THROTTLE_S)
        self._publish_model(model)

    # ------------------------------------------------------------------ shutdown

    def stop(self) -> None:
        """Stop and join the worker, then save the model to ``model_file`` (if set)."""
        self._stop.set()
        # after SIGINT the context is shut down and /rosout cannot be published to: log
        # through a logger that rosout does not know (console only)
        logger = self.get_logger() if self.context.ok() else rclpy.logging.get_logger(
            f'{self.get_name()}.shutdown')
        self._prediction_wanted.set()
        for thread, what in ((self._worker, 'identification worker'),
                             (self._predictor, 'prediction thread'),
                             (self._ingest, 'ingest thread')):
            if thread.is_alive():
                thread.join(JOIN_TIMEOUT_S)
                if thread.is_alive():
                    logger.warning(f'the {what} did not stop within {JOIN_TIMEOUT_S} s')
        if self._values['model_file'] and self._model is not None:
            ok, message = self.save_model()
            (logger.info if ok else logger.error)(f'at shutdown: {message}')

    @property
    def model(self) -> Optional[RKGNNModel]:
        """Return the published model, or None before the first one."""
        return self._model

    @property
    def generation(self) -> int:
        """Return the generation count of the running search."""
        return self._generation


class _BufferReference:
    """The buffer's newest reference from absolute time ``t0`` on (``evaluate`` API)."""

    def __init__(self, buffer: StreamBuffer, t0: float, shift=None):
        self._buffer, self._t0, self._shift = buffer, t0, shift

    def evaluate(self, times):
        """Return (θd, θ̇d), each (M, n), at ``times`` (M,) relative to ``t0``."""
        reference = self._buffer.reference_at(self._t0 + np.asarray(times, dtype=float))
        if reference is None:  # cleared meanwhile (reset, clock jump): nothing to follow
            raise _NoReference()
        theta_d, theta_d_dot = reference
        return (theta_d if self._shift is None else theta_d + self._shift), theta_d_dot


class _HeldCommand:
    """The latest commanded position held, at zero velocity (``evaluate`` API)."""

    def __init__(self, theta_d: np.ndarray):
        self._theta_d = np.asarray(theta_d, dtype=float)

    def evaluate(self, times):
        """Return (θd, θ̇d), each (M, n), at ``times`` (M,)."""
        m = np.asarray(times).size
        return np.tile(self._theta_d, (m, 1)), np.zeros((m, self._theta_d.size))


class _NoReference(Exception):
    pass


def _percentile_text(values: np.ndarray, q: float) -> str:
    return f'{np.percentile(values, q):.2f}' if values.size else 'nan'


class _PolledGroup(CallbackGroup):
    """A callback group the executor never runs: its subscriptions are polled instead."""

    def can_execute(self, entity) -> bool:
        return False

    def beginning_execution(self, entity) -> bool:
        return False

    def ending_execution(self, entity) -> None:
        pass


def _received_ns(info) -> int:
    """Return the rmw receive time (ns) from rclpy's message info, else now."""
    received = info.get('received_timestamp') if isinstance(info, dict) else None
    return received if received else time.time_ns()


def _yield_to_callbacks() -> None:
    """
    Give the calling (worker) thread a lower CPU priority than the executor's callbacks.

    The fitness kernel runs numba threads on every core; at equal priority they starve the
    executor thread, and predictions and state callbacks queue up (measured: a p50
    state-to-prediction latency of 137 ms at 1 kHz). On Linux nice is per thread and the
    numba pool, created from this thread by its first parallel call, inherits it. The GIL
    switch interval is shortened too, so a callback waits less for the worker's Python code.
    The worker's numba kernels use one core fewer than the machine has (numba's thread
    count is per calling thread): the nice value does not reach a pool created earlier by
    another thread, and a 2-core machine must keep a core for the callbacks.
    """
    import numba
    numba.set_num_threads(max(1, min(numba.config.NUMBA_NUM_THREADS,
                                     (os.cpu_count() or 1) - 1)))
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), WORKER_NICE)
    except (AttributeError, OSError):  # not Linux, or not permitted: run at equal priority
        pass
    sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)


def main(args=None):
    """Run the identifier node until SIGINT or shutdown; return the exit code."""
    rclpy.init(args=args)
    node = None
    code = 0
    try:
        node = IdentifierNode()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RuntimeError as exc:
        # SIGINT landing inside rclpy's message conversion surfaces as a pybind11
        # RuntimeError ("Unable to convert call argument"), sometimes before rclpy has shut
        # the context down: that is the requested shutdown, not a failure.
        if rclpy.ok() and 'Unable to convert call argument' not in str(exc):
            raise
    except (ConfigurationError, ParameterException) as exc:
        rclpy.logging.get_logger('identifier').fatal(f'refusing to start: {exc}')
        code = 1
    finally:
        if node is not None:
            node.stop()
            node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == '__main__':
    sys.exit(main())

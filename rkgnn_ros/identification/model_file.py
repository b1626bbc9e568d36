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
The identifier's ``model_file``: loaded at start, written on ``~/save_model`` and at shutdown.

The file is input the node does not control, so it is read as hostile: whatever it holds,
loading ends in a bounded time and memory with a model or a :class:`ModelFileError` naming
the reason, and the node starts fresh on the latter (reliability guide, item 26).

Reading (:func:`read_model`)
    Only a regular file of at most :data:`MAX_MODEL_BYTES` is read: it is opened
    non-blocking (a FIFO with no writer would block ``open``), checked on the descriptor
    (``fstat``: a FIFO, a device such as ``/dev/zero``, a directory or a socket is
    refused), and at most one byte more than the limit is read.
Parsing (:func:`parse_plain_yaml`)
    Plain YAML data only: the events are scanned first (libyaml's parser, one event at a
    time), and an alias or anchor (``*a``, ``&a``: a 2.5 kB alias bomb expands past
    gigabytes), an explicit tag (``!!python/...``, ``!foo``), nesting deeper than
    :data:`MAX_DEPTH` or more than :data:`MAX_NODES` nodes is refused before anything is
    built. Only then is the document constructed.
Validation (:func:`check_model_dict`)
    Every number is checked against the bounds of what the node can run with before a
    model is built or published: joints (at most 64 names), integration step and substeps
    (the ``model_step`` and ``substeps`` parameters' ranges; a model with 10^9 substeps
    allocated past 5 GB), network units, genome elements, scales, gains and the ``info``
    values the node reads (generation, evaluations, cost, validation_nrmse). Then
    ``RKGNNModel.from_dict`` checks the layout, and :func:`load_model_file` checks that the
    model fits the node's case, network and joints.
Writing (:func:`save_model_file`)
    Atomic (a temp file in the same folder, fsync, ``os.replace``), so a kill at any moment
    leaves the previous model loadable; and only over a regular file or at a new path:
    ``os.replace`` over a device node would turn it into a regular file, so a special file,
    a directory or a file the node may not write is refused with the reason and nothing
    is replaced. A symbolic link is followed (its target is written). Temp files left by a
    save that was killed are removed at start.
"""

import errno
import math
import numbers
import os
import stat
from typing import Callable, List, Optional, Tuple

from rkgnn_ros.core.input_files import file_kind, InputFileError, read_bounded
from rkgnn_ros.core.model.files import remove_stale_temp_files, save_text_atomic
from rkgnn_ros.core.model.model import RKGNNModel
from rkgnn_ros.identification.parameters import MAX_GAIN, MAX_JOINTS, network_specs, PARAMETERS
from rkgnn_ros.wire.conversions import MAX_NAME_BYTES
import yaml

__all__ = ['MAX_DEPTH', 'MAX_MODEL_BYTES', 'MAX_NODES', 'LoadWork', 'ModelFileError',
           'check_model_dict', 'load_at_start', 'load_model_file', 'parse_plain_yaml',
           'read_model', 'read_model_text', 'save_model_file', 'to_plain_yaml']

#: Largest model file read (bytes): the largest model the parameters allow (64 joints, 32
#: units per network: 85,376 genome elements) is about 2 MB of YAML.
MAX_MODEL_BYTES = 4 * 1024 * 1024
#: Most YAML nodes (scalars and collections) a model file may hold.
MAX_NODES = 200_000
#: Deepest nesting of collections (a model file nests 3 deep).
MAX_DEPTH = 16

_RANGES = {spec.name: spec for spec in PARAMETERS}
_DT = (_RANGES['model_step'].low, _RANGES['model_step'].high)
_MAX_SUBSTEPS = int(_RANGES['substeps'].high)
_MAX_UNITS = int(_RANGES['network.theta_units'].high)
_MAX_GENOME = 1e6         # genome elements are normalised, of order 1
_MAX_SCALE = 1e9          # scales: rad, rad/s, rad/s^2, N m (positive ones at least 1e-9)
_MAX_COUNT = 10 ** 12     # info generation and evaluations
_LOADER = getattr(yaml, 'CSafeLoader', yaml.SafeLoader)  # libyaml when built with it


class ModelFileError(ValueError):
    """A model file that cannot be used; the message says why."""


class LoadWork:
    """What loading a file cost: ``bytes`` read and YAML ``events`` scanned (both bounded)."""

    def __init__(self):
        self.bytes = 0
        self.events = 0


def read_model_text(path: str, work: Optional[LoadWork] = None) -> str:
    """
    Return the text of the regular file ``path``, or raise :class:`ModelFileError`.

    Never blocks on a FIFO and never reads more than ``MAX_MODEL_BYTES + 1`` bytes
    (:func:`~rkgnn_ros.core.input_files.read_bounded`).
    """
    try:
        data = read_bounded(path, MAX_MODEL_BYTES)
    except InputFileError as exc:
        raise ModelFileError(str(exc)) from None
    if work is not None:
        work.bytes += len(data)
    try:
        return data.decode('utf-8')
    except UnicodeDecodeError as exc:
        raise ModelFileError(f'it is not UTF-8 text (byte {exc.start})') from None


def _yaml_reason(exc: Exception) -> str:
    text = ' '.join(str(exc).split())
    return text if len(text) <= 200 else text[:200] + '...'


def parse_plain_yaml(text: str, work: Optional[LoadWork] = None):
    """
    Return the plain data of a YAML document, or raise :class:`ModelFileError`.

    No aliases, anchors or explicit tags, at most :data:`MAX_DEPTH` levels and
    :data:`MAX_NODES` nodes: checked on the event stream before the document is built,
    so memory and time stay proportional to the text.
    """
    depth = events = 0
    try:
        for event in yaml.parse(text, Loader=_LOADER):
            events += 1
            if isinstance(event, yaml.AliasEvent):
                raise ModelFileError(f'YAML aliases are not allowed (*{event.anchor})')
            if isinstance(event, yaml.NodeEvent):
                if events > MAX_NODES:
                    raise ModelFileError(f'more than {MAX_NODES} YAML nodes')
                if event.anchor is not None:
                    raise ModelFileError(f'YAML anchors are not allowed (&{event.anchor})')
                if getattr(event, 'tag', None) is not None:
                    raise ModelFileError(f'YAML tags are not allowed ({event.tag})')
                if isinstance(event, yaml.CollectionStartEvent):
                    depth += 1
                    if depth > MAX_DEPTH:
                        raise ModelFileError(f'YAML nested deeper than {MAX_DEPTH} levels')
            elif isinstance(event, yaml.CollectionEndEvent):
                depth -= 1
    except yaml.YAMLError as exc:
        raise ModelFileError(f'not valid YAML ({_yaml_reason(exc)})') from None
    finally:
        if work is not None:
            work.events += events
    try:
        return yaml.load(text, Loader=_LOADER)
    except Exception as exc:  # noqa: B902 - e.g. an integer of 5000 digits: ValueError
        raise ModelFileError(f'not valid YAML ({_yaml_reason(exc)})') from None


def _real(value) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _numbers(where: str, values, low: float, high: float, size: Optional[int] = None,
             exclusive_low: bool = False) -> None:
    """Check a list of finite numbers in ``[low, high]`` (of ``size`` elements if given)."""
    if not isinstance(values, list):
        raise ModelFileError(f'{where} must be a list of numbers, got {type(values).__name__}')
    if size is not None and len(values) != size:
        raise ModelFileError(f'{where} must have {size} values, got {len(values)}')
    for k, value in enumerate(values):
        if not _real(value) or not math.isfinite(value) or value > high or (
                value <= low if exclusive_low else value < low):
            raise ModelFileError(f'{where}[{k}] must be a finite number in '
                                 f'{"(" if exclusive_low else "["}{low}, {high}], got '
                                 f'{_shown(value)}')


def _integer(where: str, value, low: int, high: int) -> None:
    """Check an integer in ``[low, high]`` (a bool is not one)."""
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise ModelFileError(f'{where} must be an integer in [{low}, {high}], got '
                             f'{_shown(value)}')


def _shown(value) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:60] + '...'


def _plain(where: str, value) -> None:
    """Check that ``value`` is plain data (mappings with text keys, lists, scalars)."""
    stack = [(where, value)]
    while stack:
        where, value = stack.pop()
        if isinstance(value, dict):
            for key, item in value.items():
                if not isinstance(key, str):
                    raise ModelFileError(f'{where} has a key that is not text: {_shown(key)}')
                stack.append((f'{where}.{key}', item))
        elif isinstance(value, list):
            stack.extend((f'{where}[{k}]', item) for k, item in enumerate(value))
        elif isinstance(value, int) and not isinstance(value, bool):
            if abs(value) > _MAX_COUNT:
                raise ModelFileError(f'{where} must be at most {_MAX_COUNT} in magnitude, '
                                     f'got {_shown(value)}')
        elif not isinstance(value, (float, str, bool, type(None))):
            raise ModelFileError(f'{where} must be plain data, got {type(value).__name__}')


def _check_info(info) -> None:
    """Check ``info``: plain data, and the values the node reads within their bounds."""
    if info is None:
        return
    if not isinstance(info, dict):
        raise ModelFileError(f'info must be a mapping, got {type(info).__name__}')
    _plain('info', info)
    for key in ('generation', 'evaluations'):
        _integer(f'info.{key}', info.get(key, 0), 0, _MAX_COUNT)
    for key in ('cost', 'validation_nrmse'):  # .nan: not known, .inf: diverged
        value = info.get(key, math.nan)
        if not _real(value) or value < 0.0:
            raise ModelFileError(f'info.{key} must be a number >= 0 (.nan: not known, .inf: '
                                 f'diverged), got {_shown(value)}')


def check_model_dict(d) -> None:
    """
    Check a parsed model file against the node's bounds; raise :class:`ModelFileError`.

    What ``RKGNNModel.from_dict`` then checks (format, version, layout, genome size) is not
    repeated; what it does not bound is checked here, before anything is built from it.
    """
    if not isinstance(d, dict):
        raise ModelFileError(f'expected a mapping at the top level, got {type(d).__name__}')
    for key, value in d.items():
        if not isinstance(key, str):
            raise ModelFileError(f'a top-level key is not text: {_shown(key)}')
        _plain(key, value)
    names = d.get('joint_names')
    if not isinstance(names, list) or not 1 <= len(names) <= MAX_JOINTS:
        raise ModelFileError(f'joint_names must list 1 to {MAX_JOINTS} names')
    for name in names:
        if not isinstance(name, str) or not name or \
                len(name.encode('utf-8', 'surrogatepass')) > MAX_NAME_BYTES:
            raise ModelFileError(f'joint_names must be non-empty text of at most '
                                 f'{MAX_NAME_BYTES} bytes, got {_shown(name)}')
    n = len(names)
    network = d.get('network')
    if not isinstance(network, dict):
        raise ModelFileError('network must be a mapping')
    for key in ('theta_units', 'torque_units'):
        _integer(f'network.{key}', network.get(key, 0), 0, _MAX_UNITS)
    if network.get('n_joints') != n:
        raise ModelFileError(f'network.n_joints must be {n} (the joint_names), got '
                             f'{_shown(network.get("n_joints"))}')
    for key in ('coulomb_velocity', 'inertia_floor'):
        if key in network:
            _numbers(f'network.{key}', [network[key]], 0.0, _MAX_SCALE, exclusive_low=True)
    integration = d.get('integration')
    if not isinstance(integration, dict):
        raise ModelFileError('integration must be a mapping')
    _numbers('integration.dt', [integration.get('dt')], *_DT)
    _integer('integration.substeps', integration.get('substeps'), 1, _MAX_SUBSTEPS)
    _numbers('genome', d.get('genome'), -_MAX_GENOME, _MAX_GENOME)
    scales = d.get('scales')
    if not isinstance(scales, dict):
        raise ModelFileError('scales must be a mapping')
    for key, values in scales.items():
        if key == 'theta_center':
            _numbers('scales.theta_center', values, -_MAX_SCALE, _MAX_SCALE, n)
        else:
            _numbers(f'scales.{key}', values, 1e-9, _MAX_SCALE, n)
    for key in ('kp', 'kd'):
        if d.get(key) is not None:
            _numbers(key, d[key], 0.0, MAX_GAIN, n)
    _check_info(d.get('info'))


def read_model(path: str, joints=None, work: Optional[LoadWork] = None) -> RKGNNModel:
    """
    Read, parse, check and build the model in ``path``; raise :class:`ModelFileError`.

    ``joints``: the configured joint names the model must have (None: any).
    """
    d = parse_plain_yaml(read_model_text(path, work), work)
    check_model_dict(d)
    try:
        return RKGNNModel.from_dict(d, joints)
    except (TypeError, ValueError) as exc:
        raise ModelFileError(str(exc).replace('model file: ', '', 1)) from None


def check_step(model: RKGNNModel, model_step: float) -> None:
    """Refuse a model whose RKG step is too fine for ``model_step`` (at most 64 per step)."""
    needed = math.ceil(model_step / (model.dt / model.substeps) - 1e-9)
    if needed > _MAX_SUBSTEPS:
        raise ModelFileError(
            f'its RKG step ({model.dt} s / {model.substeps} substeps) would take {needed} '
            f'steps per model_step of {model_step} s, more than {_MAX_SUBSTEPS}')


def load_model_file(path: str, joints, case: str, spec_for: Callable,
                    model_step: Optional[float] = None
                    ) -> Tuple[Optional[RKGNNModel], List[Tuple[str, str]]]:
    """
    Load the model in ``path`` if it fits the node's settings.

    Parameters
    ----------
    path : str
        The ``model_file`` parameter (``~`` expanded; empty: no file).
    joints : tuple of str, optional
        The configured joints (None: take the model's).
    case : str
        The configured case ('auto': a model of any case is taken).
    spec_for : callable
        ``spec_for(n_joints, case)`` returns the network the parameters describe, or a list
        of those they allow (``network.basis: auto``: the RBF and the global network).
    model_step : float, optional
        The configured ``model_step`` (s): the model must integrate it in at most 64
        RKG steps.

    Returns
    -------
    (model or None, log lines)
        Each log line is ``(level, text)``. Never raises: an unusable file gives one
        error line naming the file and the reason, and no model.

    """
    if not path:
        return None, []
    lines = []
    try:
        path = os.path.realpath(os.path.expanduser(path))
        stale = remove_stale_temp_files(path)
        exists = os.path.lexists(path)
    except (OSError, ValueError) as exc:  # a NUL in the path, an unreadable folder
        return None, [('error', f'cannot use model_file {path!r}: {exc}; starting fresh')]
    if stale:
        lines.append(('warning', f'removed {stale} temp file(s) of {path} left by a save that '
                                 'was killed (the model file itself is intact)'))
    if not exists:
        lines.append(('info', f'model_file {path} does not exist yet: starting fresh (it is '
                              'written on ~/save_model and at shutdown)'))
        return None, lines
    try:
        model = read_model(path, joints)
        if case != 'auto' and model.case != case:
            raise ModelFileError(f'the model is for case {model.case!r}, the configured case '
                                 f'is {case!r}')
        specs = spec_for(model.n_joints, model.case)
        specs = specs if isinstance(specs, (list, tuple)) else [specs]
        if model.spec not in specs:
            raise ModelFileError(f'the network {model.spec.to_dict()} differs from the '
                                 'network.* parameters '
                                 f'{" or ".join(str(spec.to_dict()) for spec in specs)}')
        if model_step is not None:
            check_step(model, model_step)
    except ModelFileError as exc:
        lines.append(('error', f'cannot use model_file {path}: {exc}; starting fresh'))
        return None, lines
    except Exception as exc:  # noqa: B902 - whatever else: refuse the file, never the start
        lines.append(('error', f'cannot use model_file {path}: {exc!r}; starting fresh'))
        return None, lines
    lines.append(('info', f'loaded the model from {path} (case {model.case}, joints '
                          f'{list(model.joint_names)}) and published it on ~/model; it starts '
                          'the search'))
    return model, lines


class _PlainDumper(yaml.SafeDumper):
    """Writes every object in full: no anchors or aliases, which the loader refuses."""

    def ignore_aliases(self, data) -> bool:
        return True


def load_at_start(config, ingestion, log: Callable[[str, str], None]) -> Optional[RKGNNModel]:
    """
    Load the node's ``model_file`` at start (:func:`load_model_file`); return the model.

    ``config`` is the node's parameter snapshot; what the loading says goes to ``log(level,
    text)``; a usable model names the joints when ``ingestion`` does not know them yet.
    """
    model, lines = load_model_file(config['model_file'], ingestion.joints, config.case,
                                   lambda n, case: network_specs(config.values, n, case),
                                   config['model_step'])
    for level, text in lines:
        log(level, text)
    if model is not None and ingestion.joints is None:
        ingestion.set_joints(model.joint_names, 'the model file')
    return model


def to_plain_yaml(model: RKGNNModel) -> str:
    """Return the YAML of ``model`` as :func:`parse_plain_yaml` reads it (no aliases)."""
    return yaml.dump(model.to_dict(), Dumper=_PlainDumper, sort_keys=False)


def _writable_target(path: str) -> Optional[str]:
    """Return why ``path`` may not be written (None: a regular file or a new path)."""
    try:
        info = os.stat(path)
    except FileNotFoundError:
        folder = os.path.dirname(path)
        if os.path.isdir(folder) and not os.access(folder, os.W_OK | os.X_OK):
            return f'the folder {folder} is not writable'
        return None
    except OSError as exc:
        return f'cannot inspect it: {exc.strerror or exc}'
    if not stat.S_ISREG(info.st_mode):
        return f'it is {file_kind(info.st_mode)}, not a regular file; nothing was replaced'
    if not os.access(path, os.W_OK):
        return 'the node may not write it (permission); nothing was replaced'
    return None


def save_model_file(path: str, model: Optional[RKGNNModel]) -> Tuple[bool, str]:
    """Write ``model`` atomically to ``path``: ``(ok, message)``; never raises."""
    if not path:
        return False, 'parameter model_file is empty: set it to a file path first'
    if model is None:
        return False, 'no model identified yet: nothing to save'
    try:
        path = os.path.realpath(os.path.expanduser(path))
        reason = _writable_target(path)
        if reason is None:
            save_text_atomic(path, to_plain_yaml(model))
    except OSError as exc:
        reason = exc.strerror or str(exc)
        if exc.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
            reason = f'the node may not write there ({reason})'
    except Exception as exc:  # noqa: B902 - reported to the caller
        reason = repr(exc)
    if reason is not None:
        return False, f'cannot save the model to {path}: {reason}'
    return True, (f"model saved to {path} (generation {model.info.get('generation')}, "
                  f"cost {model.info.get('cost')})")


def save_identified_urdf(path: str, model) -> Tuple[bool, str]:
    """
    Write the identified URDF of a rigid-body ``model`` atomically to ``path``; never raises.

    (:func:`rkgnn_ros.core.rigid.urdf_out.identified_urdf`: the robot description with the
    identified inertials and friction, rotor inertia and offsets in a comment.)
    """
    if not path:
        return False, 'parameter identified_urdf_file is empty: set it to a file path first'
    if getattr(model, 'kind', None) != 'rigid_body':
        return False, ('no rigid-body model identified yet (it needs a robot description): '
                       'nothing to save')
    try:
        from rkgnn_ros.core.rigid.urdf_out import identified_urdf
        path = os.path.realpath(os.path.expanduser(path))
        reason = _writable_target(path)
        if reason is None:
            info = model.info
            note = (f"case {model.case}, fit {info.get('refits')}, held-out error "
                    f"{info.get('held_out_error')}, {info.get('window_s')} s of data")
            save_text_atomic(path, identified_urdf(model.arm.structure, model.arm.parameters,
                                                   note))
    except OSError as exc:
        reason = exc.strerror or str(exc)
    except Exception as exc:  # noqa: B902 - reported to the caller
        reason = repr(exc)
    if reason is not None:
        return False, f'cannot save the identified URDF to {path}: {reason}'
    return True, f'identified URDF saved to {path}'

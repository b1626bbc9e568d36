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
The identified model's file format: versioned YAML, validated on load, written atomically.

A model file holds the network structure, the scales, the genome, the joint names, the
integration settings and free-form provenance (``info``); :func:`model_from_dict` refuses a
wrong format or version, a joint set that does not match, NaN or a wrong genome size with a
clear message. :func:`save_text_atomic` writes through a temp file in the same folder,
fsync and ``os.replace``, so a crash at any moment leaves the old or the new file.
"""

import os
import tempfile
from typing import Optional, Sequence

import numpy as np
import yaml

from .scales import Scales
from .spec import NetworkSpec

MODEL_FORMAT = 'rkgnn_ros/model'
MODEL_VERSION = 1


def model_to_dict(model) -> dict:
    """Return the plain-data form of a model, what ``RKGNNModel.save`` writes."""
    d = {
        'format': MODEL_FORMAT,
        'version': MODEL_VERSION,
        'case': model.case,
        'joint_names': list(model.joint_names),
        'network': model.spec.to_dict(),
        'scales': model.scales.to_dict(),
        'integration': {'dt': model.dt, 'substeps': model.substeps,
                        'torque_interpolation': model.torque_interpolation},
        'genome': model.genome.tolist(),
        'info': _plain(model.info),
    }
    if model.kp is not None:
        d['kp'] = model.kp.tolist()
        d['kd'] = model.kd.tolist()
    return d


def model_from_dict(cls, d, joint_names: Optional[Sequence[str]] = None):
    """
    Build a model of class ``cls`` from :func:`model_to_dict` output, validating everything.

    Raises ValueError with a clear message on a wrong format or version, a joint count
    or names that do not match ``joint_names`` (when given), NaN or a wrong genome size.
    """
    if not isinstance(d, dict):
        raise ValueError('model file: expected a mapping at the top level')
    if d.get('format') != MODEL_FORMAT:
        raise ValueError(f"model file: format must be '{MODEL_FORMAT}', "
                         f"got {d.get('format')!r}")
    if d.get('version') != MODEL_VERSION:
        raise ValueError(f'model file: version {d.get("version")!r} is not supported '
                         f'(this build reads version {MODEL_VERSION})')
    for key in ('network', 'scales', 'genome', 'joint_names', 'integration'):
        if key not in d:
            raise ValueError(f'model file: missing {key!r}')
    try:
        spec = NetworkSpec.from_dict(dict(d['network']))
        scales = Scales.from_dict(d['scales'])
        names = [str(v) for v in d['joint_names']]
        integ = dict(d['integration'])
    except (TypeError, ValueError) as exc:
        raise ValueError(f'model file: {exc}') from None
    if joint_names is not None and list(joint_names) != names:
        if len(joint_names) != len(names):
            raise ValueError(f'model file: the model has {len(names)} joints, '
                             f'{len(joint_names)} are configured')
        raise ValueError(f'model file: joints {names} do not match the configured '
                         f'{list(joint_names)}')
    if d.get('case') not in (None, spec.case):
        raise ValueError(f"model file: case {d.get('case')!r} contradicts the network's "
                         f'{spec.case!r}')
    try:
        return cls(spec, scales, d['genome'], names, d.get('kp'), d.get('kd'),
                   dt=float(integ.get('dt', 0.01)), substeps=int(integ.get('substeps', 4)),
                   torque_interpolation=integ.get('torque_interpolation', 'linear'),
                   info=d.get('info') or {})
    except (TypeError, ValueError) as exc:
        raise ValueError(f'model file: {exc}') from None


def model_to_yaml(model) -> str:
    """Return the YAML text of :func:`model_to_dict`."""
    return yaml.safe_dump(model_to_dict(model), sort_keys=False)


def model_from_yaml(cls, text, joint_names=None):
    """Parse YAML text into a model of class ``cls`` (see :func:`model_from_dict`)."""
    try:
        d = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ValueError(f'model file: not valid YAML ({exc})') from None
    return model_from_dict(cls, d, joint_names)


def remove_stale_temp_files(path) -> int:
    """
    Remove the temp files a killed :func:`save_text_atomic` of ``path`` left behind.

    Only files named like its own temp files (``.<name>.*.tmp`` beside ``path``); call it
    when no save of ``path`` can be running (at start). Returns how many were removed.
    """
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    prefix = '.' + os.path.basename(path) + '.'
    removed = 0
    try:
        names = os.listdir(folder)
    except OSError:
        return 0
    for name in names:
        if name.startswith(prefix) and name.endswith('.tmp'):
            try:
                os.remove(os.path.join(folder, name))
                removed += 1
            except OSError:
                pass
    return removed


def save_text_atomic(path, text) -> None:
    """Write ``text`` to ``path`` so that a crash leaves either the old or the new file."""
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix='.' + os.path.basename(path) + '.', suffix='.tmp',
                               dir=folder)
    try:
        # mkstemp creates 0600; give the file the mode a plain open() would (or the old one's)
        try:
            mode = os.stat(path).st_mode & 0o777
        except OSError:
            mode = 0o666 & ~_umask()
        os.fchmod(fd, mode)
        with os.fdopen(fd, 'w', encoding='utf-8') as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    try:
        dir_fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)
    except OSError:  # pragma: no cover - some filesystems refuse fsync on folders
        pass


def _umask() -> int:
    """Return the process umask without changing it (os.umask would race other threads)."""
    try:
        with open('/proc/self/status', encoding='ascii') as f:
            for line in f:
                if line.startswith('Umask:'):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    return 0o022


def _plain(value):
    """Convert numpy scalars/arrays inside ``value`` to plain Python for YAML."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value

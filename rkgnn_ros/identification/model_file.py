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

A file that cannot be used (corrupt, another case or network, wrong joints, NaN weights) is
refused with a reason and the node starts fresh; temp files left by a save that was killed
are removed. Writes are atomic (``RKGNNModel.save``: a temp file in the same folder, fsync,
``os.replace``), so a kill at any moment leaves the previous model loadable.
"""

import os
from typing import Callable, List, Optional, Tuple

from rkgnn_ros.core.fitting.identify import remove_stale_temp_files, RKGNNModel

__all__ = ['load_model_file', 'save_model_file']


def load_model_file(path: str, joints, case: str, spec_for: Callable
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
        ``spec_for(n_joints, case)`` returns the network the parameters describe.

    Returns
    -------
    (model or None, log lines)
        Each log line is ``(level, text)``.

    """
    if not path:
        return None, []
    path = os.path.abspath(os.path.expanduser(path))
    lines = []
    stale = remove_stale_temp_files(path)
    if stale:
        lines.append(('warning', f'removed {stale} temp file(s) of {path} left by a save that '
                                 'was killed (the model file itself is intact)'))
    if not os.path.exists(path):
        lines.append(('info', f'model_file {path} does not exist yet: starting fresh (it is '
                              'written on ~/save_model and at shutdown)'))
        return None, lines
    try:
        model = RKGNNModel.load(path, joints)
        if case != 'auto' and model.case != case:
            raise ValueError(f'the model is for case {model.case!r}, the configured case is '
                             f'{case!r}')
        spec = spec_for(model.n_joints, model.case)
        if model.spec != spec:
            raise ValueError(f'the network {model.spec.to_dict()} differs from the network.* '
                             f'parameters {spec.to_dict()}')
    except Exception as exc:  # noqa: B902 - any unusable file: start fresh
        lines.append(('error', f'cannot use model_file {path}: {exc}; starting fresh'))
        return None, lines
    lines.append(('info', f'loaded the model from {path} (case {model.case}, joints '
                          f'{list(model.joint_names)}) and published it on ~/model; it starts '
                          'the search'))
    return model, lines


def save_model_file(path: str, model: Optional[RKGNNModel]) -> Tuple[bool, str]:
    """Write ``model`` atomically to ``path``: ``(ok, message)``; never raises."""
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

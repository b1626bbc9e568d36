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
``identify_bag``: identify an arm from a rosbag2 recording, as the identifier node would.

Record once, identify offline and reproducibly::

    ros2 bag record /joint_states /joint_commands        # or a controller's controller_state
    ros2 run rkgnn_ros identify_bag my_bag --params-file config/identifier.yaml

The recording (a folder, an ``.mcap`` or a ``.db3`` file; :mod:`rkgnn_ros.recordings.reader`) is
read in order into the node's own ingestion (:class:`~rkgnn_ros.identification.ingest.
Ingestion`: every drop rule of the live node, counted per reason), the last ``--heldout``
seconds kept apart, and the node's online policy fits the rest
(:func:`~rkgnn_ros.core.fitting.offline.identify_offline`) with the node's parameters from
the same parameters file, within ``--budget`` seconds. Written to ``--out``:

- ``model.yaml``: the model, loadable as the node's ``model_file``;
- ``report.md`` and ``report.json``: the inputs, the data coverage, the drops, the
  evolution history, the held-out θ-NRMSE of the model (and of the online identifier's
  model recorded in the bag, when there is one);
- ``heldout.png`` (measured vs predicted θ on the held-out part), ``evolution.png``,
  ``coverage.png``.

Progress goes to standard output. A recording it cannot use (missing, unknown format,
corrupt, without the needed topics, other joint names, messages it cannot decode) ends it
with a one-line error naming the file and exit code 1, never a traceback; a recording
that breaks part way is used up to there and the report says so.

``--budget`` is the wall time of the whole run, counted from its start: the fit gets what
reading left, less :data:`REPORT_SHARE` of the budget kept for scoring the model and
writing the report; the figures are drawn only when :data:`FIGURES_S` seconds are left.
The model is judged against predictions that need no model on the held-out part
(holding the first state; following the recorded reference): when it does worse, the
model and the report are written all the same, the report says so at its top, and the
exit code is :data:`EXIT_WORSE_THAN_BASELINE` (3).
"""

import json
import math
import os
import sys
import time
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
from rkgnn_ros.offline.report import markdown, write_figures

__all__ = ['main', 'IdentifyError', 'read_parameters', 'EXIT_WORSE_THAN_BASELINE']

NODE_NAME = 'identifier'
#: Exit code when the model is written but predicts the held-out part worse than a baseline.
EXIT_WORSE_THAN_BASELINE = 3
#: Share of ``--budget`` kept for scoring the model and writing the report after the fit.
REPORT_SHARE = 0.1
#: Seconds that must be left of the budget for the figures to be drawn.
FIGURES_S = 3.0
#: A joint whose θ spans less than this (rad) in the training part does not move.
MIN_MOTION = 0.01
#: Largest parameters file read (bytes); the node's own is about 10 kB.
MAX_PARAMS_BYTES = 4 * 1024 * 1024


class IdentifyError(Exception):
    """What stops identify_bag: printed as one line, exit code 1."""


# -- the parameters file --------------------------------------------------------------------


def _flatten(tree: dict, prefix: str = '') -> Dict[str, object]:
    out = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            out.update(_flatten(value, f'{prefix}{key}.'))
        else:
            out[f'{prefix}{key}'] = value
    return out


def _matches(key: str, node_name: str) -> bool:
    """Return whether a params-file key applies to the node ``node_name`` in any namespace."""
    key = key.strip()
    if key in ('/**', '**'):
        return True
    parts = [part for part in key.split('/') if part]
    if not parts or parts[-1] not in (node_name, '*'):
        return False
    return key.startswith('/**/') or key.startswith('**/') or len(parts) == 1


def read_parameters(path: str, node_name: str = NODE_NAME) -> Dict[str, object]:
    """
    Return the node's parameter values from a ROS 2 parameters file (by name).

    The entries that apply to ``node_name`` in any namespace (``/**``, ``/**/identifier``,
    ``identifier``) are merged in file order. Raises IdentifyError naming the file.
    """
    import yaml
    from rkgnn_ros.core.input_files import InputFileError, read_bounded
    try:
        tree = yaml.safe_load(read_bounded(os.path.expanduser(path), MAX_PARAMS_BYTES)
                              .decode('utf-8'))
    except InputFileError as error:
        raise IdentifyError(f'{path}: cannot read the parameters file: {error}')
    except UnicodeDecodeError as error:
        raise IdentifyError(f'{path}: the parameters file is not UTF-8 text (byte '
                            f'{error.start})')
    except yaml.YAMLError as error:
        raise IdentifyError(f'{path}: not YAML: {" ".join(str(error).split())}')
    if not isinstance(tree, dict):
        raise IdentifyError(f'{path}: not a ROS 2 parameters file (no node entries)')
    values = {}
    found = False
    for key, entry in tree.items():
        if _matches(str(key), node_name):
            params = entry.get('ros__parameters') if isinstance(entry, dict) else None
            if not isinstance(params, dict):
                raise IdentifyError(f'{path}: entry {key!r} has no ros__parameters')
            values.update(_flatten(params))
            found = True
    if not found:
        raise IdentifyError(f'{path}: no entry for the node {node_name!r} (keys '
                            f'{sorted(map(str, tree))}; use /**/{node_name})')
    return values


def _config(values: Dict[str, object], window: float, path: str):
    """Return the node's Config of ``values`` with the buffer window set to ``window``."""
    from rkgnn_ros.identification.parameters import (ConfigurationError, make_config,
                                                     OUTPUTS, PARAMETERS)
    from rkgnn_ros.identification.ros2_control import controller_gains
    known = {spec.name: spec for spec in PARAMETERS}
    outputs = {spec.name for spec in OUTPUTS}
    given = {}
    gains = {name: value for name, value in values.items() if name.startswith('gains.')}
    for name, value in values.items():
        if name in outputs or name in gains or name in ('use_sim_time', 'model_file'):
            continue
        if name not in known:
            raise IdentifyError(f'{path}: unknown parameter {name!r} of the identifier')
        if isinstance(value, list) and not value:
            value = ()
        given[name] = value
    given['window'] = min(600.0, max(float(window), float(given.get('window', 1.0))))
    given['min_window'] = min(float(given.get('min_window', 5.0)), given['window'])
    try:
        given = controller_gains(given, gains, IdentifyError)
        return make_config(**given)
    except (ConfigurationError, TypeError, ValueError) as error:
        raise IdentifyError(f'{path}: {error}')


# -- reading ----------------------------------------------------------------------------------


def _ingestion(config, log):
    from rkgnn_ros.identification.ingest import Ingestion
    return Ingestion(config, log)


def _feed(ingestion, messages, topics, recording, until_ns=None, from_ns=None) -> Dict[str, int]:
    """Feed the recorded messages into an ingestion; return how many were handed over."""
    from rclpy.serialization import serialize_message
    from rkgnn_ros.wire.controller_state import controller_state_to_joint_state
    from rkgnn_ros.wire.conversions import Rejection
    counts = {'states': 0, 'commands': 0, 'controller_states': 0, 'undecodable': 0}
    for message in messages:
        if until_ns is not None and message.log_ns >= until_ns:
            break
        if from_ns is not None and message.log_ns < from_ns:
            continue
        if message.topic == topics.states:
            ingestion.handle_state(message.raw, message.log_ns)
            counts['states'] += 1
        elif message.topic == topics.commands:
            ingestion.handle_command(message.raw, message.log_ns)
            counts['commands'] += 1
        elif message.topic == topics.controller_state:
            try:
                decoded = recording.decode(message)
            except Exception:  # noqa: B902 - a message the definitions cannot decode
                counts['undecodable'] += 1
                ingestion.drops.count('command', 'malformed')
                continue
            command = controller_state_to_joint_state(decoded)
            if isinstance(command, Rejection):
                ingestion.drops.reject(topics.controller_state, 'command', command.reason,
                                       command.message)
            else:
                ingestion.handle_command(serialize_message(command), message.log_ns)
                counts['controller_states'] += 1
    return counts


def _online_model(messages, topic: str, before_ns: int, joints):
    """Return the online identifier's last model recorded before ``before_ns`` (or None)."""
    from rclpy.serialization import deserialize_message
    from rkgnn_ros.core.fitting.identify import RKGNNModel
    from std_msgs.msg import String
    last = None
    for message in messages:
        if message.topic == topic and message.log_ns < before_ns:
            last = message
    if last is None:
        return None
    try:
        text = deserialize_message(last.raw, String).data
        return RKGNNModel.from_yaml(text, joints)
    except Exception:  # noqa: B902 - an unusable recorded model is reported as absent
        return None


def _loop_of(model):
    """
    Return the ClosedLoop of a case-1 model that carries its controller law, else None.

    The model's ``info.controller_law`` holds the law's gains and constants but not the
    weights of a θ-basis: a law with θ-terms cannot be rebuilt and the model predicts open
    loop on the recorded torque.
    """
    from rkgnn_ros.core.fitting.controller import closed_loop
    from rkgnn_ros.core.fitting.controller_laws import ControllerLaw
    from rkgnn_ros.core.fitting.online_records import ClosedLoop
    law = model.info.get('controller_law') if model.case == 'torque' else None
    if not law or int(law.get('theta_features', 0)):
        return None
    n = model.n_joints

    def vector(name):
        return np.asarray(law.get(name, np.zeros(n)), dtype=float).reshape(n)

    try:
        law = ControllerLaw(vector('kp'), vector('kd'), vector('ki'), vector('bias'),
                            vector('integral_term'), vector('feedforward'), np.zeros((n, 0)),
                            str(law.get('theta_input', 'measured')), None,
                            vector('fit_ratio'), int(law.get('samples', 0)))
        return ClosedLoop(model, closed_loop(model, law), math.nan)
    except (TypeError, ValueError):  # a law that does not fold (Kp not > 0, wrong sizes)
        return None


def _refuse_still_joints(bag: str, joints, segments) -> None:
    """
    Refuse a recording in which some joints never move (θ range below MIN_MOTION).

    Their dynamics cannot be identified from it: the fit has nothing to go on, and the
    held-out θ-NRMSE (normalised by each joint's range) of such a joint reached 1.2e11.
    """
    theta = np.vstack([seg.theta for seg in segments])
    motion = theta.max(axis=0) - theta.min(axis=0)
    still = [name for name, span in zip(joints, motion) if not span >= MIN_MOTION]
    if still:
        moving = [name for name in joints if name not in still]
        raise IdentifyError(
            f'{bag}: {len(still)} of {len(joints)} joints never move in the training part '
            f'(θ range below {MIN_MOTION:g} rad): {still}; their dynamics cannot be '
            f'identified from this recording: record them moving, or identify the others '
            f'alone (joints: {moving} in the parameters file)')


def _coverage(segments) -> dict:
    """Return per-joint ranges and spreads of θ, θ̇ (and τ) over the segments."""
    theta = np.vstack([seg.theta for seg in segments])
    theta_dot = np.vstack([seg.theta_dot for seg in segments])
    out = {'seconds': float(sum(seg.duration for seg in segments)),
           'segments': len(segments),
           'theta_min': theta.min(axis=0).tolist(), 'theta_max': theta.max(axis=0).tolist(),
           'theta_std': theta.std(axis=0).tolist(),
           'theta_dot_std': theta_dot.std(axis=0).tolist()}
    if all(seg.tau is not None for seg in segments):
        out['tau_std'] = np.vstack([seg.tau for seg in segments]).std(axis=0).tolist()
    return out


# -- the report -------------------------------------------------------------------------------


def _structure(args, config, joints, log):
    """
    Return the robot description's structure of ``joints`` (None: no description given).

    From ``--robot-description``, else the parameters file's ``robot_description``; refused
    descriptions stop the run with their reason (a user who names one wants it used).
    """
    text = args.robot_description or config['robot_description']
    if not text:
        return None
    from rkgnn_ros.identification.description import RobotDescription
    lines = []
    description = RobotDescription(lambda level, line: lines.append((level, line)))
    description.configure(text, config['urdf.locked_joints'], config['urdf.locked_positions'],
                          config['gravity'])
    structure = description.structure(joints)
    for level, line in lines:
        log(level, line)
    if structure is None:
        raise IdentifyError(f'{args.bag}: {description.status}')
    return structure


def _learned_chain(args, config, joints, segments, log):
    """
    Return the chain learned from the training part (``--learn-chain``), or None.

    Case 'torque' (or 'pd_gains', τ from the known gains, or 'unknown', the gains learned
    with it) on 3 to 7 joints only
    (:func:`~rkgnn_ros.core.fitting.chain_online.learn_chain`); a chain refused is said in
    the log and the search runs as without it (with a robot description: the description
    is not checked).
    """
    from rkgnn_ros.core.fitting.chain_online import chain_case, learn_chain, LEARNED_CASES
    if config.case not in LEARNED_CASES:
        log('warning', f'--learn-chain: the chain is learned in cases '
                       f'{list(LEARNED_CASES)}, the recording gives case {config.case}: not '
                       'learned')
        return None
    _say(args.quiet, 'learning the chain from the training part')
    structure = learn_chain(segments, joints, log=log, case=chain_case(config.case))
    if structure is None:
        _say(args.quiet, 'the learned chain was not used (see the log)')
    return structure


def _check(args, config, structure, learned, segments, log) -> Optional[dict]:
    """Return the description checked against the learned chain (``description_check``)."""
    from rkgnn_ros.offline.description_check import check_description
    check = check_description(structure, learned, segments, config['validation_fraction'])
    if check is None:
        log('warning', 'description check: too few data to fit both rigid bodies')
        return None
    log('info' if check['fits_data'] else 'warning', f'description check: {check["text"]}')
    _say(args.quiet, f'description check: {check["text"]}')
    return check


def _say(quiet: bool, text: str) -> None:
    if not quiet:
        print(text, flush=True)


def identify(args, started: Optional[float] = None) -> dict:
    """
    Identify the recording ``args.bag``; return the report (raises IdentifyError).

    ``started``: the ``time.monotonic()`` the budget counts from (default: now).
    """
    started = time.monotonic() if started is None else started
    from rkgnn_ros.core.fitting.offline import (heldout_baselines, heldout_prediction,
                                                identify_offline, judge)
    from rkgnn_ros.core.fitting.validation import MIN_SEGMENT_SAMPLES
    from rkgnn_ros.recordings.reader import (find_topics, open_recording, read_messages,
                                             RecordingError)
    values = read_parameters(args.params_file, args.node_name) if args.params_file else {}
    try:
        recording = open_recording(args.bag)
    except RecordingError as error:
        raise IdentifyError(str(error))
    try:
        topics = find_topics(recording, args.namespace, args.joint_states, args.joint_commands,
                             args.controller_state, args.model_topic)
        _say(args.quiet, f'reading {args.bag} ({recording.storage}): states {topics.states}, '
                         f'commands {topics.commands or topics.controller_state or "none"}')
        messages, truncated = read_messages(recording, topics)
        truncated = '; '.join(filter(None, (recording.note, truncated)))
        if truncated:
            _say(args.quiet, f'  warning: {truncated}; using what was read')
    except RecordingError as error:
        raise IdentifyError(str(error))
    state_times = [m.log_ns for m in messages if m.topic == topics.states]
    if len(state_times) < 2:
        recording.close()
        raise IdentifyError(f'{args.bag}: {len(state_times)} message(s) on {topics.states}'
                            + (f' ({truncated})' if truncated else ''))
    span = (state_times[-1] - state_times[0]) * 1e-9
    config = _config(values, span + 1.0, args.params_file or 'the defaults')
    if config.case not in ('torque', 'auto') and not (topics.commands or
                                                      topics.controller_state):
        recording.close()
        raise IdentifyError(f'{args.bag}: case {config.case!r} needs joint_commands or a '
                            f'controller_state topic; the recording has '
                            f'{sorted(recording.types)}')
    heldout_s = max(0.0, float(args.heldout))
    if heldout_s >= span:
        recording.close()
        raise IdentifyError(f'{args.bag}: --heldout {heldout_s:g} s leaves nothing to fit: '
                            f'the states on {topics.states} span {span:.3g} s')
    split_ns = state_times[-1] - int(heldout_s * 1e9) if heldout_s > 0 else None
    log_lines: List[Tuple[str, str]] = []

    def log(level, text):
        log_lines.append((level, text))
        if level != 'info':
            _say(args.quiet, f'  {level}: {text}')

    train_in = _ingestion(config, log)
    counts = _feed(train_in, messages, topics, recording, until_ns=split_ns)
    held_in = (_ingestion(config, lambda level, text: level != 'info' and log(level, text))
               if split_ns is not None else None)
    if held_in is not None:
        _feed(held_in, messages, topics, recording, from_ns=split_ns)
    recording.close()
    drops = {k: v for k, v in train_in.drops.counts().items() if v}
    joints = train_in.joints
    config = train_in.view()[0]  # case 'auto': the case the recorded streams decided
    capture = train_in.capture()
    pair = config.case != 'torque' or bool(topics.commands or topics.controller_state)
    train_segments = [] if capture is None else list(capture.segments(MIN_SEGMENT_SAMPLES,
                                                                      pair))
    if not train_segments:
        raise IdentifyError(
            f'{args.bag}: no usable data on {topics.states}'
            + (f' for the joints {list(joints)}' if joints else '')
            + (f'; dropped: {drops}' if drops else '')
            + (f' ({truncated})' if truncated else ''))
    _refuse_still_joints(args.bag, joints, train_segments)
    _say(args.quiet, f'{counts["states"]} states, {counts["commands"]} commands, '
                     f'{counts["controller_states"]} controller states; training part '
                     f'{sum(s.duration for s in train_segments):.1f} s, joints {list(joints)}'
                     + (f'; dropped {drops}' if drops else ''))
    budget = max(0.0, (1.0 - REPORT_SHARE) * float(args.budget) - (time.monotonic() - started))

    def progress(status, elapsed):
        _say(args.quiet, f'  {elapsed:5.1f} s  {status.state}: {status.detail}; best J '
                         f'{status.best_cost:.4g}, validation θ-NRMSE '
                         f'{status.validation_nrmse:.4g}')

    structure = _structure(args, config, joints, log)
    check = None
    if getattr(args, 'learn_chain', False):
        taught = train_segments        # with τ: measured, or the servo's of the known gains
        if config.case == 'pd_gains':
            from rkgnn_ros.core.fitting.chain_online import servo_torque
            taught = servo_torque(train_segments, config.settings.kp, config.settings.kd)
        learned = _learned_chain(args, config, joints, taught, log)
        if structure is None:
            structure = learned
        elif learned is not None and config.case == 'unknown':
            log('warning', 'description check: it compares torques; case unknown has none '
                           '(not checked)')
        elif learned is not None:
            check = _check(args, config, structure, learned, taught, log)
    _say(args.quiet, f'fitting (case {config.case}, budget {budget:.0f} s'
                     + (f', the rigid body of {structure.describe()})' if structure else ')'))
    result = identify_offline(config.settings, capture, joints, budget_s=budget,
                              max_generations=args.max_generations, progress=progress,
                              structure=structure)
    log_lines += [(line.level, line.text) for line in result.log]
    if result.model is None:
        raise IdentifyError(f'{args.bag}: no finite model after {result.generations} '
                            f'generations ({result.status.state}: {result.status.detail})')
    heldout_segments = []
    if held_in is not None and held_in.capture() is not None:
        heldout_segments = list(held_in.capture().segments(MIN_SEGMENT_SAMPLES, pair))
    nrmse, predicted, how = (heldout_prediction(result.model, heldout_segments, result.loop)
                             if heldout_segments else (math.nan, [], 'no held-out part'))
    online_model = (_online_model(messages, topics.model, split_ns or state_times[-1], joints)
                    if topics.model else None)
    online_nrmse, online_predicted = None, []
    if online_model is not None and heldout_segments:
        online_nrmse, online_predicted, _ = heldout_prediction(
            online_model, heldout_segments, _loop_of(online_model))
    baselines = heldout_baselines(heldout_segments)
    verdict = judge(nrmse, baselines)
    os.makedirs(args.out, exist_ok=True)
    result.model.save(os.path.join(args.out, 'model.yaml'))
    drawn = float(args.budget) - (time.monotonic() - started) >= FIGURES_S
    figures = write_figures(args.out, joints, heldout_segments, predicted, online_predicted,
                            result.history, train_segments, None) if drawn else []
    update = result.update
    report = {
        'recording': args.bag, 'storage': recording.storage, 'topics': topics._asdict(),
        'params_file': args.params_file, 'joints': list(joints), 'case': config.case,
        'validation_fraction': config['validation_fraction'],
        'data': {'messages': counts, 'truncated': truncated, 'drops': drops,
                 'training': _coverage(train_segments),
                 'heldout': (_coverage(heldout_segments) if heldout_segments
                             else {'seconds': 0.0, 'segments': 0})},
        'fit': {'generations': result.generations, 'seconds': result.seconds,
                'budget_s': budget, 'state': result.status.state,
                'cost': update.cost, 'validation_nrmse': update.validation_nrmse,
                'kp': list(update.kp), 'kd': list(update.kd)},
        'heldout': {'seconds': heldout_s, 'nrmse': nrmse, 'how': how,
                    'online_nrmse': online_nrmse, 'baselines': baselines},
        'verdict': verdict._asdict(), 'description_check': check,
        'figures_skipped': '' if drawn else f'less than {FIGURES_S:g} s of the budget left',
        'history': [list(map(float, h)) for h in result.history],
        'history_fields': list(result.history[0]._fields) if result.history else [],
        'log': log_lines, 'figures': figures,
        'total_seconds': time.monotonic() - started,
    }
    with open(os.path.join(args.out, 'report.json'), 'w', encoding='utf-8') as f:
        json.dump(report, f, indent=1, default=_json_default)
    with open(os.path.join(args.out, 'report.md'), 'w', encoding='utf-8') as f:
        f.write(markdown(report))
    _say(args.quiet, f'held-out {heldout_s:g} s θ-NRMSE {nrmse:.4g} ({how})'
                     + (f'; the online model recorded in the bag: {online_nrmse:.4g}'
                        if online_nrmse is not None else '') + f'; {verdict.text}')
    _say(args.quiet, f'wrote {args.out}/model.yaml, report.md, report.json'
                     + (', ' + ', '.join(figures) if figures else '')
                     + f' in {report["total_seconds"]:.1f} s')
    return report


def _json_default(value):
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return str(value)


def main(argv: Optional[Sequence[str]] = None) -> int:
    """
    Run identify_bag; return the exit code.

    0 done; 1 an error it explains; 2 a bad command line; 3
    (:data:`EXIT_WORSE_THAN_BASELINE`) the model and the report are written, but the model
    predicts the held-out part worse than a baseline. Run from the command line (``argv``
    None), the budget counts from the process's start.
    """
    from rkgnn_ros.core.fitting.budget import process_age
    from rkgnn_ros.offline.args import parser
    started = time.monotonic() - (process_age() if argv is None else 0.0)
    args = parser(NODE_NAME).parse_args(argv)
    if not args.out:
        args.out = os.path.abspath(args.bag.rstrip('/')) + '_identified'
    try:
        if os.path.exists(args.out) and not os.path.isdir(args.out):
            raise IdentifyError(f'--out {args.out}: exists and is not a folder')
        report = identify(args, started)
    except IdentifyError as error:
        print(f'identify_bag: error: {error}', file=sys.stderr, flush=True)
        return 1
    except OSError as error:  # writing the results: a full disk, no permission
        print(f'identify_bag: error: {error.filename or args.out}: '
              f'{error.strerror or error}', file=sys.stderr, flush=True)
        return 1
    except KeyboardInterrupt:
        print('identify_bag: interrupted', file=sys.stderr, flush=True)
        return 130
    if report['verdict']['worse']:
        print(f'identify_bag: warning: {report["verdict"]["text"]}; the model is written '
              f'to {args.out} all the same (exit code {EXIT_WORSE_THAN_BASELINE})',
              file=sys.stderr, flush=True)
        return EXIT_WORSE_THAN_BASELINE
    return 0


if __name__ == '__main__':
    sys.exit(main())

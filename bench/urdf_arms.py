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
6- and 7-joint URDF arms online: arm × servo × sensors, the identifier on its defaults.

Every cell starts the installed ``sim_arm`` on example-robot-data's UR5
(``config/sim_arm_ur5.yaml``, six joints) or Panda (``config/sim_arm_panda.yaml``, seven
joints, fingers locked, rotor inertia in the drives) and the installed ``identifier`` with
its defaults: it takes the robot description from sim_arm's ``robot_description`` topic and
``case: auto`` from the streams. Servos: ``pd``, ``pd_gravity`` (the URDF's gravity at the
measured θ), ``pid`` (Ki = 0.5 Kp /s). Sensors: ``exact``; ``noisy`` (1e-4 rad of encoder
noise, θ̇ by backward differences); ``no_effort`` (joint_states without effort: case 3);
``realistic`` (noisy, 1 ms of stamp jitter, 2 % of joint_states dropped, no joint_commands:
sim_arm publishes them on a topic only this bench hears, for the follow-the-reference
baseline). Coulomb and viscous friction are in both arms' configs.

Each cell runs until the arm's stamps span ``--duration`` s. Every published prediction is
scored 2 s ahead against the measured motion, beside following the reference and holding
the last state (``bench/online_servos.py``'s ``score``): ``prediction_nrmse_60s`` and
``follow_reference_nrmse`` over the predictions started in the 5 s bin ending at 60 s (RMSE /
θ range, mean over joints), ``first_model_prediction_s`` (the first prediction published
as the model's, after the earliest stamp seen), and in the cells with effort
``torque_nrmse``: the last ``~/model`` received before 60 s predicting the torque of the
joint_states after 60 s (never fitted on), compared through one Gaussian low-pass of 0.05 s
(parallel filtering: the model's torque at every sample, θ̇ and θ̈ from θ by short
derivative kernels, then both torques filtered alike, so Coulomb friction's steps are
compared as they are; 0.05 s passes the references' motion, below 1 Hz, at 97 % and keeps
the encoders' noise out of θ̈), the stamps put back on their grid as the identifier does,
RMSE / std per joint, the worst joint.

``--perturbed``: the same cells with the identifier given the URDF with every link's mass,
centre of mass and inertia scaled by a random factor in [0.7, 1.3] (seeded) and no friction,
as ``robot_description`` (a file), instead of the topic.

Writes ``bench/results/urdf_arms.json``: arm → servo → sensors → the figures; top level
``worst_ratio_to_follow_reference``, ``worst_first_model_prediction_s``,
``worst_torque_nrmse`` and ``self_check_worst_joint_ratio`` where the cells have it, and
``perturbed_urdf`` with the same (``--merge`` keeps cells not rerun).
"""

import argparse
import datetime
import json
import os
import sys
import tempfile
import threading
import time
import xml.etree.ElementTree as ElementTree

from monitor import config, Monitor, NodeProcesses  # bench/monitor.py
import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))
sys.path.insert(0, HERE)

from online_servos import MAX_WALL_FACTOR, score  # noqa: E402

ARMS = {'ur5': 'sim_arm_ur5.yaml', 'panda': 'sim_arm_panda.yaml'}
SERVOS = ('pd', 'pd_gravity', 'pid')
SENSORS = {'exact': [],
           'noisy': ['-p', 'noise.theta_std:=0.0001', '-p', 'sensors.velocity:=difference'],
           'no_effort': ['-p', 'sensors.effort:=false'],
           'realistic': ['-p', 'noise.theta_std:=0.0001', '-p', 'sensors.velocity:=difference',
                         '-p', 'sensors.stamp_jitter:=0.001', '-p', 'sensors.drop_fraction:=0.02',
                         '-r', 'joint_commands:=bench_joint_commands']}
#: Where the follow-the-reference baseline takes θd.
COMMAND_TOPIC = {'realistic': 'bench_joint_commands'}
SCORED_AT = 60.0
TORQUE_SIGMA = 0.05     # s, the Gaussian the torques are compared through


def _values(arm):
    import yaml
    with open(config(ARMS[arm]), encoding='utf-8') as f:
        return yaml.safe_load(f)['/**/sim_arm']['ros__parameters']


def servo_arguments(arm, servo):
    """Return sim_arm's arguments of a servo on ``arm``."""
    if servo == 'pd':
        return []
    if servo == 'pd_gravity':
        return ['-p', 'gravity_compensation:=measured']
    ki = [0.5 * k for k in _values(arm)['kp']]
    return ['-p', f'ki:={ki}']


def perturbed_urdf(arm, seed=0):
    """Return the path of the arm's URDF with every inertial scaled in [0.7, 1.3], no friction."""
    from rkgnn_ros.core.sim.urdf_arm import read_description
    xml, _ = read_description(_values(arm)['robot_description'])
    root = ElementTree.fromstring(xml)
    rng = np.random.default_rng(seed)
    for inertial in root.iter('inertial'):
        mass = inertial.find('mass')
        if mass is not None:
            mass.set('value', repr(float(mass.get('value')) * rng.uniform(0.7, 1.3)))
        origin = inertial.find('origin')
        if origin is not None and origin.get('xyz'):
            xyz = np.array([float(v) for v in origin.get('xyz').split()])
            origin.set('xyz', ' '.join(repr(float(v)) for v in xyz * rng.uniform(0.7, 1.3, 3)))
        inertia = inertial.find('inertia')
        if inertia is not None:
            factor = rng.uniform(0.7, 1.3)
            for key in ('ixx', 'ixy', 'ixz', 'iyy', 'iyz', 'izz'):
                if inertia.get(key) is not None:
                    inertia.set(key, repr(float(inertia.get(key)) * factor))
    for dynamics in root.iter('dynamics'):
        dynamics.set('damping', '0.0')
        dynamics.set('friction', '0.0')
    handle, path = tempfile.mkstemp(prefix=f'urdf_arms_{arm}_', suffix='.urdf')
    with os.fdopen(handle, 'w', encoding='utf-8') as f:
        f.write(ElementTree.tostring(root, encoding='unicode'))
    return path


class Recorder:
    """Records θd, the effort of joint_states and every ~/model, on the monitor's node."""

    def __init__(self, node, command_topic):
        from rclpy.qos import DurabilityPolicy, QoSProfile, qos_profile_sensor_data
        from rclpy.qos import ReliabilityPolicy
        from sensor_msgs.msg import JointState
        from std_msgs.msg import String
        from trajectory_msgs.msg import JointTrajectory
        self.lock = threading.Lock()
        self.cmd_t, self.theta_d = [], []
        self.state_t, self.state = [], []
        self.models = []        # (receipt stamp of the newest state, YAML)
        self.sources, self.by_stamp, self.first_model = {}, {}, None
        node.create_subscription(JointState, command_topic, self._on_command,
                                 qos_profile_sensor_data)
        node.create_subscription(JointState, 'joint_states', self._on_state,
                                 qos_profile_sensor_data)
        node.create_subscription(String, 'identifier/model', self._on_model, QoSProfile(
            depth=10, reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL))
        node.create_subscription(JointTrajectory, 'identifier/prediction', self._on_prediction,
                                 10)

    @staticmethod
    def _stamp(msg):
        return msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec

    def _on_command(self, msg):
        if len(msg.position):
            with self.lock:
                self.cmd_t.append(self._stamp(msg))
                self.theta_d.append(np.array(msg.position, dtype=float))

    def _on_state(self, msg):
        if len(msg.position) and len(msg.effort) == len(msg.position):
            with self.lock:
                self.state_t.append(self._stamp(msg))
                self.state.append(np.concatenate([msg.position, msg.effort]))

    def _on_model(self, msg):
        with self.lock:
            newest = self.state_t[-1] if self.state_t else -np.inf
            self.models.append((newest, msg.data))

    def _on_prediction(self, msg):
        source = msg.header.frame_id.split(';')[0] or 'unmarked'
        with self.lock:
            self.sources[source] = self.sources.get(source, 0) + 1
            self.by_stamp[self._stamp(msg)] = source
            if source == 'model' and self.first_model is None:
                self.first_model = self._stamp(msg)

    def commands(self):
        """Return (t, θd) sorted by time."""
        with self.lock:
            t, theta_d = np.array(self.cmd_t), np.array(self.theta_d)
        order = np.argsort(t)
        return t[order], theta_d[order]


def torque_nrmse(arm, recorder, start, at=SCORED_AT):
    """Return the worst joint's torque error of the last model before ``at`` on the data after."""
    import yaml
    from rkgnn_ros.core.data import Dataset
    from rkgnn_ros.core.fitting.rigid_fit import _prepare, RigidArm, torque_errors
    from rkgnn_ros.core.rigid.structure import RigidStructure
    from rkgnn_ros.core.sim.urdf_arm import UrdfArm
    from rkgnn_ros.core.stamps import StampGrid
    with recorder.lock:
        t = np.array(recorder.state_t)
        data = np.array(recorder.state)
        models = list(recorder.models)
    before = [text for stamp, text in models if stamp - start <= at]
    if not before or t.size < 200:
        return None
    model = yaml.safe_load(before[-1])
    if model.get('kind') != 'rigid_body':
        return None
    values = _values(arm)
    sim = UrdfArm(values['robot_description'], values['urdf']['joints'])
    structure = RigidStructure(sim.urdf, sim.joint_names)
    fitted = RigidArm(structure, model['parameters'])
    order = np.argsort(t)
    t, data = t[order], data[order]
    after = t - start > at
    if after.sum() < 200:
        return None
    n = structure.n_joints
    grid_of = StampGrid()       # a jittering driver's stamps back on its grid, as the node does
    t = np.array([grid_of(stamp) for stamp in t])
    t, data = t[after], data[after]
    # gap-free stretches (this process misses messages now and then), each on a 10 ms grid
    # (stamps jitter); a stretch shorter than 1 s is left out
    cuts = np.flatnonzero(np.diff(t) > 0.015) + 1
    segments = []
    for part in np.split(np.arange(t.size), cuts):
        if part.size < 100:
            continue
        grid = np.arange(t[part[0]], t[part[-1]], 0.01)
        theta = np.stack([np.interp(grid, t[part], data[part, j]) for j in range(n)], 1)
        tau = np.stack([np.interp(grid, t[part], data[part, n + j]) for j in range(n)], 1)
        segments.append(Dataset(grid - grid[0], theta, np.zeros_like(theta), tau=tau))
    if not segments:
        return None
    rows, _, _ = _prepare(structure, segments, [], TORQUE_SIGMA, False)
    return float(np.max(torque_errors(fitted, rows)))


def wait_for_identifier(node, executor, processes, timeout=120.0):
    """Spin until the identifier's ~/prediction publisher is seen (it has started)."""
    start = time.monotonic()
    while time.monotonic() - start < timeout:
        executor.spin_once(timeout_sec=0.1)
        processes.check()
        if node.count_publishers('identifier/prediction') > 0:
            return
    raise RuntimeError(f'the identifier did not start within {timeout:g} s')


def run_cell(arm, servo, sensors, duration, horizon, domain, log_dir, description=None,
             identifier_args=(), prefix=None, torque=True):
    """
    Run sim_arm and the identifier for one cell; return its figures.

    ``identifier_args``: more ``--ros-args`` of the identifier; ``prefix``: of the log
    files (default from the cell); ``torque``: compute ``torque_nrmse`` (it reads the model
    as the URDF's parameters).
    """
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    arm_args = ['--params-file', config(ARMS[arm])] + servo_arguments(arm, servo) + \
        SENSORS[sensors]
    id_args = ['-p', f'prediction.horizon:={float(horizon)}'] + list(identifier_args)
    if description is not None:
        id_args += ['-p', f'robot_description:={description}']
    prefix = prefix or (f'urdf_arms_{arm}_{servo}_{sensors}_'
                        + ('perturbed_' if description else ''))
    load = os.getloadavg()[0]
    # the identifier first, as on an arm it watches before the arm moves: the cell counts
    # from the first joint_states, not from the identifier's start-up
    identifier = NodeProcesses([('identifier', id_args)], domain, log_dir, prefix=prefix)
    nodes = None
    try:
        ctx = rclpy.Context()
        rclpy.init(context=ctx, domain_id=domain)
        monitor = Monitor(ctx, horizon)
        recorder = Recorder(monitor.node, COMMAND_TOPIC.get(sensors, 'joint_commands'))
        executor = SingleThreadedExecutor(context=ctx)
        executor.add_node(monitor.node)
        wait_for_identifier(monitor.node, executor, identifier)
        nodes = NodeProcesses([('sim_arm', arm_args)], domain, log_dir, prefix=prefix)
        t0 = time.monotonic()
        while time.monotonic() - t0 < MAX_WALL_FACTOR * duration:
            executor.spin_once(timeout_sec=0.1)
            nodes.check()
            identifier.check()
            with monitor.lock:
                simulated = monitor.meas_t[-1] - monitor.meas_t[0] if monitor.meas_t else 0.0
            if simulated >= duration:
                break
        snap = monitor.snapshot()
        commands = recorder.commands()
        executor.shutdown()
        monitor.node.destroy_node()
        rclpy.try_shutdown(context=ctx)
    finally:
        codes = (nodes.stop() if nodes is not None else []) + identifier.stop()
    if len(snap[0]) < 2 or commands[0].size < 2:
        return {'error': 'no states or no commands recorded', 'exit_codes': codes}
    cell = score(snap, commands, horizon, duration, dict(recorder.by_stamp))
    with recorder.lock:     # what the torque figure was computed from, for a second look
        np.savez_compressed(os.path.join(log_dir, prefix + 'states.npz'),
                            t=np.array(recorder.state_t), data=np.array(recorder.state),
                            models=np.array([m[1] for m in recorder.models]),
                            model_t=np.array([m[0] for m in recorder.models]))
    start = min([float(np.min(snap[0]))] + list(snap[2]))
    cell['first_model_prediction_s'] = (None if recorder.first_model is None
                                        else float(recorder.first_model - start))
    # the last model before 60 s on the motion after it (on a shorter run: its last third)
    at = min(SCORED_AT, duration * 2.0 / 3.0)
    cell['torque_nrmse'] = (torque_nrmse(arm, recorder, start, at)
                            if sensors != 'no_effort' and torque else None)
    cell['exit_codes'] = codes
    cell['load_average'] = [round(load, 2), round(os.getloadavg()[0], 2)]
    cell['published_sources'] = dict(recorder.sources)
    return cell


def _cells(table):
    for arm in ARMS:
        for servo in SERVOS:
            for sensors in SENSORS:
                cell = table.get(arm, {}).get(servo, {}).get(sensors)
                if cell is not None and 'error' not in cell:
                    yield cell


def summary(table):
    """Return the worst figures over the cells of ``table``."""
    cells = list(_cells(table))
    ratios = [c['prediction_nrmse_60s'] / c['follow_reference_nrmse'] for c in cells
              if c.get('prediction_nrmse_60s') is not None and c.get('follow_reference_nrmse')]
    firsts = [c['first_model_prediction_s'] if c.get('first_model_prediction_s') is not None
              else float('inf') for c in cells]
    torques = [c['torque_nrmse'] for c in cells if c.get('torque_nrmse') is not None]
    joint = [c['self_check_worst_joint_ratio'] for c in cells
             if c.get('self_check_worst_joint_ratio') is not None]
    out = {'worst_ratio_to_follow_reference': max(ratios) if ratios else None,
           'worst_first_model_prediction_s': max(firsts) if firsts else None,
           'worst_torque_nrmse': max(torques) if torques else None,
           'cells': len(cells)}
    if joint:
        out['self_check_worst_joint_ratio'] = max(joint)
    return out


def _fmt(value):
    return 'n/a' if value is None else f'{value:.4%}'


def save(results, table, args):
    """Write ``results`` to ``--out`` with ``table``'s summary and the run's settings."""
    table.update(summary(table))
    table['meta'] = {'date': datetime.date.today().isoformat(), 'cpus': os.cpu_count(),
                     'duration_s': args.duration, 'horizon_s': args.horizon,
                     'perturbed_seed': args.seed if args.perturbed else None,
                     'metric': 'module docstring of bench/urdf_arms.py'}
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, 'w', encoding='utf-8') as f:
        json.dump(results, f, indent=2)


def main(argv=None):
    """Run the cells; return the exit code."""
    parser = argparse.ArgumentParser(description='URDF arms online, arm x servo x sensors')
    parser.add_argument('--arms', default=','.join(ARMS))
    parser.add_argument('--servos', default=','.join(SERVOS))
    parser.add_argument('--sensors', default=','.join(SENSORS))
    parser.add_argument('--perturbed', action='store_true',
                        help='the identifier gets the URDF with perturbed inertials')
    parser.add_argument('--merge', action='store_true',
                        help='keep the cells of the existing --out file that are not run')
    parser.add_argument('--duration', type=float, default=90.0)
    parser.add_argument('--horizon', type=float, default=2.0)
    parser.add_argument('--seed', type=int, default=0, help='of the perturbed inertials')
    parser.add_argument('--domain', type=int, default=None)
    parser.add_argument('--out', default=os.path.join(HERE, 'results', 'urdf_arms.json'))
    args = parser.parse_args(argv)
    log_dir = os.path.join(os.path.dirname(HERE), 'log', 'bench')
    results = {}
    if args.merge and os.path.exists(args.out):
        with open(args.out, encoding='utf-8') as f:
            results = json.load(f)
    table = results.setdefault('perturbed_urdf', {}) if args.perturbed else results
    cells = [(a, s, m) for a in args.arms.split(',') if a for s in args.servos.split(',') if s
             for m in args.sensors.split(',') if m]
    for i, (arm, servo, sensors) in enumerate(cells):
        domain = (20 + (os.getpid() + 37 * i) % 200 if args.domain is None
                  else args.domain + i % 4)
        description = perturbed_urdf(arm, args.seed) if args.perturbed else None
        print(f'== {arm} x {servo} x {sensors}' + (' (perturbed URDF)' if description else '')
              + f': {args.duration:.0f} s on ROS_DOMAIN_ID={domain}', flush=True)
        try:
            cell = run_cell(arm, servo, sensors, args.duration, args.horizon, domain, log_dir,
                            description)
        finally:
            if description is not None:
                os.unlink(description)
        table.setdefault(arm, {}).setdefault(servo, {})[sensors] = cell
        save(results, table, args)      # each cell kept as it ends
        if 'error' in cell:
            print(f"  {cell['error']}", flush=True)
            continue
        ratio = (cell['prediction_nrmse_60s'] / cell['follow_reference_nrmse']
                 if cell.get('prediction_nrmse_60s') is not None
                 and cell.get('follow_reference_nrmse') else None)
        print(f"  at 60 s: prediction {_fmt(cell['prediction_nrmse_60s'])}  follow "
              f"{_fmt(cell['follow_reference_nrmse'])}  ratio {ratio}  first model "
              f"{cell['first_model_prediction_s']} s  torque {cell['torque_nrmse']}  "
              f"published {cell['published_sources']}  load {cell['load_average']}",
              flush=True)
    save(results, table, args)
    print(json.dumps({k: v for k, v in table.items() if k not in ARMS}, indent=1), flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())

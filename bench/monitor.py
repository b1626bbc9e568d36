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
Run the installed nodes and watch their topics: shared by ``make demo`` and the benchmarks.

:class:`NodeProcesses` starts ``sim_arm`` and ``identifier`` from the colcon install (the
executables ``ros2 run`` starts) on a given ROS domain; :class:`Monitor` records
``joint_states``, ``identifier/prediction`` and ``identifier/evolution``;
:func:`prediction_score` scores the recorded predictions against the motion that followed.
"""

import os
import signal
import subprocess
import threading

import numpy as np

CASES = {'1': 'torque', '2': 'pd_gains', '3': 'unknown', 'torque': 'torque',
         'pd_gains': 'pd_gains', 'unknown': 'unknown'}
PAPER_KP = [32.84, 42.05, 42.31]
PAPER_KD = [42.44, 0.19, 4.86]


def executable(name):
    """Return the path ``ros2 run rkgnn_ros <name>`` would start."""
    from ament_index_python.packages import get_package_prefix
    path = os.path.join(get_package_prefix('rkgnn_ros'), 'lib', 'rkgnn_ros', name)
    if not os.access(path, os.X_OK):
        raise FileNotFoundError(f'{path} is not an executable: run colcon build first')
    return path


def config(name):
    """Return an installed config file."""
    from ament_index_python.packages import get_package_share_directory
    return os.path.join(get_package_share_directory('rkgnn_ros'), 'config', name)


class Monitor:
    """Records joint_states, ~/prediction and ~/evolution of the running nodes."""

    def __init__(self, context, horizon):
        from rclpy.node import Node
        from rclpy.qos import qos_profile_sensor_data
        from sensor_msgs.msg import JointState
        from std_msgs.msg import Float64MultiArray
        from trajectory_msgs.msg import JointTrajectory
        self.node = Node('rkgnn_demo_monitor', context=context)
        self.lock = threading.Lock()
        self.horizon = horizon
        self.meas_t, self.meas_theta = [], []
        self.pred_t0, self.pred_off, self.pred_theta = [], [], []
        self.pred_frame = []     # each prediction's frame_id ('model', 'baseline:...')
        self.evolution = []
        self.labels = None
        self.first_model = None  # stamp of the first prediction the model made (not a baseline)
        self.node.create_subscription(JointState, 'joint_states', self._on_state,
                                      qos_profile_sensor_data)
        self.node.create_subscription(JointTrajectory, 'identifier/prediction',
                                      self._on_prediction, 10)
        self.node.create_subscription(Float64MultiArray, 'identifier/evolution',
                                      self._on_evolution, 10)

    @staticmethod
    def _stamp(header):
        return header.stamp.sec + 1e-9 * header.stamp.nanosec

    def _on_state(self, msg):
        if len(msg.position) == 0:
            return
        with self.lock:
            self.meas_t.append(self._stamp(msg.header))
            self.meas_theta.append(np.array(msg.position, dtype=float))

    def _on_prediction(self, msg):
        if len(msg.points) < 2:
            return
        off = np.array([p.time_from_start.sec + 1e-9 * p.time_from_start.nanosec
                        for p in msg.points])
        theta = np.array([p.positions for p in msg.points], dtype=float)
        with self.lock:
            if self.first_model is None and msg.header.frame_id.split(';')[0] == 'model':
                self.first_model = self._stamp(msg.header)
            self.pred_t0.append(self._stamp(msg.header))
            self.pred_off.append(off)
            self.pred_theta.append(theta)
            self.pred_frame.append(msg.header.frame_id)

    def _on_evolution(self, msg):
        if self.labels is None and msg.layout.dim:
            self.labels = msg.layout.dim[-1].label.split(',')
        with self.lock:
            self.evolution.append(np.array(msg.data, dtype=float))

    def snapshot(self):
        """Return copies of everything recorded so far."""
        with self.lock:
            return (np.array(self.meas_t), np.array(self.meas_theta),
                    list(self.pred_t0), list(self.pred_off), list(self.pred_theta),
                    np.array(self.evolution), self.labels)


def field(evolution, labels, name):
    """Return one column of the ~/evolution records (NaN if absent)."""
    if labels is None or name not in labels or evolution.size == 0:
        return np.full(len(evolution), np.nan)
    return evolution[:, labels.index(name)]


def prediction_score(snapshot, horizon, window=None):
    """Return (t0, errors, nrmse) of the horizon-ahead predictions (last ``window`` s)."""
    from rkgnn_ros.core.selfcheck import ahead_errors, range_normalised_rmse
    meas_t, meas_theta, t0s, offs, thetas, _, _ = snapshot
    if meas_t.size < 2:
        return np.empty(0), np.empty((0, 0)), float('nan')
    order = np.argsort(meas_t)
    meas_t, meas_theta = meas_t[order], meas_theta[order]
    t0, err = ahead_errors(t0s, offs, thetas, meas_t, meas_theta, horizon)
    theta_range = np.ptp(meas_theta, axis=0)
    recent = err if window is None or t0.size == 0 else err[t0 >= t0[-1] - window]
    return t0, err, range_normalised_rmse(recent, theta_range)


def identifier_arguments(case, horizon=2.0, extra=()):
    """Return ``--ros-args`` overrides of the identifier for a case (paper gains in case 2)."""
    case = CASES[str(case)]
    args = ['-p', f'case:={case}', '-p', f'prediction.horizon:={float(horizon)}']
    if case == 'pd_gains':
        args += ['-p', f'kp:={PAPER_KP}', '-p', f'kd:={PAPER_KD}']
    return args + list(extra)


class NodeProcesses:
    """
    The installed nodes as child processes; stopped with SIGINT on :meth:`stop`.

    Parameters
    ----------
    nodes : list of (name, extra_arguments)
        Executables of rkgnn_ros and their extra ``--ros-args`` arguments.
    domain : int
        ROS_DOMAIN_ID of the children.
    log_dir : str
        Each child's output goes to ``<log_dir>/<prefix><name>.log``.

    """

    def __init__(self, nodes, domain, log_dir, prefix=''):
        env = dict(os.environ, ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED='1')
        os.makedirs(log_dir, exist_ok=True)
        self.names, self.procs, self.logs = [], [], []
        try:
            for name, extra in nodes:
                log = open(os.path.join(log_dir, f'{prefix}{name}.log'), 'w', encoding='utf-8')
                self.logs.append(log)
                cmd = [executable(name), '--ros-args', '--params-file',
                       config(f'{name}.yaml')] + list(extra)
                self.procs.append(subprocess.Popen(cmd, env=env, stdout=log,
                                                   stderr=subprocess.STDOUT))
                self.names.append(name)
        except BaseException:
            self.stop()
            raise

    def check(self):
        """Raise RuntimeError if a child exited."""
        for name, p in zip(self.names, self.procs):
            if p.poll() is not None:
                raise RuntimeError(f'{name} exited early with code {p.returncode} '
                                   f'(log: {self.logs[self.names.index(name)].name})')

    def stop(self, timeout=15.0):
        """SIGINT every child, wait, kill stragglers; return the exit codes."""
        codes = []
        for p in self.procs:
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for p in self.procs:
            try:
                codes.append(p.wait(timeout=timeout))
            except subprocess.TimeoutExpired:
                p.kill()
                codes.append(p.wait())
        for log in self.logs:
            log.close()
        return codes

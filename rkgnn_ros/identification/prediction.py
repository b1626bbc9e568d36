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
The prediction service: the published model rolled out from the newest measured state.

:class:`Predictor` owns the prediction thread. A request (the ``prediction.rate`` timer, or
an accepted state with ``prediction.on_state``) wakes it; requests that arrive while a
prediction runs collapse into one, which starts from the newest state. The compiled rollout
releases the GIL, so the 1 kHz ingestion never waits behind it. Inputs over the horizon are
snapshots, never live buffers: the newest planned reference
(:class:`~rkgnn_ros.stream_buffer.PlannedReference`, immutable), else the newest command
held, else (case 'torque' without a fitted law) the newest torque held.

A prediction is checked finite, serialized straight to CDR
(``conversions.serialize_joint_trajectory``) and handed over as a :class:`Prediction` to
``publish``: the identifier queues it for its executor thread, which publishes it and
calls :meth:`Predictor.published`, so the latency kept for ``/diagnostics`` runs from the
middleware's receipt of the state to the actual publish. (Publishing from this thread
instead showed no lower latency in paired runs; the README's *Responsiveness* has them.)
"""

from collections import deque
import threading
import time
from typing import Callable, NamedTuple, Optional, Tuple

from builtin_interfaces.msg import Time
import numpy as np
from rkgnn_ros.conversions import make_joint_state, serialize_joint_trajectory
from rkgnn_ros.core.fitting.identify import RKGNNModel
from rkgnn_ros.core.fitting.online import ClosedLoop
from sensor_msgs.msg import JointState

__all__ = ['LATENCY_WINDOW', 'Prediction', 'Predictor']

LATENCY_WINDOW = 1000  # predictions whose latency the diagnostics summarise
JOIN_TIMEOUT_S = 10.0


class _FromReference:
    """A planned reference from absolute time ``t0`` on (the rollout's ``evaluate`` API)."""

    def __init__(self, plan, t0: float, shift=None):
        self._plan, self._t0, self._shift = plan, t0, shift

    def evaluate(self, times):
        """Return (θd, θ̇d), each (M, n), at ``times`` (M,) relative to ``t0``."""
        theta_d, theta_d_dot = self._plan.at(self._t0 + np.asarray(times, dtype=float))
        return (theta_d if self._shift is None else theta_d + self._shift), theta_d_dot


class _HeldCommand:
    """The latest commanded position held, at zero velocity (``evaluate`` API)."""

    def __init__(self, theta_d: np.ndarray):
        self._theta_d = np.asarray(theta_d, dtype=float)

    def evaluate(self, times):
        """Return (θd, θ̇d), each (M, n), at ``times`` (M,)."""
        m = np.asarray(times).size
        return np.tile(self._theta_d, (m, 1)), np.zeros((m, self._theta_d.size))


class Prediction(NamedTuple):
    """A prediction to publish: its CDR bytes, and the receipt (ns) of its state if new."""

    data: bytes
    received_ns: Optional[int]  # None: predicted again from the same state
    state: Optional[JointState] = None  # ~/predicted_state: the state prediction.lookahead on


def _state_ahead(stamp, joints, t, positions, velocities, lookahead: float):
    """
    Return the predicted JointState ``lookahead`` s after the state stamped ``stamp``.

    Interpolated linearly between the prediction's points, stamped at the time it predicts
    (the state's stamp plus the look-ahead), effort NaN; None when ``lookahead`` is 0.
    """
    if lookahead <= 0.0:
        return None
    ahead = min(float(lookahead), float(t[-1]))
    position = [float(np.interp(ahead, t, positions[:, j])) for j in range(len(joints))]
    velocity = [float(np.interp(ahead, t, velocities[:, j])) for j in range(len(joints))]
    sec, nanosec = divmod(stamp[0] * 1_000_000_000 + stamp[1] + int(round(ahead * 1e9)),
                          1_000_000_000)
    return make_joint_state(Time(sec=int(sec), nanosec=int(nanosec)), list(joints), position,
                            velocity, None)


class _Published(NamedTuple):
    model: Optional[RKGNNModel] = None
    loop: Optional[ClosedLoop] = None


class Predictor:
    """
    Predictions of the published model from the newest state, in a thread of their own.

    Parameters
    ----------
    ingestion : Ingestion
        Where the newest state, command and reference come from, and where a non-finite
        prediction or an internal error is counted.
    publish : callable
        Called with each :class:`Prediction` (from the prediction thread).
    config : callable
        Returns the current parameters (``model_step``, ``prediction.horizon``).

    """

    def __init__(self, ingestion, publish: Callable[[Prediction], None], config: Callable):
        self._ingestion = ingestion
        self._publish = publish
        self._config = config
        self._published = _Published()
        self._ready = threading.Event()  # the rollout kernels ran once (compiled)
        self._wanted = threading.Event()
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._latencies: deque = deque(maxlen=LATENCY_WINDOW)  # ms, newest predictions
        self._last_predicted_ns = None  # receipt time of the state last predicted from
        self._thread: Optional[threading.Thread] = None
        #: what the inputs over the horizon of the last prediction were (for diagnostics)
        self.inputs = 'none yet'

    def set_model(self, model: RKGNNModel, loop: Optional[ClosedLoop] = None) -> None:
        """Predict with ``model`` from now on (case 1 with a fitted law: closed by ``loop``)."""
        self._published = _Published(model, loop)

    def request(self) -> None:
        """Ask for a prediction from the newest state (requests collapse while one runs)."""
        self._wanted.set()

    def published(self, prediction: Prediction) -> None:
        """Record that ``prediction`` was published now (its state's latency, if new)."""
        if prediction.received_ns is not None:
            latency = 1e-6 * (time.time_ns() - prediction.received_ns)  # ms, receipt -> publish
            with self._lock:
                self._latencies.append(latency)

    def latencies(self) -> np.ndarray:
        """Return the newest state-to-publish times (ms), oldest first."""
        with self._lock:
            return np.array(self._latencies)

    def warm_up(self, model: RKGNNModel) -> None:
        """Run the compiled rollout once in the calling thread, so predictions never compile."""
        if self._ready.is_set():
            return
        n = model.n_joints
        t = np.arange(3) * model.dt
        zeros = np.zeros((t.size, n))
        x0 = np.concatenate([model.scales.theta_center, np.zeros(n)])
        if model.case == 'torque':
            model.simulate(x0, t, tau=zeros)
        else:
            model.simulate(x0, t, theta_d=zeros, theta_d_dot=zeros)
        self._ready.set()

    def predict(self) -> bool:
        """Publish one prediction from the newest state now; return whether one was."""
        if not self._ready.is_set():
            return False
        model, loop = self._published
        latest, joints = self._ingestion.latest_state, self._ingestion.joints
        if model is None or latest is None or joints is None or model.joint_names != joints:
            return False
        cfg = self._config()
        step = cfg['model_step']
        k = max(1, int(round(cfg['prediction.horizon'] / step)))
        t = np.arange(k + 1) * step
        inputs = what = None
        if model.case == 'torque' and loop is not None and loop.model is model:
            inputs, what = self._desired_inputs(latest.t + t, loop.shift)
            if inputs is not None:  # closed loop with the fitted law, along the reference
                model, what = loop.closed, f'closed loop (fitted law), {what}'
        if inputs is None:
            inputs, what = self._inputs(model.case, latest.t + t, latest.tau)
        if inputs is None:
            return False
        x0 = np.concatenate([latest.theta, latest.theta_dot])
        states = model.simulate(x0, t, **inputs)  # (k+1, 2n)
        n = len(joints)
        positions = np.array(states[:, :n])
        velocities = np.array(states[:, n:2 * n])
        positions[0] = latest.theta
        velocities[0] = latest.theta_dot
        if not (np.isfinite(positions).all() and np.isfinite(velocities).all()):
            self._ingestion.reject('~/prediction', 'prediction', 'prediction_non_finite',
                                   'the model diverged over the horizon; prediction not '
                                   'published')
            return False
        sec, nanosec = latest.stamp
        new = latest.received_ns != self._last_predicted_ns  # not again from the same state
        self._last_predicted_ns = latest.received_ns
        self._publish(Prediction(serialize_joint_trajectory(
            Time(sec=sec, nanosec=nanosec), joints, t, positions, velocities),
            latest.received_ns if new else None,
            _state_ahead(latest.stamp, joints, t, positions, velocities,
                         cfg['prediction.lookahead'])))
        self.inputs = what
        return True

    def _inputs(self, case: str, times: np.ndarray, tau) -> Tuple[Optional[dict], str]:
        """Return the model inputs over absolute ``times`` and what they are."""
        if case == 'torque':
            if tau is None:
                return None, ''
            return {'tau': np.tile(tau, (times.size, 1))}, 'held torque'
        return self._desired_inputs(times)

    def _desired_inputs(self, times: np.ndarray, shift=None) -> Tuple[Optional[dict], str]:
        """
        Return θd, θ̇d over absolute ``times``: the reference, else the latest command held.

        The reference is evaluated exactly at the RKG stage times (no resampling);
        ``shift`` (n,) is added to θd (the fitted law's constant).
        """
        plan = self._ingestion.reference()
        if plan is not None and times[0] <= plan.end:
            return {'reference': _FromReference(plan, float(times[0]), shift)}, 'reference'
        command = self._ingestion.latest_command
        if command is None:
            return None, ''
        held = command if shift is None else command + shift
        return {'reference': _HeldCommand(held)}, 'held command'

    # ------------------------------------------------------------------ the thread

    def start(self) -> None:
        """Start the prediction thread."""
        self._thread = threading.Thread(target=self._run, name='rkgnn_prediction',
                                        daemon=True)
        self._thread.start()

    def stop(self) -> bool:
        """Stop and join the prediction thread; return False if it did not stop in time."""
        self._stop.set()
        self._wanted.set()
        thread = self._thread
        if thread is not None and thread.is_alive():
            thread.join(JOIN_TIMEOUT_S)
            return not thread.is_alive()
        return True

    def _run(self) -> None:
        """One prediction from the newest state per request, until stopped."""
        while not self._stop.is_set():
            if not self._wanted.wait(0.1):
                continue
            self._wanted.clear()
            if self._stop.is_set():
                break
            try:
                self.predict()
            except Exception:  # noqa: B902 - the thread must survive
                if self._stop.is_set():
                    break
                self._ingestion.internal_error('prediction')

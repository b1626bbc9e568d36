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
The search worker: the thread that runs the online identification policy.

:class:`SearchWorker` runs :class:`~rkgnn_ros.core.fitting.online.OnlineIdentification`
one step at a time: it observes (one consistent view of the parameters, the joints and
the stream times, the pause and reset requests, a capture of the buffer when the policy
asks for one), steps, and queues the policy's events in the outbox for the executor thread;
a new model is warmed up for the predictor and turned into YAML here first, so the
executor only publishes. It decides nothing itself.

It runs at the lowest CPU priority (nice 19) with the numba threads of the fitness kernel
one fewer than the cores, and BLAS (numpy's and scipy's OpenBLAS) on the calling thread
only, so the executor, the ingest and the prediction threads are never starved by a
generation or a linear fit. An exception in a step is logged with its traceback, counted
(``worker_error``), shown as state 'error', and the step is retried after a back-off
(0.5 s doubling to 10 s); the policy restarts the search after three in a row.
"""

import os
import sys
import threading
import traceback
from typing import Callable, Optional

from rkgnn_ros.core.fitting.fitness import interrupt_on
from rkgnn_ros.core.fitting.online import ModelUpdate, Observation, OnlineIdentification, Status
from rkgnn_ros.core.fitting.optimizers.cmaes import load_pycma
from rkgnn_ros.identification.publishing import ModelMessage
from rkgnn_ros.identification.threads import ThreadPart

__all__ = ['SearchWorker', 'single_threaded_blas']

IDLE_WAIT_S = 0.05
WORKER_NICE = 19
GIL_SWITCH_INTERVAL_S = 0.0001
BACKOFF_MIN_S = 0.5
BACKOFF_MAX_S = 10.0


class SearchWorker(ThreadPart):
    """
    The thread that steps the policy and queues its events.

    Parameters
    ----------
    ingestion : Ingestion
        Gives the view and the buffer captures; counts ``worker_error``.
    predictor : Predictor
        Warmed up with each new model before it is queued.
    outbox : Outbox
        Where the events go.
    alive : callable
        Returns False once the node shuts down (errors then end the thread quietly).
    published : RKGNNModel, optional
        The model published at start (loaded from a file): warmed up, handed to the policy.
    policy : callable
        Builds the policy from ``published`` and ``on_status`` (default
        :class:`OnlineIdentification`; tests pass their own).
    description : RobotDescription, optional
        Gives the structure of the joints (:mod:`.description`) for each observation.

    """

    thread_name = 'rkgnn_identifier'

    def __init__(self, ingestion, predictor, outbox, alive: Callable[[], bool] = lambda: True,
                 published=None, policy: Callable = OnlineIdentification, description=None):
        self._ingestion, self._predictor, self._outbox = ingestion, predictor, outbox
        self._alive, self._published, self._description = alive, published, description
        self._lock = threading.Lock()
        self._paused = False
        self._reset = False
        self._status = Status()
        self._policy = policy(published=published, on_status=self._set_status)
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None

    @property
    def status(self) -> Status:
        """Return the search's newest status."""
        return self._status

    def _set_status(self, status: Status) -> None:
        self._status = status

    def pause(self, on: bool) -> int:
        """Pause (True) or resume the search; return the generation it is at."""
        with self._lock:
            self._paused = bool(on)
        return self._status.generation

    def request_reset(self) -> None:
        """Restart the search before its next generation (the buffer is cleared apart)."""
        with self._lock:
            self._reset = True

    def stop(self) -> bool:
        """Stop and join the worker thread; what the policy runs in the background ends too."""
        close = getattr(self._policy, 'close', None)
        if close is not None:
            close()
        return super().stop()

    def _run(self) -> None:
        """One policy step per iteration until the stop event."""
        yield_to_callbacks()
        _late_imports()
        # stop() interrupts a generation between chunks (a big one takes minutes), so the
        # thread never outlives the node that owns it
        interrupt_on(self._stop)
        if self._published is not None:
            self._predictor.warm_up(self._published)
        backoff = BACKOFF_MIN_S
        errors = 0
        while not self._stop.is_set():
            try:
                ran = self.step()
                backoff, errors = BACKOFF_MIN_S, 0
            except Exception as exc:  # noqa: B902 - the worker must survive (item 23)
                if self._stop.is_set() or not self._alive():
                    break
                errors += 1
                self._ingestion.drops.count('worker', 'worker_error')
                self._outbox.log('error', f'identification worker failed ({errors} in a row), '
                                          f'retrying in {backoff:.1f} s: {exc!r}\n'
                                          f'{traceback.format_exc()}')
                self._queue(self._policy.report_error(exc, errors))
                self._stop.wait(backoff)
                backoff = min(2.0 * backoff, BACKOFF_MAX_S)
                continue
            if not ran:
                self._stop.wait(IDLE_WAIT_S)

    def step(self) -> bool:
        """
        Observe, step the policy once, queue its events; return whether a generation ran.

        The policy may take new captures of the buffer during the step (``recapture``).
        """
        config, joints, buffer, received = self._ingestion.view()
        with self._lock:
            reset, self._reset = self._reset, False
            paused = self._paused
        structure = None if self._description is None else self._description.structure(joints)
        captures = []

        def recapture():
            captures.append(buffer.capture())
            return captures[-1]
        obs = Observation(config.settings, joints, received, paused, reset,
                          estimate_velocity=self._ingestion.velocity_estimated,
                          structure=structure,
                          recapture=None if buffer is None else recapture)
        if buffer is not None and self._policy.data_due(obs):
            obs = obs._replace(data=recapture())
        result = self._policy.step(obs)
        for capture in captures:
            buffer.count_failures(capture)
        self._queue(result.events)
        return result.ran

    def _queue(self, events) -> None:
        for event in events:
            if isinstance(event, ModelUpdate):
                self._predictor.warm_up(event.model)
                event = ModelMessage(event, event.model.to_yaml())
            self._outbox.put(event)


def _late_imports() -> None:
    """
    Import what the node's modules import at first use, here at low priority.

    pycma (1.5 s: it brings scipy.stats and matplotlib.pyplot) and scipy.signal (0.8 s) were
    most of the identifier's start-up before it could take its first joint_states; the
    worker loads them while the first data are buffered.
    """
    import scipy.signal  # noqa: F401
    load_pycma()


def yield_to_callbacks() -> None:
    """
    Give the calling (worker) thread a lower CPU priority than the node's other threads.

    The fitness kernel runs numba threads on every core; at equal priority they starve the
    executor, ingest and prediction threads, and states and predictions queue up. On Linux
    nice is per thread and the numba pool, created from this thread by its first parallel
    call, inherits it. The GIL switch interval is shortened too, so a callback waits less
    for the worker's Python code. The worker's numba kernels use one core fewer than the
    machine has (numba's thread count is per calling thread): the nice value does not reach
    a pool created earlier by another thread, and a 2-core machine must keep a core for the
    callbacks.
    """
    import numba
    numba.set_num_threads(max(1, min(numba.config.NUMBA_NUM_THREADS,
                                     (os.cpu_count() or 1) - 1)))
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), WORKER_NICE)
    except (AttributeError, OSError):  # not Linux, or not permitted: run at equal priority
        pass
    sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)
    single_threaded_blas()


def single_threaded_blas() -> None:
    """
    Run BLAS and LAPACK on the calling thread only, for the whole process (threadpoolctl).

    The node's linear algebra is small (tens to hundreds of columns). OpenBLAS's own
    threads, created at nice 0 when numpy is imported, gain nothing there and spin while
    they wait: on a 2-core machine beside other work a 1,500 x 21 product took 2.3 ms
    instead of 0.09 ms, and 100 samples offered to the excitation memory 4.9 s instead of
    0.17 s. Without threadpoolctl, BLAS keeps its threads.
    """
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # optional: the node runs without it, only slower
        return
    threadpool_limits(limits=1, user_api='blas')

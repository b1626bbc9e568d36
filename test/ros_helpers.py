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
"""Helpers for tests whose executor spins in a background thread."""

from contextlib import contextmanager
import threading
import time

from rcl_interfaces.msg import Log
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy


def run_in_executor(executor, fn, timeout=10.0):
    """
    Run ``fn`` in the executor's own thread, between two waits, and return its result.

    Destroying a publisher, subscription or node from another thread while the executor
    is building its wait set makes rclpy (Jazzy 7.1) raise in ``add_to_wait_set`` and the
    spinning thread dies: the QoS-event waitables it collected are already invalid. Run as
    an executor task, the destruction happens before the next collection.
    """
    done = threading.Event()
    outcome = {}

    def task():
        try:
            outcome['value'] = fn()
        except BaseException as exc:  # re-raised in the caller's thread
            outcome['error'] = exc
        finally:
            done.set()
    executor.create_task(task)
    if not done.wait(timeout):
        raise TimeoutError(f'the executor did not run {fn!r} within {timeout} s')
    if 'error' in outcome:
        raise outcome['error']
    return outcome.get('value')


def retire_node(executor, node, timeout=10.0):
    """Remove ``node`` from a spinning executor and destroy it in the executor's thread."""
    def retire():
        executor.remove_node(node)
        node.destroy_node()
    run_in_executor(executor, retire, timeout)


def wait_for(predicate, timeout, interval=0.02):
    """Poll ``predicate`` until it is truthy or ``timeout`` s pass; return its last value."""
    end = time.monotonic() + timeout
    while True:
        value = predicate()
        if value or time.monotonic() > end:
            return value
        time.sleep(interval)


class Rosout:
    """
    The log lines of nodes, as any user sees them: ``/rosout`` (transient local).

    ``lines(logger, *words, level=...)`` returns the texts a logger published that
    contain every word (``level``: 'info', 'warning' or 'error'; None for all).
    """

    LEVELS = {'info': Log.INFO, 'warning': Log.WARN, 'error': Log.ERROR}

    def __init__(self, node):
        self._lock = threading.Lock()
        self._logs = []
        node.create_subscription(Log, '/rosout', self._add, QoSProfile(
            depth=1000, reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL))

    def _add(self, msg):
        with self._lock:
            self._logs.append((msg.name, msg.level, msg.msg))

    def lines(self, logger, *words, level=None):
        wanted = self.LEVELS.get(level)
        with self._lock:
            logs = list(self._logs)
        return [text for name, lvl, text in logs if name == logger
                and (wanted is None or lvl == wanted) and all(w in text for w in words)]


def stamp_ns(msg) -> int:
    """Return a message's header stamp in nanoseconds."""
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


class Spinner:
    """
    Spin ``executor`` in a background thread until :meth:`stop`.

    ``Executor.shutdown`` from another thread races the spinning one in rclpy (Jazzy 7.1):
    it destroys the executor's guard condition at once, and a spin that is building its
    wait set then raises ("wait set is empty", or the context is not valid) and its thread
    dies with an unhandled exception. Here the thread spins in short waits and leaves on
    its own; the executor is shut down after it has gone.
    """

    def __init__(self, executor, period: float = 0.05):
        self.executor = executor
        self._period = period
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self):
        while not self._stop.is_set() and self.executor.context.ok():
            self.executor.spin_once(timeout_sec=self._period)

    def stop(self, timeout: float = 10.0) -> None:
        """Stop spinning, wait for the thread, then shut the executor down."""
        self._stop.set()
        self._thread.join(timeout)
        self.executor.shutdown(timeout_sec=2.0)


@contextmanager
def spinning_context(domain_id):
    """Yield (context, executor) on a private context, the executor spinning in a thread."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain_id)
    executor = SingleThreadedExecutor(context=context)
    spinner = Spinner(executor)
    try:
        yield context, executor
    finally:
        spinner.stop()
        rclpy.try_shutdown(context=context)

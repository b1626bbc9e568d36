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
The identifier's threads: each a daemon, started and joined the same way.

A part that runs in a thread derives from :class:`ThreadPart`: it has a ``_stop`` event
and a ``_run`` method that returns once the event is set.
"""

import threading
from typing import Callable, Optional

__all__ = ['JOIN_TIMEOUT_S', 'ThreadPart', 'join_thread', 'start_thread']

#: Longest wait (s) for a thread to end when its part stops.
JOIN_TIMEOUT_S = 10.0


def start_thread(target: Callable[[], None], name: str) -> threading.Thread:
    """Start and return a daemon thread named ``name`` running ``target``."""
    thread = threading.Thread(target=target, name=name, daemon=True)
    thread.start()
    return thread


def join_thread(thread: Optional[threading.Thread]) -> bool:
    """Join ``thread`` for at most :data:`JOIN_TIMEOUT_S`; return whether it has ended."""
    if thread is not None and thread.is_alive():
        thread.join(JOIN_TIMEOUT_S)
        return not thread.is_alive()
    return True


class ThreadPart:
    """A part whose ``_run`` runs in a daemon thread named :attr:`thread_name`."""

    thread_name = 'rkgnn'
    _thread: Optional[threading.Thread] = None

    def start(self) -> None:
        """Start the thread."""
        self._thread = start_thread(self._run, self.thread_name)

    def stop(self) -> bool:
        """Stop and join the thread; return False if it did not stop in time."""
        self._stop.set()
        self._wake()
        return join_thread(self._thread)

    def _wake(self) -> None:
        """Wake ``_run`` where it waits on more than the stop event (by default it does not)."""

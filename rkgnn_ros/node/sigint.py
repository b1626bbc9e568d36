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
SIGINT that ends a node's spin without a KeyboardInterrupt landing anywhere.

rclpy's signal handler (installed by ``rclpy.init``) shuts the contexts down, which ends
``spin`` with ``ExternalShutdownException``, and then calls the handler that was there
before it: Python's, which raises ``KeyboardInterrupt`` in the main thread at whatever
bytecode it is running. When that is a ``__del__`` (rclpy's ``Task.__del__`` during a
spin, seen under load), Python cannot raise it and prints "Exception ignored in ...
Traceback ... KeyboardInterrupt" on stderr instead, and the node goes on to a clean exit
with a traceback in its log.

:class:`Interrupt` is the handler rclpy chains to: it must be installed before
``rclpy.init``. Until :meth:`Interrupt.arm` (called just before spinning) it raises
``KeyboardInterrupt`` as Python's does, so a SIGINT while the node is built stops it
there; once armed, it only records the signal: the spin ends through rclpy's shutdown,
and a second SIGINT during the teardown (joining threads, saving the model) does not cut
it short (the teardown watchdog ends a teardown that hangs).
"""

import signal

__all__ = ['Interrupt']


class Interrupt:
    """The SIGINT handler of a node's ``main`` (see the module docstring)."""

    def __init__(self):
        self.armed = False
        self.count = 0

    def install(self) -> bool:
        """Install the handler (main thread, before ``rclpy.init``); False if not possible."""
        try:
            signal.signal(signal.SIGINT, self._handle)
        except ValueError:  # not the main thread
            return False
        return True

    def arm(self) -> None:
        """From now on a SIGINT is only recorded: rclpy's shutdown ends the spin."""
        self.armed = True

    def _handle(self, signum, frame) -> None:
        self.count += 1
        if not self.armed:
            raise KeyboardInterrupt

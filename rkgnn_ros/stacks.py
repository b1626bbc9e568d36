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
Where a node waits when it does not answer, and an end to a teardown that hangs.

``kill -USR1 <pid>`` prints every thread's Python stack of a running node to stderr (a
callback that never returns, a hang at shutdown), without stopping the node.
"""

import faulthandler
import os
import signal
import sys
import threading


def dump_stacks_on_sigusr1() -> bool:
    """Register the dump; return False where the platform has no SIGUSR1."""
    usr1 = getattr(signal, 'SIGUSR1', None)
    if usr1 is None:
        return False
    faulthandler.register(usr1, all_threads=True)
    return True


class TeardownWatchdog:
    """
    Ends the process if the middleware's teardown hangs.

    ``destroy_node`` and ``rclpy.try_shutdown`` wait inside the DDS library; under load a
    peer shutting down at the same moment has been seen to keep one of them waiting for
    over a minute. A node asked to stop must stop: after ``grace`` seconds the watchdog
    prints every thread's stack to stderr (where it hung) and exits with ``code``. The
    node's own work (the model file, the last messages) is done before it is armed.
    """

    def __init__(self, grace: float = 15.0):
        self.grace = float(grace)
        self._timer = None

    def arm(self, code: int) -> None:
        self._timer = threading.Timer(self.grace, self._expire, args=(int(code),))
        self._timer.daemon = True
        self._timer.start()

    def disarm(self) -> None:
        if self._timer is not None:
            self._timer.cancel()

    def _expire(self, code: int) -> None:
        try:
            sys.stderr.write(f'teardown still running after {self.grace:.0f} s: exiting with '
                             f'code {code}; the threads were at:\n')
            faulthandler.dump_traceback(file=sys.stderr, all_threads=True)
            sys.stderr.flush()
            sys.stdout.flush()
        finally:
            os._exit(code)

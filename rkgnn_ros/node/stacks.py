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
Where a node's threads wait, and an end to a teardown that hangs.

``kill -USR1 <pid>`` prints every thread's Python stack to stderr and the node goes on (a
callback that never returns, a thread that stalls). It is printed by a Python signal
handler, between two bytecodes of the main thread: safe while other threads run
(``faulthandler`` reading other threads' frames from the signal itself crashed a busy
identifier within three signals). A process stuck in C code does not run it: ``kill
-ABRT <pid>`` then prints the stacks through ``faulthandler`` and ends the process.
"""

import faulthandler
import signal
import sys
import threading
import traceback

from .sigint import Interrupt


def format_stacks() -> str:
    """Return every thread's Python stack, newest call last, as text."""
    threads = {thread.ident: thread for thread in threading.enumerate()}
    parts = []
    for ident, frame in sys._current_frames().items():
        thread = threads.get(ident)
        name = '?' if thread is None else thread.name
        native = '?' if thread is None else thread.native_id    # the TID in /proc, top -H
        parts.append(f'Thread {name} ({ident:#x}, TID {native}):\n')
        parts.extend(traceback.format_stack(frame))
    return ''.join(parts)


def _print_stacks(signum, frame) -> None:
    sys.stderr.write(format_stacks())
    sys.stderr.flush()


def dump_stacks_on_sigusr1() -> bool:
    """
    Print the stacks on SIGUSR1 and on a fatal signal; return False without SIGUSR1.

    Call it from the main thread (Python installs signal handlers there only).
    """
    faulthandler.enable()        # SIGSEGV, SIGABRT, ...: the stacks, then the process ends
    usr1 = getattr(signal, 'SIGUSR1', None)
    if usr1 is None:
        return False
    signal.signal(usr1, _print_stacks)
    return True


class TeardownWatchdog:
    """
    Ends the process if the middleware's teardown hangs.

    ``destroy_node`` and ``rclpy.try_shutdown`` wait inside the DDS library, holding the
    GIL: no Python thread could end the process then. ``faulthandler``'s watchdog is a C
    thread: after ``grace`` seconds it prints every thread's stack to stderr (headed
    ``Timeout``) and exits with code 1. The node's own work (the model file, the last
    messages) is done before it is armed.
    """

    def __init__(self, grace: float = 15.0):
        self.grace = float(grace)

    def arm(self) -> None:
        faulthandler.dump_traceback_later(self.grace, exit=True)

    def disarm(self) -> None:
        faulthandler.cancel_dump_traceback_later()


def start_up(args=None) -> Interrupt:
    """
    Print the stacks on SIGUSR1, take SIGINT, init rclpy; return the SIGINT handler.

    The handler is installed before ``rclpy.init`` (rclpy's chains to it); arm it once the
    node exists: a SIGINT then ends the spin and raises nothing.
    """
    import rclpy
    dump_stacks_on_sigusr1()
    interrupt = Interrupt()
    interrupt.install()
    rclpy.init(args=args)
    return interrupt


def tear_down(node) -> None:
    """Destroy ``node`` (if any) and shut rclpy down, under a :class:`TeardownWatchdog`."""
    import rclpy
    watchdog = TeardownWatchdog()
    watchdog.arm()
    if node is not None:
        node.destroy_node()
    rclpy.try_shutdown()
    watchdog.disarm()

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

"""A hung node can be asked where it waits, and a hung teardown ends (rkgnn_ros.stacks)."""

import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

pytestmark = pytest.mark.skipif(not hasattr(signal, 'SIGUSR1'), reason='no SIGUSR1 here')


def _python(code):
    return subprocess.Popen([sys.executable, '-c', textwrap.dedent(code)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=dict(os.environ, PYTHONUNBUFFERED='1'))


def test_sigusr1_prints_every_threads_stack_and_the_process_goes_on():
    p = _python("""
        import sys, threading, time
        from rkgnn_ros.stacks import dump_stacks_on_sigusr1
        assert dump_stacks_on_sigusr1()
        def waiting_in_a_side_thread():
            time.sleep(60)
        threading.Thread(target=waiting_in_a_side_thread, daemon=True).start()
        print('ready', flush=True)
        for _ in range(600):
            time.sleep(0.1)
        print('still here', flush=True)
        """)
    try:
        assert p.stdout.readline().strip() == 'ready'
        time.sleep(0.5)                      # the side thread is in its sleep
        p.send_signal(signal.SIGUSR1)
        time.sleep(1.0)
        assert p.poll() is None              # the dump does not stop the process
    finally:
        p.kill()
        _, err = p.communicate(timeout=30)
    assert 'waiting_in_a_side_thread' in err
    assert 'Current thread' in err or 'Thread 0x' in err


def test_a_hung_teardown_ends_with_the_code_and_the_stacks():
    p = _python("""
        import time
        from rkgnn_ros.stacks import TeardownWatchdog
        watchdog = TeardownWatchdog(grace=0.5)
        watchdog.arm(3)
        def teardown_that_hangs():
            time.sleep(60)
        teardown_that_hangs()
        """)
    _, err = p.communicate(timeout=30)
    assert p.returncode == 3
    assert 'teardown still running after' in err
    assert 'teardown_that_hangs' in err


def test_a_teardown_in_time_is_left_alone():
    p = _python("""
        import time
        from rkgnn_ros.stacks import TeardownWatchdog
        watchdog = TeardownWatchdog(grace=0.5)
        watchdog.arm(3)
        watchdog.disarm()
        time.sleep(1.5)
        print('done', flush=True)
        """)
    out, err = p.communicate(timeout=30)
    assert p.returncode == 0, err
    assert out.strip() == 'done'
    assert 'teardown still running' not in err

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

"""A hung node can be asked where it waits, and a hung teardown ends (rkgnn_ros.node.stacks)."""

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
        import threading, time
        from rkgnn_ros.node.stacks import dump_stacks_on_sigusr1
        assert dump_stacks_on_sigusr1()
        def waiting_in_a_side_thread():
            time.sleep(60)
        threading.Thread(target=waiting_in_a_side_thread, name='side', daemon=True).start()
        print('ready', flush=True)
        for _ in range(600):
            time.sleep(0.1)
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
    assert 'Thread side' in err and 'waiting_in_a_side_thread' in err
    assert 'Thread MainThread' in err


def test_a_stream_of_sigusr1_beside_busy_threads_does_not_crash_the_process():
    # (faulthandler's own SIGUSR1 dump, which reads other threads' frames from the signal,
    # crashed a busy identifier with SIGSEGV within three signals; this handler runs as
    # Python code in the main thread)
    p = _python("""
        import threading, time
        import numpy as np
        from rkgnn_ros.node.stacks import dump_stacks_on_sigusr1
        dump_stacks_on_sigusr1()
        stop = threading.Event()
        def busy(seed):
            rng = np.random.default_rng(seed)
            while not stop.is_set():
                sorted(rng.standard_normal(200).tolist())
                [np.linalg.norm(rng.standard_normal(5)) for _ in range(20)]
        threads = [threading.Thread(target=busy, args=(k,)) for k in range(2)]
        for t in threads:
            t.start()
        print('ready', flush=True)
        time.sleep(6.0)
        stop.set()
        for t in threads:
            t.join()
        print('done', flush=True)
        """)
    assert p.stdout.readline().strip() == 'ready'
    sent = 0
    while p.poll() is None and sent < 150:
        p.send_signal(signal.SIGUSR1)
        sent += 1
        time.sleep(0.02)
    out, err = p.communicate(timeout=60)
    assert p.returncode == 0, err[-2000:]
    assert out.strip() == 'done'
    assert err.count('Thread MainThread') >= 10


def test_a_hung_teardown_ends_with_the_stacks():
    p = _python("""
        import time
        from rkgnn_ros.node.stacks import TeardownWatchdog
        watchdog = TeardownWatchdog(grace=0.5)
        watchdog.arm()
        def teardown_that_hangs():
            time.sleep(60)
        teardown_that_hangs()
        """)
    _, err = p.communicate(timeout=30)
    assert p.returncode == 1
    assert 'Timeout' in err
    assert 'teardown_that_hangs' in err


def test_a_teardown_in_time_is_left_alone():
    p = _python("""
        import time
        from rkgnn_ros.node.stacks import TeardownWatchdog
        watchdog = TeardownWatchdog(grace=0.5)
        watchdog.arm()
        watchdog.disarm()
        time.sleep(1.5)
        print('done', flush=True)
        """)
    out, err = p.communicate(timeout=30)
    assert p.returncode == 0, err
    assert out.strip() == 'done'
    assert 'Timeout' not in err

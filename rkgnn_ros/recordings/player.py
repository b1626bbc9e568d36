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
A small recording player: a rosbag2's messages and ``/clock`` at any speed.

What ``ros2 bag play --clock -r RATE`` does, enough to replay a recording to the
identifier under ``use_sim_time`` where the ROS 2 command line is not installed (tests,
benchmarks): :class:`RecordingPlayer` publishes each recorded message, serialized as it was
recorded, when its recording time comes, with ``/clock`` following the recording's time,
``rate`` times faster than it was recorded.
"""

import importlib
import threading
import time
from typing import Dict, Optional, Sequence

from rkgnn_ros.recordings.reader import open_recording, read_messages
from rosgraph_msgs.msg import Clock

__all__ = ['RecordingPlayer']

#: /clock is published when the recording's time advanced by this much (s).
CLOCK_STEP_S = 0.005


def _message_class(type_name: str):
    """Return the rclpy message class of 'pkg/msg/Name' (ImportError if not installed)."""
    package, _, name = type_name.split('/')
    return getattr(importlib.import_module(f'{package}.msg'), name)


class RecordingPlayer:
    """
    Publish a recording's messages and ``/clock`` on ``node``, ``rate`` times as fast.

    Parameters
    ----------
    node : rclpy.node.Node
        Publishes; its namespace applies to relative topic names only (recorded topics are
        absolute).
    path : str
        The recording (:func:`~rkgnn_ros.recordings.reader.open_recording`).
    topics : sequence of str, optional
        Recorded topics to play (default every topic whose type is installed).
    rate : float
        Speed relative to the recording, > 0.

    """

    def __init__(self, node, path: str, topics: Optional[Sequence[str]] = None,
                 rate: float = 1.0):
        if not rate > 0.0:
            raise ValueError(f'rate must be > 0, got {rate}')
        recording = open_recording(path)
        try:
            wanted = list(topics) if topics else list(recording.types)
            self._publishers: Dict[str, object] = {}
            self.skipped = []
            for topic in wanted:
                try:
                    cls = _message_class(recording.types[topic])
                except (ImportError, AttributeError, ValueError, KeyError):
                    self.skipped.append(topic)
                    continue
                self._publishers[topic] = node.create_publisher(cls, topic, 100)
            self._messages, self.truncated = read_messages(recording, list(self._publishers))
        finally:
            recording.close()
        self._clock = node.create_publisher(Clock, '/clock', 10)
        self.rate = float(rate)
        self.published = 0

    @property
    def duration(self) -> float:
        """Return the recording's span in its own seconds."""
        if not self._messages:
            return 0.0
        return (self._messages[-1].log_ns - self._messages[0].log_ns) * 1e-9

    def play(self, stop: Optional[threading.Event] = None) -> int:
        """Play the whole recording in the calling thread; return the messages published."""
        if not self._messages:
            return 0
        first = self._messages[0].log_ns
        start = time.monotonic()
        last_clock = None
        for message in self._messages:
            due = start + (message.log_ns - first) * 1e-9 / self.rate
            while True:
                if stop is not None and stop.is_set():
                    return self.published
                wait = due - time.monotonic()
                if wait <= 0.0:
                    break
                time.sleep(min(wait, 0.05))
            if last_clock is None or message.log_ns - last_clock >= CLOCK_STEP_S * 1e9:
                self._publish_clock(message.log_ns)
                last_clock = message.log_ns
            self._publishers[message.topic].publish(message.raw)
            self.published += 1
        self._publish_clock(self._messages[-1].log_ns)
        return self.published

    def _publish_clock(self, log_ns: int) -> None:
        msg = Clock()
        msg.clock.sec, msg.clock.nanosec = divmod(int(log_ns), 1_000_000_000)
        self._clock.publish(msg)

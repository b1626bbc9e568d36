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
Files a user names (a parameters file, a URDF, a recording, a model): read without hanging.

A path can name a FIFO (``open`` blocks until a writer comes, forever), a device such as
``/dev/zero`` (endless), a directory, or a regular file of any size. :func:`read_bounded`
opens non-blocking, checks on the descriptor (``fstat``) that it is a regular file no
larger than the budget, and reads at most the budget plus one byte, so neither a FIFO nor
a 1 GB file costs more than a refusal. :func:`file_problem` says the same from ``stat``
for files another library will open (a recording's storage files).
"""

import os
import stat
from typing import Optional

__all__ = ['InputFileError', 'file_kind', 'file_problem', 'read_bounded']

_KINDS = {stat.S_IFIFO: 'a FIFO', stat.S_IFCHR: 'a character device',
          stat.S_IFBLK: 'a block device', stat.S_IFDIR: 'a directory',
          stat.S_IFSOCK: 'a socket', stat.S_IFLNK: 'a symbolic link'}


class InputFileError(ValueError):
    """A file that is not read; the message says why (``it is a FIFO, ...``)."""


def file_kind(mode: int) -> str:
    """Return what a ``st_mode`` is, in words ('a FIFO', 'a directory', ...)."""
    return _KINDS.get(stat.S_IFMT(mode), f'not a regular file (mode {oct(mode)})')


def file_problem(path: str, max_bytes: Optional[int] = None) -> Optional[str]:
    """
    Return why ``path`` is not a regular file (of at most ``max_bytes``), or None.

    From ``stat`` (symbolic links followed), without opening it: for files that another
    library opens.
    """
    try:
        info = os.stat(path)
    except OSError as exc:
        return f'cannot read it: {exc.strerror or exc}'
    if not stat.S_ISREG(info.st_mode):
        return f'it is {file_kind(info.st_mode)}, not a regular file'
    if max_bytes is not None and info.st_size > max_bytes:
        return f'it has {info.st_size} bytes, more than the limit of {max_bytes}'
    return None


def read_bounded(path: str, max_bytes: int) -> bytes:
    """
    Return the bytes of the regular file ``path``, at most ``max_bytes`` of them.

    Never blocks on a FIFO and never reads more than ``max_bytes + 1`` bytes.

    Raises
    ------
    InputFileError
        It cannot be opened, is not a regular file, or is larger than ``max_bytes``.

    """
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC)
    except OSError as exc:
        raise InputFileError(f'cannot open it: {exc.strerror or exc}') from None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise InputFileError(f'it is {file_kind(info.st_mode)}, not a regular file')
        if info.st_size > max_bytes:
            raise InputFileError(f'it has {info.st_size} bytes, more than the limit of '
                                 f'{max_bytes}')
        chunks, size = [], 0
        while size <= max_bytes:
            chunk = os.read(fd, max_bytes + 1 - size)
            if not chunk:
                break
            chunks.append(chunk)
            size += len(chunk)
    except OSError as exc:
        raise InputFileError(f'cannot read it: {exc.strerror or exc}') from None
    finally:
        os.close(fd)
    if size > max_bytes:
        raise InputFileError(f'it grew past the limit of {max_bytes} bytes while read')
    return b''.join(chunks)

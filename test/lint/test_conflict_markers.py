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

"""No text file of the package carries a merge's conflict markers."""

import pathlib
import re

from repo_paths import REPO_ROOT

ROOT = pathlib.Path(REPO_ROOT)
MARKER = re.compile(r'^(<{7}|={7}|>{7})( |$)', re.MULTILINE)
SUFFIXES = {'.py', '.md', '.yaml', '.yml', '.cfg', '.xml', '.txt', '.json', '.launch'}


def _files():
    for folder in ('rkgnn_ros', 'config', 'bench', 'tools', 'test', 'launch', '.ci'):
        base = ROOT / folder
        if base.is_dir():
            yield from (p for p in base.rglob('*') if p.suffix in SUFFIXES and p.is_file())
    yield from (p for p in ROOT.iterdir() if p.is_file() and p.suffix in SUFFIXES | {''})


def test_no_file_carries_conflict_markers():
    marked = []
    for path in _files():
        try:
            text = path.read_text(encoding='utf-8')
        except (UnicodeDecodeError, OSError):
            continue
        if MARKER.search(text):
            marked.append(str(path.relative_to(ROOT)))
    assert not marked, f'conflict markers in {marked}'


def test_the_marker_pattern_finds_a_marker():
    assert MARKER.search('text\n' + '<' * 7 + ' HEAD\nmore\n')
    assert not MARKER.search('a table row\n|===|\n')

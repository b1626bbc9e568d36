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
A translator of straight-line MATLAB functions (Symbolic Math Toolbox output) into numpy.

A published identified model often comes as ``.m`` files: ``function out = f(q, dq)``,
then statements ``name = expression;``. :func:`parse_function` reads such a text once
and returns a :class:`MatlabFunction` that evaluates it vectorised over samples: every
input is an array (..., n) and ``q(k)`` is ``q[..., k - 1]``, so one call computes all
samples. The text is parsed into closures (no ``eval`` of file contents).

The subset understood, which is what generated model files use:

- numbers, names, ``+ - .* ./ .^ * / ^`` with MATLAB's precedence (power binds tighter
  than a unary minus and groups from the left), parentheses;
- ``*``, ``/`` and ``^`` are taken element-wise: equal to MATLAB where one side is a
  scalar, the only use generated scalar code makes of them;
- ``sin cos tan exp log sqrt abs``, ``length(x)`` (the last axis), ``zeros(...)``, ``pi``;
- indexing ``v(k)``, ``m(r, c)``, ``m(r, :)`` with integer literals (1-based);
- matrix literals ``[a, b; c, d]`` (``,`` between elements, ``;`` or a new line between
  rows); a column or a row gives a vector (..., k), anything else (..., rows, cols);
- ``...`` continuations and ``%`` comments;
- ``for i = 1:N`` ... ``end`` whose body indexes by ``i`` only and carries nothing from
  one pass to the next: it runs once on whole vectors (``v(i)`` is ``v``).

Anything else (strings, transposes, ``if``, whitespace-separated matrix elements, a
loop-carried value, an undefined name) raises :class:`MatlabError` naming the line.
"""

import re
from typing import Callable, Dict, List, NamedTuple, Optional, Sequence

import numpy as np

__all__ = ['MatlabError', 'MatlabFunction', 'load_function', 'parse_function']

_FUNCTIONS = {'sin': np.sin, 'cos': np.cos, 'tan': np.tan, 'exp': np.exp, 'log': np.log,
              'sqrt': np.sqrt, 'abs': np.abs}
_CONSTANTS = {'pi': np.pi}
_TOKEN = re.compile(r"""
    (?P<space>[ \t]+)
  | (?P<number>(?:\d+(?:\.(?![*/^])\d*)?|\.\d+)(?:[eE][+-]?\d+)?)
  | (?P<name>[A-Za-z_][A-Za-z_0-9]*)
  | (?P<op>\.\*|\./|\.\^|[-+*/^()\[\],;=:])
""", re.VERBOSE)
_KEYWORDS = {'if', 'else', 'elseif', 'while', 'switch', 'case', 'otherwise', 'return',
             'break', 'continue', 'global', 'persistent', 'try', 'catch'}


class MatlabError(ValueError):
    """A MATLAB text outside the supported subset (module docstring); says where."""


class _Token(NamedTuple):
    kind: str
    text: str
    spaced: bool    # whitespace before it


class _Statement(NamedTuple):
    target: str
    run: Callable
    reads: frozenset
    line: int
    plain_reads: frozenset = frozenset()


def _logical_lines(text: str):
    """Yield (line number, text): comments dropped, continuations and open brackets joined."""
    pending, start, depth = '', 0, 0
    for number, raw in enumerate(text.splitlines(), 1):
        if "'" in raw.split('%', 1)[0]:
            raise MatlabError(f'line {number}: strings and transposes are not supported')
        line = raw.split('%', 1)[0]
        continued = '...' in line
        if continued:
            line = line.split('...', 1)[0]
        if not pending:
            start = number
        depth += line.count('[') - line.count(']')
        pending += line
        if continued:
            continue
        if depth > 0:
            pending += ';'          # a new line inside a matrix literal ends a row
            continue
        if pending.strip():
            yield start, pending
        pending = ''
    if pending.strip() or depth:
        raise MatlabError(f'line {start}: the text ends inside a statement')


def _tokens(text: str, line: int) -> List[_Token]:
    out, position, spaced = [], 0, False
    while position < len(text):
        match = _TOKEN.match(text, position)
        if match is None:
            raise MatlabError(f'line {line}: unexpected {text[position:position + 10]!r}')
        position = match.end()
        if match.lastgroup == 'space':
            spaced = True
            continue
        out.append(_Token(match.lastgroup, match.group(), spaced))
        spaced = False
    return out


def _split(tokens: List[_Token], separators) -> List[List[_Token]]:
    """Split tokens at separators outside brackets and parentheses."""
    parts, current, depth = [], [], 0
    for token in tokens:
        if token.text in '([':
            depth += 1
        elif token.text in ')]':
            depth -= 1
        if depth == 0 and token.kind == 'op' and token.text in separators:
            parts.append(current)
            current = []
        else:
            current.append(token)
    parts.append(current)
    return parts


def _reduce(values, ops):
    """Return the left-to-right result of ``values[0] op values[1] ...``."""
    def run(env):
        acc = values[0](env)
        for op, value in zip(ops, values[1:]):
            acc = op(acc, value(env))
        return acc
    return run


class _Parser:
    """Recursive descent over one statement's expression; builds closures env -> value."""

    _ADD = {'+': np.add, '-': np.subtract}
    _MUL = {'*': np.multiply, '.*': np.multiply, '/': np.true_divide, './': np.true_divide}

    def __init__(self, tokens: List[_Token], line: int, known: Dict[str, bool],
                 loop: Optional[str]):
        # known: name -> whether it holds a matrix (rows and columns; else a vector/scalar)
        self.tokens, self.line, self.known, self.loop = tokens, line, known, loop
        self.at = 0
        self.reads = set()          # every name read
        self.plain_reads = set()    # names read other than as name(i) in a loop
        self.matrix_value = False   # a matrix literal or a whole matrix is used
        self.bracket = False

    def fail(self, message: str):
        raise MatlabError(f'line {self.line}: {message}')

    def peek(self) -> Optional[_Token]:
        return self.tokens[self.at] if self.at < len(self.tokens) else None

    def take(self, text: Optional[str] = None) -> _Token:
        token = self.peek()
        if token is None or (text is not None and token.text != text):
            self.fail(f'expected {text or "more"}, got {token.text if token else "the end"}')
        self.at += 1
        return token

    def whole(self):
        run = self.additive()
        if self.peek() is not None:
            self.fail(f'unexpected {self.peek().text!r}')
        return run

    def additive(self):
        values, ops = [self.product()], []
        while self.peek() is not None and self.peek().text in self._ADD:
            token = self.peek()
            if self.bracket and token.spaced and self.at + 1 < len(self.tokens) \
                    and not self.tokens[self.at + 1].spaced:
                self.fail('whitespace-separated matrix elements are not supported')
            ops.append(self._ADD[self.take().text])
            values.append(self.product())
        return values[0] if not ops else _reduce(values, ops)

    def product(self):
        values, ops = [self.unary()], []
        while self.peek() is not None and self.peek().text in self._MUL:
            ops.append(self._MUL[self.take().text])
            values.append(self.unary())
        return values[0] if not ops else _reduce(values, ops)

    def unary(self):
        token = self.peek()
        if token is not None and token.text in '+-':
            self.take()
            inner = self.unary()
            return inner if token.text == '+' else (lambda env: np.negative(inner(env)))
        return self.power()

    def power(self):
        values, ops = [self.primary()], []
        while self.peek() is not None and self.peek().text in ('^', '.^'):
            self.take()
            ops.append(np.power)
            values.append(self.exponent())
        return values[0] if not ops else _reduce(values, ops)

    def exponent(self):
        token = self.peek()
        if token is not None and token.text in '+-':
            self.take()
            inner = self.exponent()
            return inner if token.text == '+' else (lambda env: np.negative(inner(env)))
        return self.primary()

    def primary(self):
        token = self.take()
        if token.kind == 'number':
            value = float(token.text)
            return lambda env: value
        if token.text == '(':
            inner = self.additive()
            self.take(')')
            return inner
        if token.text == '[':
            return self.matrix()
        if token.kind != 'name':
            self.fail(f'unexpected {token.text!r}')
        return self.named(token.text)

    def named(self, name: str):
        called = self.peek() is not None and self.peek().text == '('
        if name in self.known:
            self.reads.add(name)
            if not called:
                self.plain_reads.add(name)
                self.matrix_value |= self.known[name]
                return lambda env: env[name]
            return self.index(name)
        if name in _CONSTANTS and not called:
            value = _CONSTANTS[name]
            return lambda env: value
        if not called or (name not in _FUNCTIONS and name not in ('length', 'zeros')):
            self.fail(f'{name} is not defined')
        self.take('(')
        args = [self.additive()]
        while self.peek() is not None and self.peek().text == ',':
            self.take(',')
            args.append(self.additive())
        self.take(')')
        if name == 'length':
            return lambda env: float(np.shape(args[0](env))[-1])
        if name == 'zeros':
            return lambda env: np.zeros(tuple(int(a(env)) for a in args if int(a(env)) != 1))
        if len(args) != 1:
            self.fail(f'{name} takes one argument')
        function, arg = _FUNCTIONS[name], args[0]
        return lambda env: function(arg(env))

    def index(self, name: str):
        self.take('(')
        subscripts = []
        while True:
            token = self.take()
            if token.kind == 'number' and re.fullmatch(r'\d+', token.text) \
                    and int(token.text) >= 1:
                subscripts.append(int(token.text) - 1)
            elif token.text == ':':
                subscripts.append(slice(None))
            elif token.kind == 'name' and token.text == self.loop:
                subscripts.append('loop')
            else:
                self.fail(f'{name}(...): only positive integer literals, : and the loop '
                          f'variable index, got {token.text!r}')
            if self.take().text == ')':
                break
        if 'loop' in subscripts:
            if subscripts != ['loop'] or self.known[name]:
                self.fail(f'{name}(...): the loop variable indexes a vector alone')
            return lambda env: _whole(env, name, self.line)
        self.plain_reads.add(name)
        if len(subscripts) != (2 if self.known[name] else 1):
            self.fail(f'{name} is a {"matrix" if self.known[name] else "vector"}: index it '
                      f'by {"(row, column)" if self.known[name] else "one subscript"}')
        key = (Ellipsis,) + tuple(subscripts)

        def run(env):
            try:
                return np.asarray(env[name])[key]
            except IndexError:
                raise MatlabError(f'line {self.line}: {name} has shape '
                                  f'{np.shape(env[name])}, indexed by {key[1:]}') from None
        return run

    def matrix(self):
        start = self.at
        depth = 1
        while depth:
            token = self.take()
            depth += {'[': 1, ']': -1}.get(token.text, 0)
        inner = self.tokens[start:self.at - 1]
        rows = [r for r in _split(inner, ';') if r]
        cells = []
        for row in rows:
            cells.append([self.sub(part) for part in _split(row, ',')])
        widths = {len(r) for r in cells}
        if len(widths) > 1:
            self.fail('the rows of a matrix literal differ in length')
        if not cells:
            return lambda env: np.zeros(0)
        flat = len(cells) == 1 or len(cells[0]) == 1
        self.matrix_value |= not flat

        def run(env):
            values = [[cell(env) for cell in row] for row in cells]
            if flat:
                return _stack([v for row in values for v in row])
            return np.stack([_stack(row) for row in _broadcast_rows(values)], axis=-2)
        return run

    def sub(self, tokens: List[_Token]):
        if not tokens:
            self.fail('an empty matrix element')
        parser = _Parser(tokens, self.line, self.known, self.loop)
        parser.bracket = True
        run = parser.whole()
        if parser.matrix_value:
            self.fail('a matrix inside a matrix literal is not supported')
        self.reads |= parser.reads
        self.plain_reads |= parser.plain_reads
        return run


def _whole(env, name, line):
    value = np.asarray(env[name])
    if value.ndim == 0 or value.shape[-1] != env[_LOOP_COUNT]:
        raise MatlabError(f'line {line}: {name}(i) in a loop of {env[_LOOP_COUNT]} '
                          f'passes, but {name} has shape {value.shape}')
    return value


def _stack(values):
    return np.stack(np.broadcast_arrays(*[np.asarray(v, dtype=float) for v in values]), -1)


def _broadcast_rows(values):
    flat = np.broadcast_arrays(*[np.asarray(v, dtype=float) for row in values for v in row])
    width = len(values[0])
    return [flat[i:i + width] for i in range(0, len(flat), width)]


class MatlabFunction:
    """
    One parsed MATLAB function, evaluated vectorised over samples.

    Call it with one array per input, each (..., n); it returns its output variable.
    """

    def __init__(self, name: str, inputs: Sequence[str], output: str,
                 statements: Sequence[_Statement], loop_counts: Dict[int, _Statement]):
        self.name, self.inputs, self.output = name, tuple(inputs), output
        self._statements = list(statements)
        self._loop_counts = dict(loop_counts)
        last = {}
        for index, statement in enumerate(self._statements):
            reads = set(statement.reads)
            if index in self._loop_counts:
                reads |= self._loop_counts[index].reads
            for read in reads:
                last[read] = index
        self._free = [[] for _ in self._statements]
        for read, index in last.items():
            if read != output and read not in self.inputs:
                self._free[index].append(read)

    def __call__(self, *arrays, block: int = 1024) -> np.ndarray:
        """
        Return the output for the inputs ``arrays``, each (..., n).

        Inputs of two or more axes are evaluated ``block`` samples (first axis) at a time:
        generated code keeps thousands of temporaries alive, each the size of a block.
        """
        if len(arrays) != len(self.inputs):
            raise TypeError(f'{self.name} takes {len(self.inputs)} inputs, got {len(arrays)}')
        arrays = [np.asarray(a, dtype=float) for a in arrays]
        count = arrays[0].shape[0] if arrays[0].ndim >= 2 else 0
        if count > block and all(a.ndim >= 2 and a.shape[0] == count for a in arrays):
            first = self._run([a[:block] for a in arrays])
            if first.ndim == 0 or first.shape[0] != block:     # the output ignores the samples
                return first
            return np.concatenate([first] + [self._run([a[i:i + block] for a in arrays])
                                             for i in range(block, count, block)])
        return self._run(arrays)

    def _run(self, arrays) -> np.ndarray:
        env = dict(zip(self.inputs, arrays))
        with np.errstate(all='ignore'):
            for index, statement in enumerate(self._statements):
                if index in self._loop_counts:
                    env[_LOOP_COUNT] = int(self._loop_counts[index].run(env))
                env[statement.target] = statement.run(env)
                for name in self._free[index]:
                    env.pop(name, None)
        if self.output not in env:
            raise MatlabError(f'{self.name} never assigns its output {self.output}')
        return np.asarray(env[self.output], dtype=float)

    def __len__(self) -> int:
        """Return the number of statements."""
        return len(self._statements)


_LOOP_COUNT = '__loop_count__'


class _Loop(NamedTuple):
    variable: str
    first: int          # index of the loop's first statement


def _header(tokens: List[_Token], line: int):
    texts = [t.text for t in tokens]
    if len(texts) < 6 or texts[2] != '=' or tokens[1].kind != 'name' \
            or tokens[3].kind != 'name' or texts[4] != '(' or texts[-1] != ')':
        raise MatlabError(f'line {line}: expected "function out = name(inputs)"')
    inputs = [t.text for t in tokens[5:-1] if t.text != ',']
    if not inputs or any(not re.fullmatch(r'[A-Za-z_]\w*', name) for name in inputs):
        raise MatlabError(f'line {line}: inputs must be names')
    return texts[3], inputs, texts[1]


def parse_function(text: str) -> MatlabFunction:
    """Return the function the MATLAB ``text`` defines (module docstring for the subset)."""
    header, loop, ended = None, None, False
    known: Dict[str, bool] = {}
    statements: List[_Statement] = []
    loop_counts: Dict[int, _Statement] = {}
    for line, logical in _logical_lines(text):
        for part in _split(_tokens(logical, line), ';,'):
            if not part:
                continue
            first = part[0].text
            if header is None:
                if first != 'function':
                    raise MatlabError(f'line {line}: expected the function line first')
                header = _header(part, line)
                known.update(dict.fromkeys(header[1], False))
                continue
            if ended:
                raise MatlabError(f'line {line}: text after the end of the function')
            if first in _KEYWORDS or first == 'function':
                raise MatlabError(f'line {line}: {first!r} is not supported')
            if first == 'for':
                if loop is not None:
                    raise MatlabError(f'line {line}: nested loops are not supported')
                loop = _Loop(_loop_variable(part, line), len(statements))
                count = _Parser(part[5:], line, known, None)
                loop_counts[len(statements)] = _Statement(
                    _LOOP_COUNT, count.whole(), frozenset(count.reads), line)
                continue
            if first == 'end' and len(part) == 1:
                if loop is None:
                    ended = True
                    continue
                _check_loop(statements[loop.first:])
                loop = None
                continue
            statements.append(_assignment(part, line, known, loop))
    if header is None:
        raise MatlabError('no function line')
    if loop is not None:
        raise MatlabError('a for loop is not closed by end')
    return MatlabFunction(header[0], header[1], header[2], statements, loop_counts)


def _loop_variable(part: List[_Token], line: int) -> str:
    texts = [t.text for t in part]
    if len(texts) < 6 or part[1].kind != 'name' or texts[2:5] != ['=', '1', ':']:
        raise MatlabError(f'line {line}: expected "for i = 1:N"')
    return texts[1]


def _check_loop(body: Sequence[_Statement]) -> None:
    """Refuse a loop whose passes depend on each other (it could not run vectorised)."""
    assigned = {statement.target for statement in body}
    for statement in body:
        carried = statement.plain_reads & assigned
        if carried:
            raise MatlabError(f'line {statement.line}: {sorted(carried)} read in the loop '
                              'other than as name(i), while the loop assigns them')


def _assignment(part: List[_Token], line: int, known: Dict[str, bool],
                loop: Optional[_Loop]) -> _Statement:
    texts = [t.text for t in part]
    if '=' not in texts:
        raise MatlabError(f'line {line}: expected an assignment')
    equals = texts.index('=')
    target = part[0].text
    if part[0].kind != 'name' or target in _KEYWORDS:
        raise MatlabError(f'line {line}: cannot assign to {target!r}')
    if loop is None and equals != 1:
        raise MatlabError(f'line {line}: only "name = ..." may be assigned outside a loop')
    if loop is not None and texts[1:equals] != ['(', loop.variable, ')']:
        raise MatlabError(f'line {line}: in a loop only "name({loop.variable}) = ..." may be '
                          'assigned')
    parser = _Parser(part[equals + 1:], line, known, loop.variable if loop else None)
    run = parser.whole()
    if loop is not None:
        run = _whole_target(run, target, line)
    known[target] = parser.matrix_value
    return _Statement(target, run, frozenset(parser.reads), line,
                      frozenset(parser.plain_reads))


def _whole_target(run: Callable, target: str, line: int) -> Callable:
    """Return ``run`` checked to give all N elements of ``target`` in a loop of N passes."""
    def checked(env):
        value = np.asarray(run(env), dtype=float)
        count = env[_LOOP_COUNT]
        before = env.get(target)
        if value.ndim == 0 or value.shape[-1] != count or (
                before is not None and np.ndim(before) and np.shape(before)[-1] != count):
            raise MatlabError(f'line {line}: {target}(i) over {count} passes must give every '
                              f'element (shapes {np.shape(before)} and {value.shape})')
        return value
    return checked


def load_function(path: str) -> MatlabFunction:
    """Return the function the ``.m`` file at ``path`` defines (read at call time)."""
    with open(path, encoding='utf-8') as handle:
        text = handle.read()
    try:
        return parse_function(text)
    except MatlabError as error:
        raise MatlabError(f'{path}: {error}') from None

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
Parameter tables: one row per node parameter, saying what it is and what a change does.

Both nodes list their parameters as :class:`ParameterSpec` rows. A row is the one place for
a parameter's declaration (type, description, the range rclpy enforces, read-only), the
checks rclpy cannot make (open bounds, NaN, choices, array elements and lengths, text
sizes: :meth:`ParameterSpec.check`) and its :class:`Change`: what setting it at run time
does. A node applies a set of parameters by the union of their changes, so adding a
parameter is adding a row.

Every value a row accepts must be one its node can run with: a range says what is useful
(a rate of 1e-300 Hz passes ``> 0`` but makes no timer), not only what is positive, and
arrays and strings have a size budget (``max_items``, ``max_bytes``) so that no accepted
value makes an allocation fail.
"""

from dataclasses import dataclass
import enum
import math
from typing import Optional, Tuple

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.parameter import Parameter

__all__ = ['Change', 'ParameterSpec']

_T = Parameter.Type
_TYPE_NAMES = {_T.DOUBLE: 'double', _T.INTEGER: 'integer', _T.BOOL: 'bool',
               _T.STRING: 'string', _T.DOUBLE_ARRAY: 'double array',
               _T.STRING_ARRAY: 'string array'}
_ARRAYS = (_T.DOUBLE_ARRAY, _T.STRING_ARRAY)


class Change(enum.Flag):
    """What setting a parameter at run time does (flags combine)."""

    LIVE = enum.auto()     # taken at once
    ES = enum.auto()       # handed to the optimizer between two generations
    BUFFER = enum.auto()   # the stream buffer is rebuilt (its data cleared)
    RESTART = enum.auto()  # the search restarts before the next generation
    START = enum.auto()    # read-only: set at start (params file, --ros-args -p)
    OUTPUT = enum.auto()   # set by the node; sets from outside are refused


@dataclass(frozen=True)
class ParameterSpec:
    """
    One declared parameter.

    Attributes
    ----------
    name, default, description : str, object, str
        ``default`` also gives the type unless ``ptype`` is set (an empty array needs it).
    low, high : float, optional
        Bounds; both given: a range in the descriptor, which rclpy enforces (closed).
        For arrays ``low`` bounds every element.
    constraints : str
        Further rules, in words (``ros2 param describe`` shows them).
    change : Change
        What a run-time change does.
    ptype : Parameter.Type, optional
        The type, when the default does not tell it.
    low_open : bool
        ``low`` itself is excluded (checked by :meth:`check`, not by rclpy).
    choices : tuple of str
        The allowed values of a string.
    off_below : float, optional
        0 switches the feature off; any other value must be at least this (e.g. a rate:
        0 or >= 0.1 Hz). Checked by :meth:`check`; the descriptor's range is then ``[0,
        high]``.
    max_items : int, optional
        Arrays: at most this many elements.
    max_bytes : int, optional
        Strings and string arrays: at most this many UTF-8 bytes per string, and no NUL.

    """

    name: str
    default: object
    description: str
    low: Optional[float] = None
    high: Optional[float] = None
    constraints: str = ''
    change: Change = Change.LIVE
    ptype: Optional[Parameter.Type] = None
    low_open: bool = False
    choices: Tuple[str, ...] = ()
    off_below: Optional[float] = None
    max_items: Optional[int] = None
    max_bytes: Optional[int] = None

    @property
    def kind(self) -> Parameter.Type:
        """Return the parameter's type (given, or that of the default)."""
        if self.ptype is not None:
            return self.ptype
        if isinstance(self.default, (list, tuple)):
            return _T.STRING_ARRAY if isinstance(self.default[0], str) else _T.DOUBLE_ARRAY
        return Parameter.Type.from_parameter_value(self.default)

    @property
    def read_only(self) -> bool:
        """Return whether rclpy refuses run-time sets (``Change.START``)."""
        return self.change == Change.START

    def bound_text(self) -> str:
        """Return the bound as text, e.g. ``in (0.0, 10.0]``."""
        if self.off_below is not None:
            return f'0 (off) or in [{self.off_below}, {self.high}]'
        if self.low is None and self.high is None:
            return ''
        if self.high is None:
            return f'{">" if self.low_open else ">="} {self.low}'
        return f'in {"(" if self.low_open else "["}{self.low}, {self.high}]'

    def descriptor(self) -> ParameterDescriptor:
        """Return the ParameterDescriptor rclpy enforces (type, closed range, read-only)."""
        extra = [self.constraints] if self.constraints else []
        if self.low_open:
            extra.insert(0, f'> {self.low}')
        if self.off_below is not None:
            extra.insert(0, f'0 (off) or >= {self.off_below}')
        if self.max_items is not None:
            extra.append(f'at most {self.max_items} elements')
        if self.max_bytes is not None:
            extra.append(f'at most {self.max_bytes} bytes per string')
        if self.choices:
            extra.insert(0, 'one of ' + ', '.join(self.choices))
        kind = self.kind
        desc = ParameterDescriptor(name=self.name, type=kind.value,
                                   description=self.description,
                                   additional_constraints='; '.join(extra),
                                   read_only=self.read_only)
        if kind == _T.DOUBLE and self.low is not None and self.high is not None:
            desc.floating_point_range = [FloatingPointRange(
                from_value=float(self.low), to_value=float(self.high), step=0.0)]
        elif kind == _T.INTEGER and self.low is not None and self.high is not None:
            desc.integer_range = [IntegerRange(
                from_value=int(self.low), to_value=int(self.high), step=1)]
        return desc

    def declare(self, node):
        """
        Declare the parameter on ``node``; return its value (given at start, else default).

        An array without a default is declared by type and set to ``[]`` when no value was
        given (rclpy leaves it unset; a read-only one, which rclpy refuses to set, stays
        unset and reads as ``[]``). Outputs ignore values given at start.
        """
        kind = self.kind
        output = self.change == Change.OUTPUT
        if kind in _ARRAYS and not self.default:
            param = node.declare_parameter(self.name, kind, self.descriptor(),
                                           ignore_override=output)
            if param.type_ == _T.NOT_SET:  # no value given, or `[]` in a params file
                if self.read_only:
                    return []
                node.set_parameters([Parameter(self.name, kind, [])])
            return node.get_parameter(self.name).value
        return node.declare_parameter(self.name, self.default, self.descriptor(),
                                      ignore_override=output).value

    def plain(self, value):
        """Return ``value`` as plain immutable Python (tuples for arrays)."""
        kind = self.kind
        if kind == _T.DOUBLE:
            return float(value)
        if kind == _T.INTEGER:
            return int(value)
        if kind == _T.BOOL:
            return bool(value)
        if kind == _T.STRING:
            return str(value)
        if kind == _T.DOUBLE_ARRAY:
            return tuple(float(v) for v in value)
        if kind == _T.STRING_ARRAY:
            return tuple(str(v) for v in value)
        return value

    def check(self, value) -> Optional[str]:
        """Return why ``value`` is invalid (None if valid); the reason names the parameter."""
        name, kind = self.name, self.kind
        if not _type_ok(kind, value):
            return (f'{name} must be a {_TYPE_NAMES.get(kind, kind)}, got {_shown(value)} '
                    f'({type(value).__name__})')
        if kind == _T.DOUBLE:
            if not math.isfinite(value) or not self._number_ok(value):
                return f'{name} must be a finite number {self.bound_text()}, got {value!r}'
        elif kind == _T.INTEGER:
            if not self._number_ok(value):
                return f'{name} must be an integer {self.bound_text()}, got {value}'
        elif kind == _T.STRING:
            reason = self._text_reason(value)
            if reason:
                return f'{name} {reason}'
            if self.choices and value not in self.choices:
                return f'{name} must be one of {", ".join(self.choices)}, got {_shown(value)}'
        elif kind in _ARRAYS and self.max_items is not None and len(value) > self.max_items:
            return f'{name} must hold at most {self.max_items} elements, got {len(value)}'
        elif kind == _T.DOUBLE_ARRAY:
            if not all(math.isfinite(v) and (self.low is None or v >= self.low)
                       and (self.high is None or v <= self.high) for v in value):
                bound = self.bound_text()
                return f'{name} must hold finite values{" " + bound if bound else ""}, got ' \
                       f'{_shown(list(value))}'
        if kind == _T.STRING_ARRAY:
            if any(not v for v in value) or len(set(value)) != len(value):
                return f'{name} must hold non-empty, distinct names, got {_shown(list(value))}'
            for v in value:
                reason = self._text_reason(v)
                if reason:
                    return f'{name}: a name {reason}'
        return None

    def _number_ok(self, value) -> bool:
        if self.off_below is not None and value == 0:
            return True
        low = self.low if self.off_below is None else self.off_below
        if low is not None and (value <= low if self.low_open else value < low):
            return False
        return self.high is None or value <= self.high

    def _text_reason(self, text: str) -> Optional[str]:
        if self.max_bytes is None:
            return None
        if '\x00' in text:
            return 'must not contain a NUL character'
        size = len(text.encode('utf-8', 'surrogatepass'))
        if size > self.max_bytes:
            return f'must be at most {self.max_bytes} bytes, got {size}'
        return None


def _shown(value, limit: int = 80) -> str:
    """Return ``repr(value)``, cut to ``limit`` characters (a reason quotes what it got)."""
    text = repr(value)
    return text if len(text) <= limit else f'{text[:limit]}... ({len(text)} characters)'


def _type_ok(kind, value) -> bool:
    if kind == _T.DOUBLE:
        return isinstance(value, float)
    if kind == _T.INTEGER:
        return isinstance(value, int) and not isinstance(value, bool)
    if kind == _T.BOOL:
        return isinstance(value, bool)
    if kind == _T.STRING:
        return isinstance(value, str)
    if kind in _ARRAYS:
        element = float if kind == _T.DOUBLE_ARRAY else str
        return not isinstance(value, (str, bytes)) and all(
            isinstance(v, element) for v in value)
    return False

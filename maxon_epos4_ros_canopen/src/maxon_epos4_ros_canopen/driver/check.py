"""The one command check: a pure function of (command, axis or snapshot,
limits) that gives the saturated device value or the reason for refusing.

The caller's thread checks against the latest AxisSnapshot and answers with
it; the cycle takes a Checked command after ``state_problem`` only (the
axis's state may have changed since), or checks a cycle callback's command
against the Axis itself. The value is saturated and converted here, once.
"""
from __future__ import annotations

import math
from typing import Any, Dict, NamedTuple, Optional, Union

from ..cia402 import State
from ..limits import JointLimits, saturate
from .convert import Converter
from .modes import COMMAND_KINDS, MODES, mode_of

# Bound once for check_command, which runs for every command (a module
# global is one lookup, an enum member through its class several).
_ENABLED = State.OPERATION_ENABLED
_mode_get = MODES.get
_isfinite = math.isfinite
_tuple_new = tuple.__new__


class Checked(NamedTuple):
    """A command that passed check_command: saturated and converted once."""
    kind: str
    value: float     # ROS units, saturated to the joint limits
    raw: int         # the device value
    clipped: bool


def check_command(axis: Any, kind: str, value: Any, limits: JointLimits, converter: Converter,
                  env: Dict[str, float]) -> Union[Checked, str]:
    """The one command check: a Checked command, or the reason (str) why it
    is refused. ``axis`` is an Axis or an AxisSnapshot; ``env`` holds the
    objects the conversion reads (it is written to). The caller's thread
    checks against the latest snapshot, a cycle callback against the axis;
    the cycle takes a Checked command after state_problem only."""
    mode = _mode_get(axis.active_mode)
    # The common case decided in one expression: every condition of
    # command_problem holds. Anything else takes command_problem for the
    # reason (same checks, same order of messages).
    if not (type(value) is float and _isfinite(value) and mode is not None and mode.command_kind == kind
            and not axis.error and axis.ready and not axis.halted and axis.state is _ENABLED
            and not axis.homing):
        problem = command_problem(axis, kind, value)
        if problem:
            return problem
    value, clipped = saturate(limits, kind, float(value))
    raw, err = converter.convert(kind, value, env)
    if err:
        return err
    # tuple.__new__ straight from the fields: Checked(...) minus its Python-level __new__
    return _tuple_new(Checked, (kind, value, raw, clipped))


def command_problem(axis: Any, kind: str, value: Any) -> Optional[str]:
    """Why a command cannot be taken now (None: it can): the value, then
    the axis's state. ``axis`` is an Axis or an AxisSnapshot."""
    if kind not in COMMAND_KINDS:
        return "unknown command kind %r (position, velocity, effort)" % (kind,)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return "command must be a number"
    try:
        value = float(value)
    except OverflowError:
        return "%s command refused: not a finite number" % kind
    if not math.isfinite(value):
        return "%s command %r refused: not a finite number" % (kind, value)
    return state_problem(axis, kind)


def state_problem(axis: Any, kind: str) -> Optional[str]:
    """Why the axis takes no ``kind`` command now (None: it does)."""
    if axis.error:
        return "%s is in error (%s): call recover" % (axis.name, axis.error)
    if not axis.ready:
        return "%s is not initialized: call init" % axis.name
    if axis.halted:
        return "%s is halted: call recover before sending commands" % axis.name
    if axis.state != State.OPERATION_ENABLED:
        return "%s is not operation enabled (state %s)" % (axis.name, axis.state.value if axis.state else "unknown")
    if axis.homing:
        return "%s is homing" % axis.name
    mode = mode_of(axis.active_mode)
    if mode is None or mode.command_kind is None:
        return "%s has no mode for commands yet (start a controller)" % axis.name
    if mode.command_kind != kind:
        return "%s is in mode %s, which takes %s commands, not %s" % (
            axis.name, mode.name, mode.command_kind, kind)
    return None

"""An axis's units: commands in ROS units to device values (Converter), and
the drive's readings to ROS units (FromDevice). Both immutable, one per
axis; the expressions were compiled once when the configuration was loaded.
"""
from __future__ import annotations

import math
from typing import Any, Dict, Mapping, Optional, Tuple

from ..config_schema import NodeConfig
from ..objects import find_variable
from ..units import EVALUATION_ERRORS, Expression, object_variable_name
from .modes import POSITION_ACTUAL, TARGET_OF_KIND

_isfinite = math.isfinite


class Converter:
    """Commands in ROS units to device values: immutable, one per axis.

    The expressions were compiled once when the configuration was loaded;
    the target objects' integer ranges come from the object dictionary.
    """

    _VARIABLE = {"position": "pos", "velocity": "vel", "effort": "eff"}

    def __init__(self, cfg: NodeConfig, od: Any) -> None:
        self.expressions: Dict[str, Expression] = {
            "position": cfg.pos_to_device, "velocity": cfg.vel_to_device, "effort": cfg.eff_to_device}
        self.ranges: Dict[str, Tuple[int, int, int]] = {}
        for kind, key in TARGET_OF_KIND.items():
            bits = len(find_variable(od, key))
            self.ranges[kind] = (-(1 << (bits - 1)), (1 << (bits - 1)) - 1, key.index)
        self.dynamic = {k: bool(e.objects) for k, e in self.expressions.items()}
        # per kind, what convert needs, in one lookup: (compiled function,
        # variable, lowest, highest device value)
        self._prepared: Dict[str, Tuple[Any, str, int, int]] = {
            kind: (self.expressions[kind].raw, self._VARIABLE[kind], lo, hi)
            for kind, (lo, hi, _) in self.ranges.items()}

    def convert(self, kind: str, value: float, env: Dict[str, float]) -> Tuple[Optional[int], Optional[str]]:
        """Device value of a command, or why there is none. ``env`` holds the
        objects the expression reads; its ``pos``/``vel``/``eff`` entry is
        overwritten with ``value``."""
        fn, variable, lo, hi = self._prepared[kind]
        env[variable] = value
        try:  # Expression.evaluate, inline: every command goes through here
            raw = float(fn(env))
        except EVALUATION_ERRORS:
            raw = math.nan
        if not _isfinite(raw):
            return None, "%s %g converts to %r by %r: refused" % (kind, value, raw, self.expressions[kind].text)
        raw_int = int(round(raw))
        if not lo <= raw_int <= hi:
            index = self.ranges[kind][2]
            return None, "%s %g converts to %d, outside 0x%04X's range %d..%d" % (kind, value, raw_int, index, lo, hi)
        return raw_int, None


class FromDevice:
    """The drive's readings in ROS units: pos/vel/eff_from_device."""

    def __init__(self, cfg: NodeConfig) -> None:
        self.expressions: Tuple[Expression, ...] = (cfg.pos_from_device, cfg.vel_from_device, cfg.eff_from_device)
        # a constant conversion (eff_from_device: "0") has one value: not evaluated per cycle
        self._const = tuple(e.evaluate({}) if e.constant else None for e in self.expressions)
        self._raw = tuple(e.raw for e in self.expressions)

    def values(self, env: Mapping[str, Any]) -> Tuple[float, float, float]:
        """Position, velocity and effort from the objects in ``env`` (NaN
        where an expression fails)."""
        # Expression.evaluate, inline (three calls less per axis per cycle)
        pos, vel, eff = self._raw
        cpos, cvel, ceff = self._const
        if cpos is None:
            try:
                cpos = float(pos(env))
            except EVALUATION_ERRORS:
                cpos = math.nan
        if cvel is None:
            try:
                cvel = float(vel(env))
            except EVALUATION_ERRORS:
                cvel = math.nan
        if ceff is None:
            try:
                ceff = float(eff(env))
            except EVALUATION_ERRORS:
                ceff = math.nan
        return cpos, cvel, ceff

    def position_of(self, raw_position: int, env: Mapping[str, Any]) -> float:
        """A raw position in ROS units, the other objects from ``env`` (NaN
        if it fails)."""
        if self._const[0] is not None:
            return self._const[0]
        env = dict(env)
        env[object_variable_name(POSITION_ACTUAL)] = raw_position
        try:
            return float(self._raw[0](env))
        except EVALUATION_ERRORS:
            return math.nan

"""Reading a parameter tree: YAML files merged as successive rosparam loads
merge them, and typed access to one mapping that names the key and the
source in every ConfigError.
"""
from __future__ import annotations

import math
from typing import Any, Dict, Iterable, List, Mapping, Optional

from .config_schema import ConfigError

__all__ = ["merge_params", "load_yaml_files", "ParamReader"]


def merge_params(base: Mapping[str, Any], override: Mapping[str, Any]) -> Dict[str, Any]:
    """Deep merge: override wins, dicts are merged key by key.

    This is what ``<rosparam command="load">`` of several files into one
    namespace does, and how ros_canopen puts ``defaults`` under each node.
    An empty entry (``node1:`` followed only by comments, as in the seed's
    ros.yaml) adds nothing and does not erase what another file set.
    """
    out: Dict[str, Any] = dict(base)
    for k, v in override.items():
        if v is None and isinstance(out.get(k), Mapping):
            continue
        if isinstance(v, Mapping) and isinstance(out.get(k), Mapping):
            out[k] = merge_params(out[k], v)
        else:
            out[k] = v
    return out


def load_yaml_files(paths: Iterable[str]) -> Dict[str, Any]:
    """Read YAML files in order and merge them like successive rosparam loads."""
    import yaml  # only this helper needs it; the node gets its tree from ROS

    tree: Dict[str, Any] = {}
    for path in paths:
        with open(path, "r", encoding="utf-8") as f:
            data = yaml.safe_load(f)
        if data is None:
            continue
        if not isinstance(data, Mapping):
            raise ConfigError(path, "(top level)", "expected a mapping of keys, got %s" % type(data).__name__)
        tree = merge_params(tree, data)
    return tree


class ParamReader:
    """Typed access to one mapping with key paths for error messages."""

    def __init__(self, source: str, warnings: List[str]) -> None:
        self.source = source
        self.warnings = warnings

    def fail(self, key: str, problem: str) -> ConfigError:
        return ConfigError(self.source, key, problem)

    def mapping(self, value: Any, key: str, allow_none: bool = True) -> Mapping[str, Any]:
        if value is None and allow_none:
            return {}
        if not isinstance(value, Mapping):
            raise self.fail(key, "expected a mapping, got %s %r" % (type(value).__name__, value))
        return value

    def string(self, value: Any, key: str) -> str:
        if not isinstance(value, str):
            raise self.fail(key, "expected a string, got %s %r" % (type(value).__name__, value))
        return value

    def boolean(self, value: Any, key: str) -> bool:
        if not isinstance(value, bool):
            raise self.fail(key, "expected true or false, got %s %r" % (type(value).__name__, value))
        return value

    def integer(self, value: Any, key: str, lo: Optional[int] = None, hi: Optional[int] = None) -> int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.fail(key, "expected an integer, got %s %r" % (type(value).__name__, value))
        if lo is not None and value < lo or hi is not None and value > hi:
            raise self.fail(key, "%d out of range %s..%s" % (value, lo, hi))
        return value

    def number(self, value: Any, key: str, lo: float = 0.0, hi: float = math.inf) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.fail(key, "expected a number, got %s %r" % (type(value).__name__, value))
        try:
            number = float(value)
        except OverflowError:  # an int too large for a float (10**400)
            number = math.inf if value > 0 else -math.inf
        if not math.isfinite(number) or not lo <= number <= hi:
            shown = "%.6g" % number if math.isfinite(number) else ("a number too large" if isinstance(value, int)
                                                                   else repr(number))
            raise self.fail(key, "%s must be a finite number in %g..%g" % (shown, lo, hi))
        return number

    def unknown(self, mapping: Mapping[str, Any], known: Iterable[str], prefix: str) -> None:
        known = set(known)
        for k in mapping:
            if k not in known:
                self.warnings.append("%s: unknown option %s%s ignored" % (self.source, prefix, k))

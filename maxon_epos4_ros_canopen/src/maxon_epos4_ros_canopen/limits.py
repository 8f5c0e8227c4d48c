"""Joint limits from the URDF (``robot_description``), applied to commands.

ros_canopen's robot layer loads the URDF and saturates every command to the
joint's limits before it is converted to device units; this module does the
same for the driver. Limits are in ROS units (the units the commands are
in). A joint the URDF gives no limit for is not limited; a continuous joint
has no position limits.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Dict, Optional, Tuple

__all__ = ["JointLimits", "UrdfError", "limits_from_urdf", "saturate"]


class UrdfError(ValueError):
    """robot_description cannot be read."""


@dataclass(frozen=True)
class JointLimits:
    """Command limits in ROS units; None: not limited."""
    lower: Optional[float] = None
    upper: Optional[float] = None
    velocity: Optional[float] = None
    effort: Optional[float] = None

    def describe(self) -> str:
        parts = []
        if self.lower is not None or self.upper is not None:
            parts.append("position [%s, %s]" % (_fmt(self.lower), _fmt(self.upper)))
        if self.velocity is not None:
            parts.append("velocity %g" % self.velocity)
        if self.effort is not None:
            parts.append("effort %g" % self.effort)
        return ", ".join(parts) or "none"


def _fmt(value: Optional[float]) -> str:
    return "-" if value is None else "%g" % value


def saturate(limits: JointLimits, kind: str, value: float) -> Tuple[float, bool]:
    """The command clipped to the limits, and whether it was clipped."""
    if kind == "position":
        lo, hi = limits.lower, limits.upper
    elif kind == "velocity":
        lo, hi = (None, None) if limits.velocity is None else (-limits.velocity, limits.velocity)
    else:
        lo, hi = (None, None) if limits.effort is None else (-limits.effort, limits.effort)
    if lo is not None and value < lo:
        return lo, True
    if hi is not None and value > hi:
        return hi, True
    return value, False


def _finite(value: Optional[float]) -> Optional[float]:
    if value is None:
        return None
    value = float(value)
    return value if math.isfinite(value) else None


def limits_from_urdf(xml: str) -> Dict[str, JointLimits]:
    """Every joint's limits in a URDF document; raises UrdfError if it does
    not parse. A velocity or effort of 0 means "not given" (as in URDF's
    defaults) and does not limit."""
    # urdf_parser_py is the URDF parser ROS ships (urdfdom_py); it reports
    # tags it does not model (transmissions' hardwareInterface) on stderr.
    from urdf_parser_py import xml_reflection
    from urdf_parser_py.urdf import URDF

    xml_reflection.core.on_error = lambda _message: None
    try:
        robot = URDF.from_xml_string(xml)
    except Exception as exc:  # lxml/ElementTree and the parser raise many kinds
        raise UrdfError("robot_description is not a valid URDF: %s" % exc) from None
    out: Dict[str, JointLimits] = {}
    for joint in robot.joints:
        limit = getattr(joint, "limit", None)
        if limit is None:
            out[joint.name] = JointLimits()
            continue
        positional = joint.type in ("revolute", "prismatic")
        velocity = _finite(getattr(limit, "velocity", None))
        effort = _finite(getattr(limit, "effort", None))
        out[joint.name] = JointLimits(
            lower=_finite(limit.lower) if positional else None,
            upper=_finite(limit.upper) if positional else None,
            velocity=velocity if velocity else None,
            effort=effort if effort else None)
    return out

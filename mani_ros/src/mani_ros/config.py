"""Load and validate config/mani.yaml into a typed ManiConfig (ROS-free).

Every error names the key and the file (or the ROS parameter the dictionary
came from), so a typo in mani.yaml is found before a node talks to a motor.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, fields, replace
from typing import Any, Dict, Mapping, Optional, Tuple, Type, TypeVar, get_type_hints

import yaml

from .protocol import COMMAND_DATA_LENGTHS, DRIVE_NODES, EPS_SENSORS, INT16_MAX, NODE_NAMES

WHEELS: Tuple[str, ...] = tuple(NODE_NAMES[node] for node in DRIVE_NODES)


class ConfigError(ValueError):
    """mani.yaml (or its dictionary) is not valid; the text names key and file."""


@dataclass(frozen=True)
class Rover:
    wheel_base: float
    track: float
    wheel_radius: float


@dataclass(frozen=True)
class Steering:
    min_angle: float
    max_angle: float
    offsets: Dict[str, float]


@dataclass(frozen=True)
class Can:
    interface: str
    device: str
    sim_device: str
    bitrate: int
    command_data_length: int


@dataclass(frozen=True)
class Frames:
    odom: str
    base_link: str


@dataclass(frozen=True)
class Timeouts:
    locomotion: float
    cmd_vel_teleop: float
    cmd_vel_autonomous: float
    feedback: float


@dataclass(frozen=True)
class Power:
    overcurrent_switch_off: bool
    max_current: Dict[str, float]   # [A] per EPS sensor: currentFb's full scale


@dataclass(frozen=True)
class OdometryNoise:
    xy_variance_per_m: float
    yaw_variance_per_rad: float
    twist_variance_linear: float
    twist_variance_angular: float


@dataclass(frozen=True)
class Simulation:
    steer_rate: float
    drive_acceleration: float
    orientation_tolerance: int
    velocity_tolerance: int
    odometry_period: float
    eps_period: float
    motor_power_on: bool


@dataclass(frozen=True)
class ManiConfig:
    rover: Rover
    steering: Steering
    DRIVE_ENC_PPR: int
    STEER_ENC_PPR: int
    MAX_VEL: float   # [rad/s] fastest wheel rotation
    can: Can
    frames: Frames
    timeouts: Timeouts
    power: Power
    odometry: OdometryNoise
    simulation: Simulation
    source: str = "<dict>"

    # Derived figures, so that every node converts the same way.
    @property
    def wheel_circumference(self) -> float:
        return 2.0 * math.pi * self.rover.wheel_radius

    @property
    def max_wheel_speed(self) -> float:
        """MAX_VEL as wheel rim speed [m/s]."""
        return self.MAX_VEL * self.rover.wheel_radius

    @property
    def max_velocity_pulses(self) -> int:
        """MAX_VEL in drive encoder pulses/s, the largest velocityCmd."""
        return int(self.MAX_VEL / (2.0 * math.pi) * self.DRIVE_ENC_PPR)

    def wheel_positions(self) -> Dict[str, Tuple[float, float]]:
        """(x, y) of each wheel's steering axis in base_link [m]; x forward,
        y left, base_link in the middle of the four wheels."""
        x, y = self.rover.wheel_base / 2.0, self.rover.track / 2.0
        return {"front_left": (x, y), "rear_left": (-x, y),
                "rear_right": (-x, -y), "front_right": (x, -y)}


T = TypeVar("T")


def _where(path: str, source: str) -> str:
    return "%s in %s" % (path, source)


def _value(kind: Any, value: Any, path: str, source: str) -> Any:
    if kind is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ConfigError("%s must be a number, got %r" % (_where(path, source), value))
        return float(value)
    if kind is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError("%s must be an integer, got %r" % (_where(path, source), value))
        return value
    if kind is bool:
        if not isinstance(value, bool):
            raise ConfigError("%s must be true or false, got %r" % (_where(path, source), value))
        return value
    if kind is str:
        if not isinstance(value, str) or not value:
            raise ConfigError("%s must be a non-empty string, got %r" % (_where(path, source), value))
        return value
    raise AssertionError("no rule for %r" % (kind,))


def _section(kind: Type[T], data: Any, path: str, source: str) -> T:
    if not isinstance(data, Mapping):
        raise ConfigError("%s must be a mapping, got %r" % (_where(path or "the top level", source), data))
    hints = get_type_hints(kind)
    names = [f.name for f in fields(kind) if f.name != "source"]
    prefix = path + "." if path else ""
    for key in data:
        if key not in names:
            raise ConfigError("unknown key %s (known: %s)"
                              % (_where(prefix + str(key), source), ", ".join(names)))
    values: Dict[str, Any] = {}
    for name in names:
        if name not in data:
            raise ConfigError("missing key %s" % _where(prefix + name, source))
        hint = hints[name]
        if isinstance(hint, type) and hint not in (float, int, bool, str):
            values[name] = _section(hint, data[name], prefix + name, source)
        elif name == "offsets":
            values[name] = _per_name(data[name], WHEELS, "one angle [rad]", prefix + name, source)
        elif name == "max_current":
            values[name] = _per_name(data[name], EPS_SENSORS, "one current [A]", prefix + name, source)
        else:
            values[name] = _value(hint, data[name], prefix + name, source)
    return kind(**values)


def _per_name(data: Any, names: Tuple[str, ...], what: str, path: str, source: str) -> Dict[str, float]:
    if not isinstance(data, Mapping) or set(data) != set(names):
        raise ConfigError("%s must give %s for each of %s, got %r"
                          % (_where(path, source), what, ", ".join(names), data))
    return {name: _value(float, data[name], path + "." + name, source) for name in names}


def _require(ok: bool, path: str, source: str, rule: str) -> None:
    if not ok:
        raise ConfigError("%s %s" % (_where(path, source), rule))


def config_from_dict(data: Any, source: str = "<dict>") -> ManiConfig:
    """A validated ManiConfig from the dictionary of mani.yaml (for example a
    ROS parameter namespace); source names it in error messages."""
    config = replace(_section(ManiConfig, data, "", source), source=source)
    for name in ("wheel_base", "track", "wheel_radius"):
        _require(getattr(config.rover, name) > 0, "rover." + name, source, "must be > 0")
    steering = config.steering
    _require(-math.pi <= steering.min_angle < steering.max_angle <= math.pi,
             "steering.min_angle/max_angle", source, "must satisfy -pi <= min_angle < max_angle <= pi")
    _require(steering.min_angle <= 0.0 <= steering.max_angle,
             "steering.min_angle/max_angle", source, "must include 0 (straight ahead)")
    for wheel, offset in steering.offsets.items():
        _require(abs(offset) <= math.pi, "steering.offsets." + wheel, source, "must be within [-pi, pi]")
    for name in ("DRIVE_ENC_PPR", "STEER_ENC_PPR"):
        _require(0 < getattr(config, name) <= INT16_MAX, name, source, "must be in 1..32767")
    _require(config.MAX_VEL > 0, "MAX_VEL", source, "must be > 0 (rad/s)")
    _require(config.max_velocity_pulses <= INT16_MAX, "MAX_VEL", source,
             "is %d drive encoder pulses/s, beyond an int16 on the bus"
             % config.max_velocity_pulses)
    _require(0 < config.can.bitrate <= 1000000, "can.bitrate", source, "must be in 1..1000000")
    _require(config.can.command_data_length in COMMAND_DATA_LENGTHS, "can.command_data_length",
             source, "must be 2 (the rover's code) or 4 (the seed's table)")
    for sensor, current in config.power.max_current.items():
        _require(current > 0, "power.max_current." + sensor, source, "must be > 0")
    for f in fields(Timeouts):
        _require(getattr(config.timeouts, f.name) > 0, "timeouts." + f.name, source, "must be > 0")
    for f in fields(OdometryNoise):
        _require(getattr(config.odometry, f.name) >= 0, "odometry." + f.name, source, "must be >= 0")
    sim = config.simulation
    for name in ("steer_rate", "drive_acceleration", "odometry_period", "eps_period"):
        _require(getattr(sim, name) > 0, "simulation." + name, source, "must be > 0")
    for name in ("orientation_tolerance", "velocity_tolerance"):
        _require(getattr(sim, name) >= 0, "simulation." + name, source, "must be >= 0")
    return config


def default_config_path() -> str:
    """config/mani.yaml of the package source tree this module belongs to, or
    of the installed package (found with rospkg) when run from an install."""
    path = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)),
                                         "..", "..", "config", "mani.yaml"))
    if os.path.exists(path):
        return path
    try:
        import rospkg  # plain Python, no ROS master needed
        return os.path.join(rospkg.RosPack().get_path("mani_ros"), "config", "mani.yaml")
    except Exception:  # noqa: BLE001 - rospkg absent or package unknown: report the source path
        return path


def load_config(path: Optional[str] = None) -> ManiConfig:
    """Read and validate mani.yaml (default: the package's config/mani.yaml)."""
    path = path or default_config_path()
    try:
        with open(path, "r", encoding="utf-8") as stream:
            data = yaml.safe_load(stream)
    except OSError as error:
        raise ConfigError("cannot read %s: %s" % (path, error.strerror or error)) from error
    except yaml.YAMLError as error:
        raise ConfigError("%s is not valid YAML: %s" % (path, error)) from error
    return config_from_dict(data, path)

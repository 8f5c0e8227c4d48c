"""A simulated MANI rover on any python-can bus (ROS-free).

It plays the four drive nodes and the EPS of docs/mani_protocol.md:

- steering moves toward the commanded orientation at a finite rate and the
  wheel ramps to the commanded velocity, while the motor power is on and the
  switchCmd enabled steerMode / driveMode (without drive power the wheel
  coasts to a stop);
- after an orientationCmd or velocityCmd a node sends one locomotionFb
  task_completed = 1 once both set points are reached;
- odometryFb streams while publisherMode is on;
- the EPS answers powerCmd with powerFb, reports powerFb and currentFb
  periodically, and errorWrn / currentWrn from the sensor currents, which
  can be forced to over-current values (fault injection);
- a node can be made silent (it neither moves nor answers);
- unknown ids, feedback ids and invalid frames are ignored (and counted).

Use RoverSim(bus, config).start() / stop() for a running simulator, or
handle() and advance() to drive it step by step. main() is the CLI behind
scripts/mani_sim_rover.
"""
from __future__ import annotations

import argparse
import logging
import math
import signal
import threading
import time
from dataclasses import dataclass
from typing import Callable, Dict, List, Optional, Sequence

import can

from . import protocol as p
from .config import ConfigError, ManiConfig, load_config
from .odometry import counters_from_count

LOG = logging.getLogger("mani_ros.rover_sim")

# Control period of the simulated nodes [s].
TICK = 0.01
# A set point counts as reached no sooner than this after the last command
# [s], so that an orientationCmd and the velocityCmd right behind it are
# judged as one command even on a slow machine.
SETTLE = 0.05

# Fault names of inject(), as in the simulated rover's ROS service.
FAULT_SILENT = "silent"
FAULT_CURRENT_WARNING = "current_warning"
FAULT_OVERCURRENT = "overcurrent"
FAULT_CLEAR = "clear"
ALL = 255


@dataclass
class DriveState:
    """One simulated drive node; orientation [steer pulses], velocity
    [drive pulses/s], count [drive pulses since zeroing]."""
    node_id: int
    steer_mode: bool = False
    drive_mode: bool = False
    publisher_mode: bool = False
    orientation: float = 0.0
    velocity: float = 0.0
    count: float = 0.0
    target_orientation: int = 0
    target_velocity: int = 0
    task_pending: bool = False
    commanded_at: float = 0.0
    silent: bool = False
    next_odometry: float = 0.0

    def feedback(self, ppr: int) -> p.OdometryFb:
        pulses, revolutions = counters_from_count(int(self.count), ppr)
        return p.OdometryFb(self.node_id, _int16(self.orientation), _int16(self.velocity),
                            pulses, revolutions)


def _int16(value: float) -> int:
    return max(p.INT16_MIN, min(p.INT16_MAX, int(round(value))))


def _toward(value: float, target: float, step: float) -> float:
    if abs(target - value) <= step:
        return float(target)
    return value + math.copysign(step, target - value)


class RoverSim:
    """The four drive nodes and the EPS of a MANI rover on one CAN bus."""

    def __init__(self, bus: can.BusABC, config: ManiConfig,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.bus = bus
        self.config = config
        self._clock = clock
        sim = config.simulation
        self._steer_rate = sim.steer_rate * config.STEER_ENC_PPR / (2.0 * math.pi)   # [steer pulses/s]
        self._drive_accel = sim.drive_acceleration / config.wheel_circumference * config.DRIVE_ENC_PPR  # [pulses/s^2]
        self.drives: Dict[int, DriveState] = {}
        for node in p.DRIVE_NODES:
            # The wheels start straight ahead, in the configured encoding
            # (the rover's: STEER_ENC_PPR / 4 pulses).
            straight = int(round(-config.steering.offsets[p.NODE_NAMES[node]]
                                 * config.STEER_ENC_PPR / (2.0 * math.pi)))
            self.drives[node] = DriveState(node, orientation=float(straight),
                                           target_orientation=straight)
        self.motor_power = sim.motor_power_on
        self.eps_silent = False
        self.forced_current: Dict[int, float] = {}   # sensor index -> A
        self._reported_errors: Optional[tuple] = None
        self._reported_warnings: Optional[tuple] = None
        self._next_eps = 0.0
        self.time = 0.0
        self.stats = {"received": 0, "handled": 0, "ignored": 0, "invalid": 0, "sent": 0,
                      "send_errors": 0}
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None

    # -- running -------------------------------------------------------------

    def start(self) -> None:
        """Run the simulator in a background thread until stop()."""
        if self._thread is not None:
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="mani_rover_sim", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None

    def _run(self) -> None:
        last = self._clock()
        while not self._stop.is_set():
            try:
                frame = self.bus.recv(timeout=TICK)
                if frame is not None:
                    self.handle(frame)
                now = self._clock()
                if now - last >= TICK:
                    self.advance(now - last)
                    last = now
            except Exception:  # noqa: BLE001 - the simulator must outlive any bad frame or bus hiccup
                LOG.exception("simulated rover: unexpected error, carrying on")
                time.sleep(0.5)   # a broken bus would otherwise flood the log

    # -- frames in ------------------------------------------------------------

    def handle(self, frame: can.Message) -> None:
        """Process one received frame (commands only; everything else is ignored)."""
        with self._lock:
            self.stats["received"] += 1
            try:
                message = p.decode_can_message(frame)
            except p.ProtocolError as error:
                self.stats["invalid"] += 1
                LOG.debug("ignored invalid frame 0x%X: %s", frame.arbitration_id, error)
                return
            if isinstance(message, p.PowerCmd):
                self._power_cmd(message)
            elif isinstance(message, (p.SwitchCmd, p.OrientationCmd, p.VelocityCmd)):
                self._drive_cmd(message)
            else:
                self.stats["ignored"] += 1   # feedback of other nodes: not for us
                return
            self.stats["handled"] += 1

    def _power_cmd(self, message: p.PowerCmd) -> None:
        if self.eps_silent:
            return
        self.motor_power = message.motor_power
        self._send(p.PowerFb(self.motor_power))

    def _drive_cmd(self, message: p.Message) -> None:
        drive = self.drives[message.node_id]  # type: ignore[union-attr]
        if drive.silent:
            return
        if isinstance(message, p.SwitchCmd):
            drive.steer_mode = message.steer_mode
            drive.drive_mode = message.drive_mode
            drive.publisher_mode = message.publisher_mode
            if message.zero_encoders:
                drive.orientation = 0.0
                drive.target_orientation = 0
                drive.count = 0.0
            return
        if isinstance(message, p.OrientationCmd):
            drive.target_orientation = message.orientation
        else:
            drive.target_velocity = message.velocity  # type: ignore[union-attr]
        drive.task_pending = True
        drive.commanded_at = self.time

    # -- time -----------------------------------------------------------------

    def advance(self, dt: float) -> None:
        """Move the simulated motors by dt seconds and send what is due."""
        with self._lock:
            self.time += dt
            for drive in self.drives.values():
                self._move(drive, dt)
                if drive.silent:
                    continue
                if (drive.task_pending and self._due(drive.commanded_at + SETTLE)
                        and self._reached(drive)):
                    drive.task_pending = False
                    self._send(p.LocomotionFb(drive.node_id, True))
                if drive.publisher_mode and self._due(drive.next_odometry):
                    drive.next_odometry = self._next(drive.next_odometry,
                                                     self.config.simulation.odometry_period)
                    self._send(drive.feedback(self.config.DRIVE_ENC_PPR))
            self._eps()

    def _due(self, when: float) -> bool:
        return self.time + 1e-9 >= when   # sums of TICK are not exact

    def _next(self, when: float, period: float) -> float:
        # Keep the cadence; after a pause (publisher off, stalled thread) restart it.
        return when + period if when + period > self.time else self.time + period

    def _move(self, drive: DriveState, dt: float) -> None:
        if self.motor_power and drive.steer_mode:
            drive.orientation = _toward(drive.orientation, drive.target_orientation,
                                        self._steer_rate * dt)
        target = drive.target_velocity if self.motor_power and drive.drive_mode else 0
        before = drive.velocity
        drive.velocity = _toward(drive.velocity, target, self._drive_accel * dt)
        drive.count += (before + drive.velocity) / 2.0 * dt

    def _reached(self, drive: DriveState) -> bool:
        sim = self.config.simulation
        return (abs(drive.orientation - drive.target_orientation) <= sim.orientation_tolerance
                and abs(drive.velocity - drive.target_velocity) <= sim.velocity_tolerance)

    # -- EPS -------------------------------------------------------------------

    def _limits(self) -> List[float]:
        return [self.config.power.max_current[name] for name in p.EPS_SENSORS]

    def currents(self) -> List[float]:
        """Present current of each EPS sensor [A] (EPS_SENSORS order)."""
        limits = self._limits()
        wheels = []
        for node, limit in zip(p.DRIVE_NODES, limits[1:]):
            drive = self.drives[node]
            moving = self.motor_power and (drive.steer_mode or drive.drive_mode)
            load = (abs(drive.velocity) / self.config.max_velocity_pulses * 0.25 * limit
                    if self.motor_power else 0.0)
            wheels.append((0.03 * limit if moving else 0.0) + load)
        values = [0.05 * limits[0] + sum(wheels)] + wheels
        for index, forced in self.forced_current.items():
            values[index] = forced
        return values

    def _eps(self) -> None:
        if self.eps_silent:
            return
        limits = self._limits()
        currents = self.currents()
        errors = tuple(c > limit for c, limit in zip(currents, limits))
        warnings = tuple(c > 0.8 * limit for c, limit in zip(currents, limits))
        periodic = self._due(self._next_eps)
        if periodic:
            self._next_eps = self._next(self._next_eps, self.config.simulation.eps_period)
            self._send(p.PowerFb(self.motor_power))
            for index, (current, limit) in enumerate(zip(currents, limits)):
                self._send(p.CurrentFb.from_amperes(index, current, limit))
        # A warning frame goes out when its flags change (the all-clear too)
        # and is repeated while any flag is set.
        if errors != self._reported_errors or (periodic and any(errors)):
            self._send(p.ErrorWrn(*errors))
        if warnings != self._reported_warnings or (periodic and any(warnings)):
            self._send(p.CurrentWrn(*warnings))
        self._reported_errors, self._reported_warnings = errors, warnings

    # -- fault injection -------------------------------------------------------

    def set_silent(self, node_id: int, silent: bool = True) -> None:
        """A drive node (1..4) or the EPS (0) stops (or resumes) answering."""
        with self._lock:
            if node_id == p.POWER_SUPPLY:
                self.eps_silent = silent
            elif node_id in self.drives:
                self.drives[node_id].silent = silent
            else:
                raise ValueError("node %r is not 0 (EPS) or a drive node 1..4" % (node_id,))

    def force_current(self, sensor_index: int, amperes: Optional[float]) -> None:
        """Force one EPS sensor's current [A] (None: back to the model)."""
        if not 0 <= sensor_index < len(p.EPS_SENSORS):
            raise ValueError("sensor %r is not 0..%d (%s)" % (sensor_index, len(p.EPS_SENSORS) - 1,
                                                             ", ".join(p.EPS_SENSORS)))
        with self._lock:
            if amperes is None:
                self.forced_current.pop(sensor_index, None)
            else:
                self.forced_current[sensor_index] = max(0.0, float(amperes))

    def inject(self, fault: str, index: int, active: bool = True) -> str:
        """Fault injection by name (the ROS service of the simulated rover):
        silent (index = node 0..4), current_warning / overcurrent (index =
        sensor 0..4), clear (index = node or sensor, 255 = everything).
        Returns what was done; raises ValueError for a bad request."""
        if fault == FAULT_SILENT:
            self.set_silent(index, active)
            return "node %d %s" % (index, "silent" if active else "answers again")
        if fault in (FAULT_CURRENT_WARNING, FAULT_OVERCURRENT):
            if not 0 <= index < len(p.EPS_SENSORS):
                raise ValueError("sensor %r is not 0..%d (%s)" % (index, len(p.EPS_SENSORS) - 1,
                                                                 ", ".join(p.EPS_SENSORS)))
            limit = self._limits()[index]
            level = limit * (0.9 if fault == FAULT_CURRENT_WARNING else 1.2)
            self.force_current(index, level if active else None)
            return "sensor %s: %s" % (p.EPS_SENSORS[index],
                                      "%.1f A" % level if active else "back to normal")
        if fault == FAULT_CLEAR:
            with self._lock:
                if index == ALL:
                    self.forced_current.clear()
                    self.eps_silent = False
                    for drive in self.drives.values():
                        drive.silent = False
                    return "all faults cleared"
                if not 0 <= index < len(p.EPS_SENSORS):
                    raise ValueError("clear needs a node/sensor 0..4 or 255, got %r" % (index,))
                self.forced_current.pop(index, None)
                if index <= 4:
                    self.set_silent(index, False)
                return "faults of %d cleared" % index
        raise ValueError("unknown fault %r (known: %s)" % (
            fault, ", ".join((FAULT_SILENT, FAULT_CURRENT_WARNING, FAULT_OVERCURRENT, FAULT_CLEAR))))

    # -- frames out ------------------------------------------------------------

    def _send(self, message: p.Message) -> None:
        try:
            self.bus.send(p.to_can_message(message), timeout=0.1)
            self.stats["sent"] += 1
        except can.CanError as error:
            # A full transmit queue must not stop the simulated rover.
            self.stats["send_errors"] += 1
            LOG.warning("simulated rover: cannot send %s: %s", p.describe(message), error)


def main(argv: Optional[Sequence[str]] = None) -> int:
    """CLI: run the simulated rover on a CAN interface until Ctrl-C / SIGTERM."""
    parser = argparse.ArgumentParser(
        prog="mani_sim_rover",
        description="Simulated MANI rover (four drive nodes and the EPS) on a CAN bus.")
    parser.add_argument("--interface", default="socketcan", help="python-can interface (default socketcan)")
    parser.add_argument("--channel", default=None,
                        help="CAN channel (default: can.sim_device of the configuration)")
    parser.add_argument("--config", default=None, help="mani.yaml (default: the package's)")
    parser.add_argument("--silent", type=int, action="append", default=[], metavar="NODE",
                        help="node 0..4 that never answers (repeatable)")
    parser.add_argument("--motor-power", choices=("on", "off"), default=None,
                        help="motor power at start (default: simulation.motor_power_on)")
    parser.add_argument("--verbose", action="store_true", help="log every ignored frame")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    try:
        config = load_config(args.config)
    except ConfigError as error:
        LOG.error("%s", error)
        return 2
    channel = args.channel or config.can.sim_device
    try:
        bus = can.Bus(interface=args.interface, channel=channel)
    except (can.CanError, OSError, ValueError, ImportError) as error:
        LOG.error("cannot open CAN %s %s: %s", args.interface, channel, error)
        return 1
    sim = RoverSim(bus, config)
    try:
        for node in args.silent:
            sim.set_silent(node)
        if args.motor_power is not None:
            sim.motor_power = args.motor_power == "on"
    except ValueError as error:
        LOG.error("%s", error)
        bus.shutdown()
        return 2
    done = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: done.set())
    sim.start()
    LOG.info("simulated MANI rover on %s %s (motor power %s)", args.interface, channel,
             "on" if sim.motor_power else "off")
    try:
        while not done.wait(0.5):
            pass
    finally:
        sim.stop()
        bus.shutdown()
        LOG.info("simulated rover stopped: %s", sim.stats)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

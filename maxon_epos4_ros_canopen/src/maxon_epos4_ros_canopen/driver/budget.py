"""How much of the CAN bus a configuration uses, per SYNC period (ROS-free).

Frame length: a CAN 2.0A data frame (11-bit identifier) with n data bytes
is, with worst-case bit stuffing,

    8n + 44 + floor((34 + 8n - 1) / 4)  bits

44 bits of frame overhead (start of frame, identifier, RTR, IDE, r0, DLC,
CRC, CRC delimiter, ACK slot and delimiter, end of frame), of which the
34 + 8n bits from the start of frame to the end of the CRC are subject to
stuffing, at worst one stuff bit per 4 bits after the first. This is the
bound of R. I. Davis, A. Burns, R. J. Bril, J. J. Lukkien, "Controller Area
Network (CAN) schedulability analysis: refuted, revisited and revised",
Real-Time Systems 35(3), 2007, section 3 (there with the 3-bit
intermission included: 8n + 47 + ...). The bus is busy for the intermission
too, so each frame here costs its stuffed length plus 3 bits.

What is counted per SYNC period (``sync/interval_ms``, or ``update_ms``
without SYNC):

* the SYNC (1 data byte with the overflow counter, else none);
* the master's heartbeat (``heartbeat/rate``) and every drive's (0x1017
  from the DCF or ``dcf_overlay``), scaled to the period;
* per axis, TxPDOs by transmission type (CiA 301: type 0, acyclic
  synchronous, at worst every SYNC; type n in 1..240 every n-th SYNC;
  252/253, on remote request only, never, as the driver sends no RTR;
  254/255, event driven, every event timer, else every cycle) and the RxPDOs the cycle sends every
  period: the one with the controlword and those with the targets of the
  node's modes (a PPM/PVM target may change every cycle: counted as such);
  other RxPDOs are sent on change and refreshed every ``REFRESH_CYCLES``.

SDO traffic (``publish`` objects read with ``!``, services) and EMCYs are
not periodic and not counted.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Mapping, Optional, Sequence, Tuple, Union

from ..config_schema import DriverConfig, NodeConfig
from .outputs import REFRESH_CYCLES  # the cycle resends an unchanged RxPDO this often
from .plan import CONTROLWORD, MODE_TARGETS, PRODUCER_HEARTBEAT, RX_REQUIRED, MapPlan, NodePlan

DEFAULT_BITRATE = 1_000_000
INTERMISSION_BITS = 3
LOAD_LIMIT = 0.8          # check_budget warns above this share of the bit rate
MAX_NODES = 127
SYNC_COB_ID = 0x080

Plans = Union[Mapping[str, NodePlan], Sequence[NodePlan]]


def frame_bits(data_bytes: int) -> int:
    """Worst-case stuffed length of a CAN 2.0A data frame, intermission excluded."""
    if not 0 <= data_bytes <= 8:
        raise ValueError("a classic CAN frame carries 0..8 data bytes, not %r" % (data_bytes,))
    n = 8 * data_bytes
    return n + 44 + (34 + n - 1) // 4


def wire_bits(data_bytes: int) -> int:
    """Bits a frame keeps the bus busy: stuffed frame plus intermission."""
    return frame_bits(data_bytes) + INTERMISSION_BITS


@dataclass(frozen=True)
class Frame:
    name: str
    cob_id: int
    data_bytes: int
    per_sync: float     # frames per SYNC period (0.5: every other SYNC)

    @property
    def bits(self) -> float:
        return self.per_sync * wire_bits(self.data_bytes)


@dataclass(frozen=True)
class AxisBudget:
    name: str
    node_id: int
    layout: str         # NodePlan.source
    modes: Tuple[int, ...]
    frames: Tuple[Frame, ...]

    @property
    def frames_per_sync(self) -> float:
        return sum(f.per_sync for f in self.frames)

    @property
    def pdo_frames_per_sync(self) -> float:
        return sum(f.per_sync for f in self.frames if "PDO" in f.name)

    @property
    def bits_per_sync(self) -> float:
        return sum(f.bits for f in self.frames)


@dataclass(frozen=True)
class BusBudget:
    period_s: float
    bitrate: int
    shared: Tuple[Frame, ...]    # SYNC, master heartbeat
    axes: Tuple[AxisBudget, ...]

    @property
    def frames_per_sync(self) -> float:
        return sum(f.per_sync for f in self.shared) + sum(a.frames_per_sync for a in self.axes)

    @property
    def bits_per_sync(self) -> float:
        return sum(f.bits for f in self.shared) + sum(a.bits_per_sync for a in self.axes)

    @property
    def load(self) -> float:
        """Share of the bit rate in use (1.0: the bus is full)."""
        return self.bits_per_sync / (self.bitrate * self.period_s)

    def max_axes(self, limit: float = 1.0) -> int:
        """How many axes like the most demanding configured one fit under
        ``limit`` x the bit rate, next to the SYNC and master heartbeat."""
        if not self.axes:
            return 0
        axis = max(a.bits_per_sync for a in self.axes)
        room = limit * self.bitrate * self.period_s - sum(f.bits for f in self.shared)
        return max(0, min(MAX_NODES, int(math.floor(room / axis)))) if axis > 0 else MAX_NODES


def _period_s(config: DriverConfig) -> float:
    sync = config.sync
    return (sync.interval_ms if sync.interval_ms > 0 else sync.update_ms) / 1000.0


def _payload(m: MapPlan) -> int:
    return (sum(bits for _, bits in m.entries) + 7) // 8


def _heartbeat_ms(plan: NodePlan) -> int:
    for w in plan.writes:
        if w.key == PRODUCER_HEARTBEAT:
            return int.from_bytes(w.data[:2], "little")
    return 0


def tpdo_per_sync(m: MapPlan, sync_ms: float, update_ms: float) -> float:
    """Frames of a TxPDO per SYNC period (per cycle without SYNC), by its
    transmission type (see the module text)."""
    t = m.trans_type
    period_ms = sync_ms if sync_ms > 0 else update_ms
    if sync_ms > 0 and t <= 240:
        return 1.0 / max(1, t)
    if 241 <= t <= 251:
        raise ValueError("TxPDO%d: transmission type %d is reserved (CiA 301)" % (m.number, t))
    if t in (252, 253):
        return 0.0
    return period_ms / float(m.event_timer or update_ms)


def axis_budget(node: NodeConfig, plan: NodePlan, config: DriverConfig) -> AxisBudget:
    """Frames of one axis per SYNC period (see the module text for the rules)."""
    sync = config.sync
    period = _period_s(config)
    cycles_per_sync = period / (sync.update_ms / 1000.0)
    modes = plan.modes or node.modes
    if modes:
        every_cycle = {CONTROLWORD} | {k for m in modes for k in MODE_TARGETS.get(m, ())}
    else:  # modes unknown: any target may be the cyclic one
        every_cycle = set(RX_REQUIRED)
    frames = []
    for m in plan.rx:
        if not (m.enabled and m.entries):
            continue
        per_cycle = 1.0 if any(k in every_cycle for k, _ in m.entries) else 1.0 / REFRESH_CYCLES
        frames.append(Frame("RxPDO%d" % m.number, m.cob_id, _payload(m), per_cycle * cycles_per_sync))
    for m in plan.tx:
        if not (m.enabled and m.entries):
            continue
        per_sync = tpdo_per_sync(m, sync.interval_ms, sync.update_ms)
        if per_sync > 0:
            frames.append(Frame("TxPDO%d" % m.number, m.cob_id, _payload(m), per_sync))
    hb = _heartbeat_ms(plan)
    if hb > 0:
        frames.append(Frame("heartbeat", 0x700 + node.node_id, 1, period / (hb / 1000.0)))
    return AxisBudget(node.name, node.node_id, plan.source, tuple(modes), tuple(frames))


def _plan_list(config: DriverConfig, plans: Plans) -> Sequence[NodePlan]:
    if isinstance(plans, Mapping):
        out = []
        for n in config.nodes:
            plan = plans.get(n.name, plans.get(n.key))
            if plan is None:
                raise KeyError("no plan for node %s" % n.name)
            out.append(plan)
        return out
    if len(plans) != len(config.nodes):
        raise ValueError("%d plans for %d nodes" % (len(plans), len(config.nodes)))
    return list(plans)


def config_bitrate(config: DriverConfig) -> int:
    return int(getattr(config.bus, "bitrate", None) or DEFAULT_BITRATE)


def bus_budget(config: DriverConfig, plans: Plans, bitrate: Optional[int] = None) -> BusBudget:
    """The bus load of ``config`` with ``plans`` (a plan per node, by node
    name or in the order of ``config.nodes``)."""
    period = _period_s(config)
    shared = []
    if config.sync.interval_ms > 0:
        shared.append(Frame("SYNC", SYNC_COB_ID, 1 if config.sync.overflow else 0, 1.0))
    hb = config.heartbeat
    if hb is not None:
        shared.append(Frame("master heartbeat", hb.can_id, len(hb.data), hb.rate * period))
    axes = tuple(axis_budget(n, p, config) for n, p in zip(config.nodes, _plan_list(config, plans)))
    return BusBudget(period, int(bitrate or config_bitrate(config)), tuple(shared), axes)


def check_budget(config: DriverConfig, plans: Plans, bitrate: Optional[int] = None) -> Optional[str]:
    """A warning when the configured bus would be more than 80 % loaded, else None."""
    b = bus_budget(config, plans, bitrate)
    if b.load <= LOAD_LIMIT:
        return None
    return ("CAN bus budget: %.0f %% of %d bit/s in use at a %.3g ms SYNC period (%d axes, %.1f frames, "
            "%.0f bits per period with worst-case stuffing); at most %d such axes stay under %.0f %%: "
            "use pdo_layout: compact (with readings_every: N, the readings beside the statusword and "
            "position every N-th SYNC), a longer sync/interval_ms or fewer axes on this bus"
            % (100 * b.load, b.bitrate, b.period_s * 1000, len(b.axes), b.frames_per_sync, b.bits_per_sync,
               b.max_axes(LOAD_LIMIT), 100 * LOAD_LIMIT))


def _rate(per_sync: float) -> str:
    if per_sync == 1.0:
        return "every period"
    if per_sync > 0 and abs(1.0 / per_sync - round(1.0 / per_sync)) < 1e-9:
        return "every %d periods" % round(1.0 / per_sync)
    return "%.3g per period" % per_sync


def format_budget(b: BusBudget) -> str:
    """A table for people: per axis, shared frames, total and headroom."""
    names = {1: "PPM", 3: "PVM", 6: "HM", 8: "CSP", 9: "CSV", 10: "CST"}
    lines = ["bus budget: %d bit/s, SYNC period %.3g ms, worst-case bit stuffing (+3 bit intermission)"
             % (b.bitrate, b.period_s * 1000),
             "%-22s %4s %-8s %-10s %13s %12s %13s" % ("axis", "node", "layout", "modes", "PDOs/period",
                                                      "frames/per.", "bits/period")]
    for a in b.axes:
        lines.append("%-22s %4d %-8s %-10s %13.2f %12.2f %13.0f" % (
            a.name, a.node_id, a.layout, ",".join(names.get(m, str(m)) for m in a.modes) or "-",
            a.pdo_frames_per_sync, a.frames_per_sync, a.bits_per_sync))
    for f in b.shared:
        lines.append("%-22s %4s %-8s %-10s %13s %12.2f %13.0f" % (f.name, "", "", "", "", f.per_sync, f.bits))
    shown: Tuple[Tuple[str, int, float], ...] = ()
    for a in b.axes:  # each axis whose frames differ from the one above
        kinds = tuple((f.name, f.data_bytes, f.per_sync) for f in a.frames)
        if kinds != shown:
            lines.append("  %s: %s" % (a.name, ", ".join("%s %d B %s" % (f.name, f.data_bytes, _rate(f.per_sync))
                                                         for f in a.frames)))
            shown = kinds
    lines.append("total: %.2f frames and %.0f bits per period = %.0f frames/s, %.0f bit/s, load %.1f %%"
                 % (b.frames_per_sync, b.bits_per_sync, b.frames_per_sync / b.period_s,
                    b.bits_per_sync / b.period_s, 100 * b.load))
    lines.append("axes like the most demanding one: at most %d under %.0f %% load, %d at 100 %%"
                 % (b.max_axes(LOAD_LIMIT), 100 * LOAD_LIMIT, b.max_axes(1.0)))
    if b.axes:
        lines.append("PDO frames per axis per period: %.3g on average"
                     % (sum(a.pdo_frames_per_sync for a in b.axes) / len(b.axes)))
    return "\n".join(lines)


def plan_config(config: DriverConfig) -> "Mapping[str, NodePlan]":
    """Every node's plan, as the driver makes it at start (no bus needed)."""
    from ..config_schema import ConfigError
    from ..objects import load_dictionary
    from .plan import plan_node

    plans = {}
    for n in config.nodes:
        try:
            od = load_dictionary(n.eds_file, n.node_id)
        except Exception as e:  # canopen raises many kinds on a bad file
            raise ConfigError(config.source, "nodes/%s/eds_file" % n.key, "cannot read %s: %s" % (n.eds_file, e)) from None
        plans[n.name] = plan_node(n, od, config.sync, config.source, config.heartbeat)
    return plans


def main(argv: Optional[Sequence[str]] = None, resolver: Optional[Callable[[str], str]] = None) -> int:
    """``bus_budget [--bitrate B] LAYER.yaml...``: the YAML layers the node
    loads, merged in order; prints the budget. Exit 0 when the load is at
    most 80 %, 1 above, 2 on a configuration error."""
    import argparse

    from ..config import ConfigError, load_config
    from ..config_reader import load_yaml_files

    ap = argparse.ArgumentParser(prog="bus_budget", description="CAN bus load of a driver configuration "
                                 "(frames and bits per SYNC period, worst-case bit stuffing).")
    ap.add_argument("layers", nargs="+", metavar="LAYER.yaml", help="bus, node, ROS and controller layers")
    ap.add_argument("--bitrate", type=int, default=None,
                    help="bit/s (default: the bus layer's bitrate, else %d)" % DEFAULT_BITRATE)
    args = ap.parse_args(argv)
    if args.bitrate is not None and args.bitrate <= 0:
        ap.error("--bitrate must be > 0")
    try:
        config = load_config(load_yaml_files(args.layers), ", ".join(args.layers), resolver)
        b = bus_budget(config, plan_config(config), args.bitrate)
    except (ConfigError, OSError, ValueError) as e:
        print("bus_budget: %s" % e)
        return 2
    print(format_budget(b))
    warning = check_budget(config, plan_config(config), b.bitrate)
    if warning:
        print("WARNING: " + warning)
        return 1
    return 0

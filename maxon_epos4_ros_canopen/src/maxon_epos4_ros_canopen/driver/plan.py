"""What init writes to a node, worked out once at start from its DCF/EDS.

* the configuration the DCF carries (its ParameterValues) as ready-to-send
  SDO payloads, with ``dcf_overlay`` on top;
* the PDO mapping: the DCF's own when it already carries every object the
  driver exchanges each cycle, otherwise one the driver lays out itself;
  with the node layer's ``pdo_layout: compact``, the driver's smallest
  layout for the node's modes (see ``compact_maps``): objects it leaves out
  are moved by SDO (``NodePlan.sdo_rx()``/``sdo_tx()``).

Everything is checked here, before any frame is sent, so a bad overlay value
or an object missing from the dictionary stops the node at start.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from functools import cached_property
from typing import Any, Dict, Iterable, List, Mapping, Optional, Sequence, Tuple

from canopen.objectdictionary import ODArray, ODRecord, ODVariable, ObjectDictionary
from canopen.objectdictionary import datatypes as dt

from ..config_schema import ConfigError, HeartbeatConfig, NodeConfig, SyncConfig
from ..objects import (ObjectKey, ObjectStringError, ObjectValueError, encode_value,
                       find_variable, is_writable)
from .modes import (CONTROLWORD, MODES, MODES_DISPLAY, MODES_OF_OPERATION, POSITION_ACTUAL, STATUSWORD,
                    TARGET_POSITION, TARGET_TORQUE, TARGET_VELOCITY, VELOCITY_ACTUAL)


HOMING_METHOD = ObjectKey(0x6098)
PRODUCER_HEARTBEAT = ObjectKey(0x1017)

# Objects the driver writes in its RPDOs every cycle, and reads from TPDOs.
RX_REQUIRED = (CONTROLWORD, MODES_OF_OPERATION, TARGET_POSITION, TARGET_VELOCITY, TARGET_TORQUE)
TX_REQUIRED = (STATUSWORD, MODES_DISPLAY, POSITION_ACTUAL, VELOCITY_ACTUAL)
DRIVER_OWNED = frozenset(RX_REQUIRED)  # set_object refuses these: the cycle owns them

# The target each mode of operation takes (HM needs only the controlword).
MODE_TARGETS: Dict[int, Tuple[ObjectKey, ...]] = {
    n: ((m.target,) if m.target is not None else ()) for n, m in MODES.items()}
CYCLIC_MODES = tuple(n for n, m in MODES.items() if m.cyclic)  # their target goes out every SYNC
PDO_BITS = 64

RPDO_COMM, RPDO_MAP, TPDO_COMM, TPDO_MAP = 0x1400, 0x1600, 0x1800, 0x1A00
PDO_COUNT = 4
_RX_COB_BASE = (0x200, 0x300, 0x400, 0x500)
_TX_COB_BASE = (0x180, 0x280, 0x380, 0x480)
_PDO_NOT_VALID = 0x80000000

# Parameter values init must not write although the DCF carries them:
# PDO records (configured separately, in the safe order), store/restore
# (writing would save to flash), error history (writing clears it), SDO
# server parameters (would cut the line init talks over), program control.
_SKIP_RANGES = ((0x1400, 0x1BFF), (0x1010, 0x1011), (0x1003, 0x1003),
                (0x1200, 0x12FF), (0x1F50, 0x1FFF))


@dataclass(frozen=True)
class SdoWrite:
    key: ObjectKey
    data: bytes
    text: str          # for messages: "0x6098 sub 0 = -3 (DCF)"


@dataclass(frozen=True)
class MapPlan:
    number: int        # 1..4
    cob_id: int
    enabled: bool
    trans_type: int
    event_timer: Optional[int]
    rtr_allowed: bool
    entries: Tuple[Tuple[ObjectKey, int], ...]  # (object, bits)

    @property
    def length(self) -> int:
        """Bytes of a frame of this PDO."""
        return sum(bits for _, bits in self.entries) // 8


@dataclass(frozen=True)
class NodePlan:
    """What init writes; the PDO maps say exactly which objects travel by PDO.

    source: "dcf" (the DCF's mapping), "driver" (the driver's own, because
    the DCF lacked objects: every RX_REQUIRED/TX_REQUIRED object mapped) or
    "compact" (``pdo_layout: compact``: only what ``modes`` need; the rest,
    ``sdo_rx()``/``sdo_tx()``, is the core's to move by SDO).
    modes: the modes the layout serves, () when it serves every mode.
    """
    writes: Tuple[SdoWrite, ...]
    rx: Tuple[MapPlan, ...]
    tx: Tuple[MapPlan, ...]
    source: str
    modes: Tuple[int, ...] = ()

    def write_with_canopen(self, node: Any) -> None:
        """Write this plan's PDO maps to a drive through python-canopen's own
        PDO classes (``node``: a ``canopen.RemoteNode``): an independent
        master that sets up the same PDOs, for benchmarks and for tests that
        hold the plan against the wire."""
        for plans, maps in ((self.rx, node.rpdo.map), (self.tx, node.tpdo.map)):
            for mp in plans:
                pdo = maps[mp.number]
                pdo.clear()
                for key, bits in mp.entries:
                    pdo.add_variable(key.index, key.subindex, bits)
                pdo.cob_id, pdo.enabled, pdo.trans_type = mp.cob_id, mp.enabled, mp.trans_type
                pdo.save()

    @cached_property
    def written(self) -> Mapping[ObjectKey, bytes]:
        """The data init writes to each object (DCF values and overlay)."""
        return {w.key: w.data for w in self.writes}

    def configured_value(self, od: ObjectDictionary, key: ObjectKey) -> Optional[int]:
        """The value init writes to ``key`` (DCF or overlay), else the
        dictionary's default; None when the dictionary lacks the object."""
        try:
            var = find_variable(od, key)
        except ObjectStringError:
            return None
        data = self.written.get(key)
        if data is not None:
            return int(var.decode_raw(data))
        value = var.default if var.value is None else var.value
        return None if value is None else int(value)

    def rx_keys(self) -> List[ObjectKey]:
        return [k for m in self.rx if m.enabled for k, _ in m.entries]

    def tx_keys(self) -> List[ObjectKey]:
        return [k for m in self.tx if m.enabled for k, _ in m.entries]

    def rx_mapped(self, key: ObjectKey) -> bool:
        return key in self.rx_keys()

    def tx_mapped(self, key: ObjectKey) -> bool:
        return key in self.tx_keys()

    def sdo_rx(self) -> List[ObjectKey]:
        """Objects the core writes that no RxPDO carries: write them by SDO
        when they change (0x6060 at a mode switch)."""
        have = set(self.rx_keys())
        return [k for k in RX_REQUIRED if k not in have]

    def sdo_tx(self) -> List[ObjectKey]:
        """Objects the core reads that no TxPDO carries: read them by SDO
        when needed (0x6061 to confirm a mode switch)."""
        have = set(self.tx_keys())
        return [k for k in TX_REQUIRED if k not in have]

    def tx_period_ms(self, key: ObjectKey, sync: SyncConfig) -> Optional[float]:
        """How often a TxPDO brings ``key`` (ms), as planned: a type-N PDO
        every N SYNC periods, an event-timer PDO every timer; None when no
        TxPDO carries it or when it comes only on change."""
        for m in self.tx:
            if m.enabled and any(k == key for k, _ in m.entries):
                if sync.interval_ms > 0 and 1 <= m.trans_type <= 240:
                    return m.trans_type * sync.interval_ms
                return float(m.event_timer) if m.event_timer else None
        return None

    def supports(self, mode: int) -> bool:
        """Whether the layout carries what ``mode`` needs every cycle."""
        have = set(self.rx_keys())
        return mode in MODE_TARGETS and CONTROLWORD in have and all(k in have for k in MODE_TARGETS[mode])


def _variables(od: ObjectDictionary) -> Iterable[ODVariable]:
    for obj in od.values():
        if isinstance(obj, ODVariable):
            yield obj
        elif isinstance(obj, (ODRecord, ODArray)):
            for sub in obj.values():
                yield sub


def _skipped(index: int) -> bool:
    return any(lo <= index <= hi for lo, hi in _SKIP_RANGES)


_NODEID_RE = re.compile(r"^\$NODEID\s*\+\s*(\S+)$|^(\S+)\s*\+\s*\$NODEID$", re.IGNORECASE)


def _overlay_value(var: ODVariable, text: str, node_id: int):
    """Encode an overlay value; ``$NODEID+0x200`` is allowed as in EDS files."""
    m = _NODEID_RE.match(text.strip())
    if m:
        base = encode_value(var, m.group(1) or m.group(2))
        return encode_value(var, str(base + node_id))
    return encode_value(var, text)


def _pdo_value(od: ObjectDictionary, index: int, sub: int) -> Optional[int]:
    try:
        var = od[index][sub]
    except KeyError:
        return None
    value = var.value if var.value is not None else var.default
    return value if isinstance(value, int) else None


def dcf_maps(od: ObjectDictionary, rx: bool) -> List[MapPlan]:
    """The PDO configuration a DCF carries (ParameterValue, else default)."""
    comm, mapping = (RPDO_COMM, RPDO_MAP) if rx else (TPDO_COMM, TPDO_MAP)
    out = []
    for n in range(PDO_COUNT):
        cob = _pdo_value(od, comm + n, 1)
        count = _pdo_value(od, mapping + n, 0)
        if cob is None or count is None:
            continue
        entries = []
        for sub in range(1, count + 1):
            raw = _pdo_value(od, mapping + n, sub) or 0
            index, subindex, bits = raw >> 16, (raw >> 8) & 0xFF, raw & 0xFF
            if index and bits:
                entries.append((ObjectKey(index, subindex), bits))
        trans = _pdo_value(od, comm + n, 2)
        out.append(MapPlan(n + 1, cob & 0x1FFFFFFF, not cob & _PDO_NOT_VALID,
                           255 if trans is None else trans, None, not cob & 0x40000000, tuple(entries)))
    return out


def _own_maps(od: ObjectDictionary, node_id: int, keys: Sequence[ObjectKey], rx: bool,
              trans_type: int, event_timer: Optional[int]) -> List[MapPlan]:
    """First-fit packing of keys into at most four 8-byte PDOs."""
    bins: List[List[Tuple[ObjectKey, int]]] = []
    for key in keys:
        bits = len(find_variable(od, key))
        for b in bins:
            if sum(x for _, x in b) + bits <= 64:
                b.append((key, bits))
                break
        else:
            bins.append([(key, bits)])
    if len(bins) > PDO_COUNT:
        raise ValueError("%d objects do not fit into %d %sPDOs" % (len(keys), PDO_COUNT, "R" if rx else "T"))
    bases = _RX_COB_BASE if rx else _TX_COB_BASE
    out = []
    for n in range(PDO_COUNT):
        entries = tuple(bins[n]) if n < len(bins) else ()
        out.append(MapPlan(n + 1, bases[n] + node_id, bool(entries), trans_type,
                           None if rx else event_timer, not rx, entries))
    return out


def _pack(od: ObjectDictionary, keys: Sequence[ObjectKey]) -> List[List[Tuple[ObjectKey, int]]]:
    """Keys into as few 64-bit PDOs as fit: first fit in the given order
    (keeps the statusword with the position, the controlword with the
    cyclic target), first fit by decreasing size when that needs fewer."""
    sized = [(k, len(find_variable(od, k))) for k in keys]

    def first_fit(items: Sequence[Tuple[ObjectKey, int]]) -> List[List[Tuple[ObjectKey, int]]]:
        bins: List[List[Tuple[ObjectKey, int]]] = []
        for item in items:
            for b in bins:
                if sum(x for _, x in b) + item[1] <= PDO_BITS:
                    b.append(item)
                    break
            else:
                bins.append([item])
        return bins

    ordered = first_fit(sized)
    decreasing = first_fit(sorted(sized, key=lambda kb: -kb[1]))
    return decreasing if len(decreasing) < len(ordered) else ordered


def compact_maps(od: ObjectDictionary, node_id: int, modes: Sequence[int],
                 tx_objects: Sequence[ObjectKey], readings_every: int = 1) -> Tuple[List[MapPlan], List[MapPlan]]:
    """The compact layout: RxPDOs carry the controlword and the targets of
    ``modes`` (cyclic modes' targets first, so the one sent every SYNC
    shares a frame with the controlword); TxPDOs the statusword, the
    position actual value and ``tx_objects`` (what the unit conversions
    read). Modes of operation (0x6060/0x6061) are left to SDO: they change
    only at a mode switch. Unused PDOs are disabled.

    With ``readings_every`` N > 1 the statusword and the position have
    TxPDO1 to themselves, sent every SYNC, and the other readings follow
    in TxPDOs of transmission type N (every N-th SYNC, CiA 301): two
    frames per axis per SYNC plus 1/N per readings PDO."""
    rx_keys: List[ObjectKey] = [CONTROLWORD]
    for cyclic_first in (True, False):
        for mode in modes:
            if (mode in CYCLIC_MODES) == cyclic_first:
                for k in MODE_TARGETS[mode]:
                    if k not in rx_keys:
                        rx_keys.append(k)
    tx_keys: List[ObjectKey] = [STATUSWORD, POSITION_ACTUAL]
    for k in tx_objects:
        if k not in tx_keys:
            tx_keys.append(k)
    if not 1 <= readings_every <= 240:
        raise ValueError("readings_every %r is no synchronous transmission type (1..240)" % (readings_every,))
    out = []
    for keys, rx in ((rx_keys, True), (tx_keys, False)):
        if rx or readings_every == 1:
            bins = _pack(od, keys)
        else:  # the statusword and position alone in the first, the rest packed behind
            bins = _pack(od, keys[:2]) + (_pack(od, keys[2:]) if len(keys) > 2 else [])
        if len(bins) > PDO_COUNT:
            raise ValueError("%d objects do not fit into %d %sPDOs" % (len(keys), PDO_COUNT, "R" if rx else "T"))
        bases = _RX_COB_BASE if rx else _TX_COB_BASE
        out.append([MapPlan(n + 1, bases[n] + node_id, n < len(bins),
                            1 if rx or n == 0 else readings_every, None, not rx,
                            tuple(bins[n]) if n < len(bins) else ()) for n in range(PDO_COUNT)])
    return out[0], out[1]


def _timing(maps: List[MapPlan], sync: SyncConfig, rx: bool) -> List[MapPlan]:
    """With SYNC, PDOs are synchronous (type 1); without it, event driven
    (255) and TPDOs sent every update period by the drive's event timer."""
    out = []
    for m in maps:
        if sync.interval_ms > 0:
            trans, timer = (1, None) if not 1 <= m.trans_type <= 240 else (m.trans_type, None)
        else:  # a type-N TPDO every N cycles
            every = m.trans_type if 1 <= m.trans_type <= 240 else 1
            trans, timer = 255, None if rx else max(1, int(round(every * sync.update_ms)))
        out.append(MapPlan(m.number, m.cob_id, m.enabled, trans, timer, m.rtr_allowed, m.entries))
    return out


HEARTBEAT_CONSUMER_1 = ObjectKey(0x1016, 1)
# Heartbeats of the master the drive may miss before it reacts (0x6007):
# one late frame is no master loss, three missing frames are.
MISSED_HEARTBEATS = 3


def heartbeat_consumer(master: Optional[HeartbeatConfig]) -> Optional[Tuple[int, int]]:
    """(master node-ID, timeout ms) the drives watch, from the bus layer's
    ``heartbeat``; None when the master sends no heartbeat a drive could
    watch (none configured, or not on a heartbeat COB-ID 0x701..0x77F)."""
    if master is None or master.extended or not 0x701 <= master.can_id <= 0x77F or master.rate <= 0:
        return None
    period_ms = 1000.0 / master.rate
    return master.can_id - 0x700, max(1, min(0xFFFF, int(round(MISSED_HEARTBEATS * period_ms))))


def plan_node(cfg: NodeConfig, od: ObjectDictionary, sync: SyncConfig, source: str,
              master_heartbeat: Optional[HeartbeatConfig] = None) -> NodePlan:
    """Everything init will write to this node; ConfigError on any problem.

    With the master's heartbeat given, the drive's heartbeat consumer
    0x1016sub1 is set to watch it (a drive whose master dies stops by its
    own abort connection reaction, 0x6007); ``dcf_overlay`` "1016sub1" wins."""
    prefix = "nodes/%s/" % cfg.key

    def fail(key: str, problem: str) -> ConfigError:
        return ConfigError(source, prefix + key, problem)

    for key in RX_REQUIRED + TX_REQUIRED:
        try:
            find_variable(od, key)
        except ObjectStringError as e:
            raise fail("eds_file", "%s: a CiA 402 drive needs object %s (%s)" % (cfg.eds_file, key, e)) from None

    writes: Dict[ObjectKey, SdoWrite] = {}
    for var in _variables(od):
        if var.value is None or _skipped(var.index) or not is_writable(var):
            continue
        key = ObjectKey(var.index, var.subindex)
        if key in DRIVER_OWNED or var.data_type in (dt.DOMAIN,):
            continue
        try:
            data = var.encode_raw(var.value)
        except (ValueError, TypeError, Exception) as e:  # canopen raises struct/Object errors
            raise fail("eds_file", "%s: ParameterValue of %s cannot be encoded: %s" % (cfg.eds_file, key, e)) from None
        writes[key] = SdoWrite(key, data, "%s = %s (DCF)" % (key, var.value))
    consumer = heartbeat_consumer(master_heartbeat)
    if consumer is not None and HEARTBEAT_CONSUMER_1.index in od:
        var = find_variable(od, HEARTBEAT_CONSUMER_1)
        value = consumer[0] << 16 | consumer[1]
        writes[HEARTBEAT_CONSUMER_1] = SdoWrite(HEARTBEAT_CONSUMER_1, var.encode_raw(value), "%s = 0x%08X (watch the "
                                                "master's heartbeat, node %d, %d ms)" % (HEARTBEAT_CONSUMER_1, value,
                                                                                          consumer[0], consumer[1]))
    for key, text, written in cfg.dcf_overlay:
        try:
            var = find_variable(od, key)
            if not is_writable(var):
                raise ObjectValueError("object %s is read-only" % key)
            value = _overlay_value(var, text, cfg.node_id)
            data = var.encode_raw(value)
        except (ObjectStringError, ObjectValueError) as e:
            raise fail("dcf_overlay/" + written, str(e)) from None
        if key in DRIVER_OWNED:
            raise fail("dcf_overlay/" + written, "object %s is commanded by the driver every cycle" % key)
        writes.pop(key, None)
        writes[key] = SdoWrite(key, data, "%s = %s (dcf_overlay)" % (key, text))

    tx_needed: List[ObjectKey] = list(TX_REQUIRED)
    conversions: List[ObjectKey] = []  # what the unit conversions read
    for name in ("pos_from_device", "vel_from_device", "eff_from_device",
                 "pos_to_device", "vel_to_device", "eff_to_device"):
        for key in getattr(cfg, name).objects:
            try:
                var = find_variable(od, key)
            except ObjectStringError as e:
                raise fail(name, str(e)) from None
            if not var.pdo_mappable and name.endswith("from_device"):
                raise fail(name, "object %s cannot be mapped to a TPDO" % key)
            if var.pdo_mappable and key not in tx_needed:
                tx_needed.append(key)
            if var.pdo_mappable and key not in conversions:
                conversions.append(key)
    for pub in cfg.publish:
        try:
            find_variable(od, pub.key)
        except ObjectStringError as e:
            raise fail("publish", "%s: %s" % (pub.spec, e)) from None

    if cfg.pdo_layout == "compact":
        unknown = [m for m in cfg.modes if m not in MODE_TARGETS]
        if unknown or not cfg.modes:
            raise fail("modes", "pdo_layout compact needs the node's modes (supported: %s), got %s"
                       % (", ".join(str(m) for m in sorted(MODE_TARGETS)), list(cfg.modes)))
        try:
            rx, tx = compact_maps(od, cfg.node_id, cfg.modes, conversions, cfg.readings_every)
        except ValueError as e:
            raise fail("pdo_layout", str(e)) from None
        return NodePlan(tuple(writes.values()), tuple(_timing(rx, sync, True)), tuple(_timing(tx, sync, False)),
                        "compact", tuple(cfg.modes))

    rx_dcf = dcf_maps(od, rx=True)
    tx_dcf = dcf_maps(od, rx=False)
    rx_have = {k for m in rx_dcf if m.enabled for k, _ in m.entries}
    tx_have = {k for m in tx_dcf if m.enabled for k, _ in m.entries}
    if set(RX_REQUIRED) <= rx_have and set(tx_needed) <= tx_have:
        rx, tx, origin = rx_dcf, tx_dcf, "dcf"
    else:
        try:
            rx = _own_maps(od, cfg.node_id, RX_REQUIRED, True, 1, None)
            tx = _own_maps(od, cfg.node_id, tx_needed, False, 1, None)
        except ValueError as e:
            raise fail("eds_file", str(e)) from None
        origin = "driver"
    return NodePlan(tuple(writes.values()), tuple(_timing(rx, sync, True)), tuple(_timing(tx, sync, False)), origin)

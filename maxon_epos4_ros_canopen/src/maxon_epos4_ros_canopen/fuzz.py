"""Random and malformed CAN frames for robustness tests (ROS-free).

Public API
----------
``FrameFuzzer(seed, node_ids=(), cob_ids=(), weights=None, exclude=())``
    ``frames(count)`` yields ``count`` python-can messages, the same ones for
    the same arguments (one ``random.Random(seed)``; nothing depends on time).
    Each frame is drawn from a *kind* (``KINDS``) with the given weights:
    random 11-bit and 29-bit ids with 0-8 bytes, remote frames, forged TPDOs
    and RPDOs on the CANopen COB-IDs of ``node_ids``, EMCYs, boot-ups,
    heartbeats with any state byte, SDO responses nobody asked for, SDO
    requests (weight 0 unless asked for: they write objects), NMT commands
    (valid, unknown, wrong length), SYNCs of any length, and frames on the
    extra ``cob_ids`` of the interface under test.
``Exclusion.parse("000#0200")``
    A frame the generator must never emit: ``ID[-ID][#HEXPREFIX]`` (ids in
    hex, standard ids; ``x`` after the id for extended ids: ``1ABx``) matches
    the ids in the range whose data starts with the prefix. ``NMT_STOP_ALL``
    ("000#0200") is the usual one: an NMT stop to all nodes ends every test.
``parse_weights("nmt=0,tpdo=5")``
    Weights for ``FrameFuzzer``; unknown kinds or negative weights raise
    ``ValueError``.
``send(bus, frames, rate=None, on_full=...) -> FuzzReport``
    Sends the frames, at most ``rate`` frames/s when given; a full transmit
    queue is retried after a short pause (it is the bus being busy, not a
    defect); counts sent and dropped frames and the time taken.
"""
from __future__ import annotations

import random
import re
import time
from dataclasses import dataclass
from typing import Dict, Iterable, Iterator, List, Optional, Sequence, Tuple

import can

KINDS: Tuple[str, ...] = (
    "random", "extended", "remote", "tpdo", "rpdo", "emcy", "bootup", "heartbeat",
    "sdo_response", "sdo_request", "nmt", "sync", "target",
)
DEFAULT_WEIGHTS: Dict[str, float] = {
    "random": 20, "extended": 5, "remote": 4, "tpdo": 12, "rpdo": 12, "emcy": 6,
    "bootup": 3, "heartbeat": 8, "sdo_response": 10, "sdo_request": 0, "nmt": 4,
    "sync": 4, "target": 12,
}
_NMT_COMMANDS = (0x01, 0x02, 0x80, 0x81, 0x82)
_NMT_STATES = (0x00, 0x04, 0x05, 0x7F)
# SDO server command specifiers a response may carry, plus anything else.
_SDO_RESPONSE_HEADERS = (0x43, 0x47, 0x4B, 0x4F, 0x42, 0x41, 0x60, 0x20, 0x30, 0x00, 0x01,
                         0x0B, 0x80, 0xA0, 0xC1, 0xA2)
_TPDO_BASES = (0x180, 0x280, 0x380, 0x480)
_RPDO_BASES = (0x200, 0x300, 0x400, 0x500)


@dataclass(frozen=True)
class Exclusion:
    """Frames on ids ``first..last`` whose data starts with ``prefix``."""

    first: int
    last: int
    prefix: bytes = b""
    extended: bool = False

    _PATTERN = re.compile(r"^([0-9A-Fa-f]{1,8})(?:-([0-9A-Fa-f]{1,8}))?(x?)(?:#([0-9A-Fa-f]*))?$")

    @classmethod
    def parse(cls, text: str) -> "Exclusion":
        match = cls._PATTERN.match(text.strip().replace("0x", "").replace(" ", ""))
        if not match or len(match.group(4) or "") % 2:
            raise ValueError("exclusion %r: expected ID[-ID][x][#HEXPREFIX], e.g. 000#0200" % text)
        first = int(match.group(1), 16)
        last = int(match.group(2), 16) if match.group(2) else first
        extended = bool(match.group(3))
        limit = 0x1FFFFFFF if extended else 0x7FF
        if not first <= last <= limit:
            raise ValueError("exclusion %r: ids must be ascending and at most 0x%X" % (text, limit))
        return cls(first, last, bytes.fromhex(match.group(4) or ""), extended)

    def matches(self, msg: can.Message) -> bool:
        return (msg.is_extended_id == self.extended and self.first <= msg.arbitration_id <= self.last
                and not msg.is_remote_frame and bytes(msg.data[:len(self.prefix)]) == self.prefix
                and len(msg.data) >= len(self.prefix))


NMT_STOP_ALL = Exclusion.parse("000#0200")


def parse_weights(text: str, base: Optional[Dict[str, float]] = None) -> Dict[str, float]:
    """``"kind=weight,..."`` over ``base`` (default: DEFAULT_WEIGHTS)."""
    weights = dict(DEFAULT_WEIGHTS if base is None else base)
    for item in filter(None, (part.strip() for part in text.split(","))):
        kind, _, value = item.partition("=")
        if kind not in KINDS:
            raise ValueError("unknown frame kind %r (kinds: %s)" % (kind, ", ".join(KINDS)))
        try:
            weight = float(value)
        except ValueError:
            raise ValueError("weight of %s: %r is not a number" % (kind, value)) from None
        if weight < 0:
            raise ValueError("weight of %s must be >= 0" % kind)
        weights[kind] = weight
    return weights


class FrameFuzzer:
    """Deterministic generator of random and malformed frames."""

    def __init__(self, seed: int, node_ids: Sequence[int] = (), cob_ids: Sequence[int] = (),
                 weights: Optional[Dict[str, float]] = None, exclude: Iterable[Exclusion] = ()):
        for node_id in node_ids:
            if not 1 <= node_id <= 127:
                raise ValueError("node id %r outside 1..127" % (node_id,))
        for cob in cob_ids:
            if not 0 <= cob <= 0x7FF:
                raise ValueError("COB-ID 0x%X is not an 11-bit id" % cob)
        self.seed = seed
        self.node_ids = list(node_ids)
        self.cob_ids = list(cob_ids)
        self.weights = dict(DEFAULT_WEIGHTS if weights is None else weights)
        unknown = set(self.weights) - set(KINDS)
        if unknown:
            raise ValueError("unknown frame kinds %s" % sorted(unknown))
        if not self.cob_ids:
            self.weights["target"] = 0.0
        self.exclude = list(exclude)
        self._kinds = [k for k in KINDS if self.weights.get(k, 0) > 0]
        if not self._kinds:
            raise ValueError("every frame kind has weight 0")
        self._cumulative = []
        total = 0.0
        for kind in self._kinds:
            total += self.weights[kind]
            self._cumulative.append(total)
        self.counts: Dict[str, int] = {k: 0 for k in KINDS}

    def frames(self, count: int) -> Iterator[can.Message]:
        """``count`` frames (excluded ones are replaced, not skipped)."""
        if count < 0:
            raise ValueError("count must be >= 0")
        rng = random.Random(self.seed)
        emitted = attempts = 0
        while emitted < count:
            attempts += 1
            if attempts > 100 * count + 1000:
                raise ValueError("the exclusions leave no frame to send")
            kind = rng.choices(self._kinds, cum_weights=self._cumulative)[0]
            msg = getattr(self, "_" + kind)(rng)
            if any(rule.matches(msg) for rule in self.exclude):
                continue
            self.counts[kind] += 1
            emitted += 1
            yield msg

    # ------------------------------------------------------------ kinds
    def _node(self, rng: random.Random) -> int:
        return rng.choice(self.node_ids) if self.node_ids else rng.randint(1, 127)

    @staticmethod
    def _data(rng: random.Random, length: Optional[int] = None) -> bytes:
        n = rng.randint(0, 8) if length is None else length
        return bytes(rng.getrandbits(8) for _ in range(n))

    @staticmethod
    def _length(rng: random.Random, usual: int) -> int:
        """Mostly the length the protocol uses, sometimes any other."""
        return usual if rng.random() < 0.7 else rng.randint(0, 8)

    @staticmethod
    def _std(cob: int, data: bytes) -> can.Message:
        return can.Message(arbitration_id=cob, data=data, is_extended_id=False)

    def _random(self, rng: random.Random) -> can.Message:
        return self._std(rng.getrandbits(11), self._data(rng))

    def _extended(self, rng: random.Random) -> can.Message:
        return can.Message(arbitration_id=rng.getrandbits(29), data=self._data(rng), is_extended_id=True)

    def _remote(self, rng: random.Random) -> can.Message:
        pool = [0x700 + self._node(rng), rng.choice(_TPDO_BASES) + self._node(rng), rng.getrandbits(11)]
        if self.cob_ids:
            pool.append(rng.choice(self.cob_ids))
        return can.Message(arbitration_id=rng.choice(pool), is_remote_frame=True,
                           dlc=rng.randint(0, 8), is_extended_id=False)

    def _tpdo(self, rng: random.Random) -> can.Message:
        return self._std(rng.choice(_TPDO_BASES) + self._node(rng), self._data(rng, self._length(rng, 8)))

    def _rpdo(self, rng: random.Random) -> can.Message:
        return self._std(rng.choice(_RPDO_BASES) + self._node(rng), self._data(rng, self._length(rng, 6)))

    def _emcy(self, rng: random.Random) -> can.Message:
        return self._std(0x080 + self._node(rng), self._data(rng, self._length(rng, 8)))

    def _bootup(self, rng: random.Random) -> can.Message:
        return self._std(0x700 + self._node(rng), b"\x00")

    def _heartbeat(self, rng: random.Random) -> can.Message:
        state = rng.choice(_NMT_STATES) if rng.random() < 0.5 else rng.getrandbits(8)
        data = bytes([state]) if rng.random() < 0.85 else self._data(rng)
        return self._std(0x700 + self._node(rng), data)

    def _sdo_response(self, rng: random.Random) -> can.Message:
        data = bytes([rng.choice(_SDO_RESPONSE_HEADERS)]) + self._data(rng, 7)
        return self._std(0x580 + self._node(rng), data[:self._length(rng, 8)])

    def _sdo_request(self, rng: random.Random) -> can.Message:
        return self._std(0x600 + self._node(rng), self._data(rng, self._length(rng, 8)))

    def _nmt(self, rng: random.Random) -> can.Message:
        command = rng.choice(_NMT_COMMANDS) if rng.random() < 0.7 else rng.getrandbits(8)
        target = rng.choice([0, self._node(rng), rng.getrandbits(8)])
        data = bytes([command, target])
        if rng.random() < 0.2:
            data = self._data(rng)
        return self._std(0x000, data)

    def _sync(self, rng: random.Random) -> can.Message:
        return self._std(0x080, self._data(rng, 0 if rng.random() < 0.5 else None))

    def _target(self, rng: random.Random) -> can.Message:
        return self._std(rng.choice(self.cob_ids), self._data(rng))


@dataclass
class FuzzReport:
    """What ``send`` did."""

    sent: int = 0
    dropped: int = 0  # transmit queue full even after retries
    seconds: float = 0.0

    @property
    def rate(self) -> float:
        return self.sent / self.seconds if self.seconds > 0 else 0.0

    def summary(self) -> str:
        return "sent %d frames in %.1f s (%.0f frames/s), %d dropped (transmit queue full)" % (
            self.sent, self.seconds, self.rate, self.dropped)


def send(bus: can.BusABC, frames: Iterable[can.Message], rate: Optional[float] = None,
         retries: int = 50, pause: float = 0.002) -> FuzzReport:
    """Send ``frames`` on ``bus``, at most ``rate`` per second when given."""
    if rate is not None and rate <= 0:
        raise ValueError("rate must be > 0 frames/s")
    report = FuzzReport()
    start = time.monotonic()
    interval = 1.0 / rate if rate else 0.0
    for n, msg in enumerate(frames):
        if interval:
            due = start + n * interval
            delay = due - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        for _ in range(retries + 1):
            try:
                bus.send(msg, timeout=0.1)
                report.sent += 1
                break
            except can.CanError:  # ENOBUFS: the readers are behind; let them catch up
                time.sleep(pause)
        else:
            report.dropped += 1
    report.seconds = time.monotonic() - start
    return report


def describe(msg: can.Message) -> str:
    """candump-like text of a frame (for --dry-run and failure messages)."""
    width = 8 if msg.is_extended_id else 3
    if msg.is_remote_frame:
        return "%0*X#R%d" % (width, msg.arbitration_id, msg.dlc)
    return "%0*X#%s" % (width, msg.arbitration_id, bytes(msg.data).hex().upper())


__all__: List[str] = ["KINDS", "DEFAULT_WEIGHTS", "Exclusion", "NMT_STOP_ALL", "parse_weights",
                      "FrameFuzzer", "FuzzReport", "send", "describe"]

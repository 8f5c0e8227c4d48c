"""Object access: every SDO transfer the driver makes (one node at a time,
under that node's lock, tried again when disturbed) and the user's
get_object/set_object.

``ObjectAccess`` owns the per-node SDO locks and the object caches (each
cache read and written under its node's lock or by the service holding
the service lock); the SDO clients are the link's."""
from __future__ import annotations

import logging
import random
import struct
import threading
from typing import Any, Callable, Dict, Optional, Tuple

from canopen.sdo import SdoClient
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from ..objects import (ObjectKey, ObjectStringError, ObjectValueError, decode_value, encode_value,
                       find_variable, is_readable, is_writable, parse_object_key)
from ..result import Result, fail, ok
from .cycle import ControlCycle
from .deadline import Deadline
from .inbox import SetHeartbeat, SetOutput
from .link import Link
from .modes import POSITION_ACTUAL
from .nodes import NodeTable, StateTimeout, Timeouts
from .plan import DRIVER_OWNED, PRODUCER_HEARTBEAT
from .sdo import no_answer

log = logging.getLogger("maxon_epos4_ros_canopen.driver")

_SDO_ATTEMPTS = 3  # tries of a transfer whose answer did not come
_SDO_FOREIGN_ANSWERS = 7  # more tries when the answer was another client's

# Objects set_object refuses, and why: the driver configures or sends them
# itself, or writing them would act on the drive's memory.
_REFUSED_RANGES = (
    (0x1400, 0x1BFF, "a PDO communication or mapping parameter: the driver configures its PDOs itself"),
    (0x1010, 0x1011, "store/restore parameters: the driver does not write the drive's memory"),
    (0x1005, 0x1005, "the SYNC COB-ID: the driver's SYNC depends on it"),
    (0x1200, 0x12FF, "an SDO server parameter: the driver talks over it"),
)


class ObjectAccess:
    """SDO transfers and the object services (see the module's docstring)."""

    def __init__(self, nodes: NodeTable, link: Link, cycle: ControlCycle, timeouts: Timeouts) -> None:
        self._nodes = nodes
        self._link = link
        self._clock = link.clock
        self._random = random.Random()  # the pauses between tries on a busy channel
        self._cycle = cycle
        self._timeouts = timeouts
        self._sdo_locks = {name: threading.Lock() for name in nodes}
        self.cache: Dict[str, Dict[ObjectKey, Any]] = {name: {} for name in nodes}  # under the SDO lock

    # =============================================================== SDO
    def upload(self, name: str, key: ObjectKey, until: Optional[Deadline] = None) -> Any:
        var = find_variable(self._nodes[name].od, key)
        return var.decode_raw(self.sdo_transfer(name, lambda sdo: sdo.upload(key.index, key.subindex), until))

    def download(self, name: str, index: int, sub: int, data: bytes, until: Optional[Deadline] = None) -> None:
        self.sdo_transfer(name, lambda sdo: sdo.download(index, sub, data), until)

    def sdo_transfer(self, name: str, transfer: Callable[[SdoClient], Any], until: Optional[Deadline] = None) -> Any:
        """One SDO transfer, tried again when its answer was not the one asked
        for (another client on the same SDO channel, a user's tool or a test
        probe, or a stray frame can take an answer) or did not come in time
        (a loaded host). Every transfer the driver makes may be repeated:
        reads, and writes of a value. An abort is final. Each attempt waits
        longer than the one before (1, 2, 3 × sdo_timeout): a drive whose
        answer came late once, on a host that stalled, gets the time, and
        the late answer to the same request still counts.
        An answer for another object means another client is busy on the
        same channel: the next try comes after a short random pause, so two
        clients polling the drive do not meet again at once.
        ``until``: a deadline (shutdown's) the transfer ends by, waiting for
        the node's SDO channel included: no attempt starts after it, none
        waits past it, and then DeadlinePassed (an SdoCommunicationError)
        says so."""
        lock = self._sdo_locks[name]
        if until is None:
            lock.acquire()
        elif not self._clock.acquire(lock, until.left()):
            raise until.passed_error("the SDO channel of %s stayed busy with another transfer" % name)
        try:
            client = self._link.sdo[name]
            tally = client.tally()
            late = 0
            last: Optional[BaseException] = None
            try:
                for attempt in range(_SDO_ATTEMPTS + _SDO_FOREIGN_ANSWERS):
                    wait = self._timeouts.sdo * (late + 1)
                    if until is not None:
                        if until.passed:
                            raise until.passed_error("not sent" if last is None else "not tried again after: %s" % last)
                        wait = min(wait, until.left())
                        client.give_up_by = until.at
                    client.RESPONSE_TIMEOUT = wait
                    try:
                        return transfer(client)
                    except (SdoCommunicationError, struct.error) as e:
                        # apart from a missing answer (sdo.no_answer), every
                        # communication error is an answer that was not this request's (another
                        # client's, "Node returned a value for ... instead",
                        # "Unexpected response"), whatever its wording, and
                        # so is an answer shorter than 8 bytes, which canopen
                        # fails to unpack (a forged or corrupt frame)
                        foreign = not no_answer(e)
                        late += 0 if foreign else 1
                        last = e
                        if until is not None and until.passed:
                            # the deadline cut this attempt's wait short: no answer in time
                            raise until.passed_error("no answer in time (%s; %s)" % (e, client.since(tally))) from e
                        if late == _SDO_ATTEMPTS or attempt + 1 == _SDO_ATTEMPTS + _SDO_FOREIGN_ANSWERS:
                            if isinstance(e, struct.error):
                                raise SdoCommunicationError("malformed SDO answer (%s)" % e) from e
                            if foreign:
                                raise
                            # what came, and why it was no answer, tells the
                            # drive's silence from this host's trouble
                            raise SdoCommunicationError("%s; %s" % (e, client.since(tally))) from e
                        log.warning("%s: SDO transfer disturbed (%s%s): trying again",
                                    name, e, "" if foreign else "; " + client.since(tally))
                        if foreign:
                            pause = self._random.uniform(0.005, 0.05)
                            self._clock.sleep(pause if until is None else min(pause, until.left()))
            finally:
                client.RESPONSE_TIMEOUT = self._timeouts.sdo
                client.give_up_by = None
        finally:
            lock.release()

    def write_u32(self, name: str, index: int, sub: int, value: int) -> None:
        self.download(name, index, sub, value.to_bytes(4, "little"))

    def write_u8(self, name: str, index: int, sub: int, value: int) -> None:
        self.download(name, index, sub, bytes([value]))

    def position(self, name: str) -> int:
        """0x6064 read over SDO: a position the driver can vouch for (an
        answer to its own request), unlike a TPDO anyone could have sent."""
        return int(self.upload(name, POSITION_ACTUAL))

    def known(self, name: str, key: ObjectKey) -> Any:
        """``key``'s value in the drive: what this configuration has just
        written to it (a drive holds a value it accepted: reading it back
        would be one more transfer on a bus all drives share), else read."""
        data = self._nodes[name].plan.written.get(key)
        if data is None:
            return self.upload(name, key)
        return find_variable(self._nodes[name].od, key).decode_raw(data)

    def await_value(self, name: str, key: ObjectKey, done: Callable[[int], bool], shows: str,
                    until: Optional[Deadline] = None) -> int:
        """Read ``key`` over SDO until ``done(value)``, for at most the state
        timeout (and until ``until``): the drive's own answers, no cycle
        involved. An EPOS4 changes state within a millisecond, so the first
        reads come at once and later ones less often."""
        deadline = self._clock.now() + self._timeouts.state
        pause = 0.0005
        while True:
            value = int(self.upload(name, key, until))
            if done(value):
                return value
            if self._clock.now() > deadline or self._cycle.abort.is_set():
                raise StateTimeout(shows % value)
            self._clock.sleep(pause if until is None else min(pause, until.left()))
            pause = min(2 * pause, 0.02)

    # ========================================================== objects
    def _object(self, node_name: Any, obj: Any) -> Tuple[Optional[str], Any, Optional[Result]]:
        n = self._nodes.name(node_name)
        if n is None:
            return None, None, self._nodes.unknown(node_name)
        try:
            key = parse_object_key(obj)
            var = find_variable(self._nodes[n].od, key)
        except ObjectStringError as e:
            return None, None, fail(str(e))
        if n not in self._link.sdo:
            return None, None, fail("driver not initialized: call init")
        return n, var, None

    def get_object(self, node_name: str, obj: str, cached: bool = False) -> Result:
        """ros_canopen's get_object; always answers."""
        try:
            return self._get_object(node_name, obj, cached)
        except Exception as e:  # a bus going away mid-request, anything
            return fail("reading %s from %s: %s" % (obj, node_name, e))

    def _get_object(self, node_name: str, obj: str, cached: bool) -> Result:
        n, var, err = self._object(node_name, obj)
        if err is not None:
            return err
        key = ObjectKey(var.index, var.subindex)
        if not is_readable(var):
            return fail("object %s is write-only" % key)
        readings = self._cycle.snapshot.axes[n].readings
        if cached and key in readings:
            return ok(value=decode_value(var, readings[key]))
        cache = self.cache[n]
        if cached and key in cache:
            return ok(value=decode_value(var, cache[key]))
        try:
            value = self.upload(n, key)
        except SdoAbortedError as e:
            return fail("reading %s from %s: %s" % (key, n, e))
        except SdoCommunicationError as e:
            return fail("reading %s from %s: no answer (%s)" % (key, n, e))
        cache[key] = value
        return ok(value=decode_value(var, value))

    def set_object(self, node_name: str, obj: str, value: str, cached: bool = False) -> Result:
        """ros_canopen's set_object; always answers. Objects the driver owns
        are refused with the reason."""
        try:
            return self._set_object(node_name, obj, value, cached)
        except Exception as e:
            return fail("writing %s to %s: %s" % (obj, node_name, e))

    def _set_object(self, node_name: str, obj: str, value: str, cached: bool) -> Result:
        n, var, err = self._object(node_name, obj)
        if err is not None:
            return err
        key = ObjectKey(var.index, var.subindex)
        if key in DRIVER_OWNED:
            return fail("object %s is written by the driver every cycle: use the controllers "
                        "and services instead" % key)
        for lo, hi, why in _REFUSED_RANGES:
            if lo <= key.index <= hi:
                return fail("object %s is refused: %s" % (key, why))
        if not is_writable(var):
            return fail("object %s is read-only" % key)
        try:
            py_value = encode_value(var, value)
            data = var.encode_raw(py_value)
        except ObjectValueError as e:
            return fail(str(e))
        cache = self.cache[n]
        if cached and cache.get(key) == py_value:
            return ok("unchanged")
        try:
            self.download(n, key.index, key.subindex, data)
        except SdoAbortedError as e:
            return fail("writing %s to %s: %s" % (key, n, e))
        except SdoCommunicationError as e:
            return fail("writing %s to %s: no answer (%s)" % (key, n, e))
        cache[key] = py_value
        cycle = self._cycle
        if key in self._nodes[n].plan.rx_keys():
            # keep the RPDO from writing the old value back
            cycle.wait(lambda s: True, 1.0, cycle.post(SetOutput(n, key, int(py_value))))
        if key == PRODUCER_HEARTBEAT:
            cycle.post(SetHeartbeat(n, int(py_value)))
        return ok()

    # ==================================================== ROS layer/diag
    def published_types(self) -> Dict[str, int]:
        """topic -> CANopen data type of the ROS layer's published objects."""
        out = {}
        for node in self._nodes.values():
            for pub in node.cfg.publish:
                out[pub.topic] = find_variable(node.od, pub.key).data_type
        return out

    def read_published(self) -> Dict[str, Any]:
        """topic -> value of every ``publish`` object: from its TPDO when
        mapped, else the cache, read by SDO when forced (``!``) or never read.
        Objects that cannot be read are left out (and logged)."""
        out: Dict[str, Any] = {}
        if not self._link.sdo:
            return out
        snap = self._cycle.snapshot.axes
        for name, node in self._nodes.items():
            readings = snap[name].readings
            cache = self.cache[name]
            for pub in node.cfg.publish:
                if pub.key in readings and not pub.force:
                    out[pub.topic] = readings[pub.key]
                    continue
                if pub.force or pub.key not in cache:
                    try:
                        cache[pub.key] = self.upload(name, pub.key)
                    except Exception as e:  # SDO abort, timeout, network closed meanwhile
                        log.warning("publish %s: %s", pub.topic, e)
                        continue
                out[pub.topic] = cache[pub.key]
        return out

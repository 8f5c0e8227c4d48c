"""Init against the virtual EPOS4: nodes are configured and enabled over SDO
before the cycle starts, so the cycle's first RxPDOs already hold Operation
Enabled; a node that stops answering is named with the step, and the
others end disabled. What the tests look at: frames on the bus and the
simulated drives' object dictionaries."""
import math

import pytest

from maxon_epos4_ros_canopen.cia402 import State, state_from_statusword
from maxon_epos4_ros_canopen.driver.modes import CONTROLWORD, MODES_OF_OPERATION, TARGET_POSITION
from maxon_epos4_ros_canopen.driver.plan import DRIVER_OWNED
from driver_support import DCF1, DCF2, J1, J2
from search_share import every_nth

SYNC = 0x080
SDO_UPLOAD_ANSWER = 0x40  # command specifier bits of an SDO upload answer (expedited or not)


@pytest.fixture
def rig(driver_rig):
    return driver_rig


def _field(plan, key):
    """(COB-ID, byte offset, bytes) of ``key`` in the first enabled RxPDO carrying it."""
    for m in plan.rx:
        if not m.enabled:
            continue
        offset = 0
        for k, bits in m.entries:
            if k == key:
                return m.cob_id, offset, bits // 8
            offset += bits // 8
    raise AssertionError("%s is in no RxPDO" % (key,))


def _values(rig, plan, key, signed=False):
    cob, offset, size = _field(plan, key)
    return [int.from_bytes(data[offset:offset + size], "little", signed=signed) for data in rig.sent(cob)]


def _statusword_answers(frames, node_id):
    """Statuswords a node answered to SDO reads of 0x6041, in bus order."""
    out = []
    for m in frames:
        data = bytes(m.data)
        if m.arbitration_id == 0x580 + node_id and len(data) == 8 and data[0] & 0xE0 == SDO_UPLOAD_ANSWER \
                and data[1:4] == b"\x41\x60\x00":
            out.append(int.from_bytes(data[4:6], "little"))
    return out


def _silent_after(rig, node_id, key, value=None):
    """Node ``node_id`` answers nothing from the moment it is written ``key``
    (``value``, when given) over SDO: it stops answering at that step."""
    node = rig.sim.nodes[node_id]
    after_write = node.store.after_write

    def hook(k, v):
        after_write(k, v)
        if k == key and (value is None or v == value):
            node.silent_until = math.inf
    node.store.after_write = hook


def _init_until_first_sync(rig, **start):
    """Start and init the driver; the frames on the bus up to its first SYNC."""
    d = rig.start(**start)
    r = d.init()
    assert r.success, r.message
    frames = list(rig._collect())
    first_sync = next((i for i, m in enumerate(frames) if m.arbitration_id == SYNC), len(frames))
    return d, frames[:first_sync]


def test_drives_are_enabled_over_sdo_before_the_first_sync(rig):
    d, before_sync = _init_until_first_sync(rig, nodes=((1, DCF1, J1), (2, DCF2, J2)))
    for nid in (1, 2):
        states = [state_from_statusword(sw) for sw in _statusword_answers(before_sync, nid)]
        # the drive itself said Operation Enabled, to a read over SDO, before any SYNC
        assert State.OPERATION_ENABLED in states, (nid, states)
        assert rig.state(nid) == State.OPERATION_ENABLED
    for name, nid in ((J1, 1), (J2, 2)):
        a = d.joints[name]
        assert a.ready and a.attached and not a.error
        assert a.held_state == State.OPERATION_ENABLED and a.target_state is None
        plan = a.plan
        assert rig.until(lambda: len(_values(rig, plan, CONTROLWORD)) >= 3)
        # no cycle walked the drive through the CiA 402 states: from the very
        # first RxPDO the controlword is enable operation
        assert set(_values(rig, plan, CONTROLWORD)) == {0x000F}
        # and the targets it holds are what the drive had: its position
        position = rig.read(0x6064, node=nid)
        assert rig.read(0x607A, node=nid) == position
        assert set(_values(rig, plan, TARGET_POSITION, signed=True)) == {position}


def test_a_mode_requested_before_init_is_set_before_enabling(rig):
    d = rig.start()
    assert d.switch_mode([J1], 8).success  # a controller started before init
    r = d.init()
    assert r.success, r.message
    assert rig.read(0x6061) == 8 and rig.state() == State.OPERATION_ENABLED
    a = d.joints[J1]
    assert a.active_mode == 8 and a.mode_display == 8
    plan = a.plan
    assert rig.until(lambda: len(_values(rig, plan, CONTROLWORD)) >= 3)
    assert set(_values(rig, plan, CONTROLWORD)) == {0x000F}
    assert d.set_command(J1, "position", 0.0).success


def test_a_drive_in_fault_at_init_gets_a_fault_reset(rig):
    d = rig.start()
    node = rig.sim.nodes[1]
    after_write = node.store.after_write

    def fault_while_configured(k, v):
        after_write(k, v)
        if k == (0x6065, 0):  # a DCF parameter: the drive faults in the middle of init
            node.raise_fault(0x8611, node.t)  # following error
    node.store.after_write = fault_while_configured
    r = d.init()
    assert r.success, r.message
    assert rig.state() == State.OPERATION_ENABLED
    sdo_writes = [bytes(m.data) for m in rig._collect() if m.arbitration_id == 0x601]
    assert any(w[1:4] == b"\x40\x60\x00" and w[4:6] == b"\x80\x00" for w in sdo_writes)  # fault reset
    assert set(_values(rig, d.joints[J1].plan, CONTROLWORD)) <= {0x000F}


@pytest.mark.parametrize("key,value,step", [
    ((0x1600, 0), None, "PDO mapping"),            # configuring
    ((0x6040, 0), 0x0007, "0x6040"),               # enabling: answers shutdown, not switch on
    ((0x6040, 0), 0x000F, "0x6040"),               # enabling: the last step
])
def test_a_node_that_stops_answering_is_named_with_the_step_and_the_others_end_disabled(rig, key, value, step):
    d = rig.start(nodes=((1, DCF1, J1), (2, DCF2, J2), (3, DCF1, "third")))
    d.sdo_timeout = 0.3  # bounds how long the silent node takes to fail
    _silent_after(rig, 2, key, value)
    r = d.init()
    assert not r.success
    assert "node 2" in r.message and step in r.message, r.message
    assert "node 1" not in r.message and "node 3" not in r.message, r.message
    assert not d.initialized
    for nid in (1, 3):
        assert rig.state(nid) == State.SWITCH_ON_DISABLED, nid


def test_init_of_127_drives_in_one_process(rig):
    # SEARCH_SHARE (search_share.py): every N-th node-ID, node-ID 127 always among them
    node_ids = every_nth(range(1, 128), phase=126)
    nodes = tuple((nid, DCF1, "j%d" % nid) for nid in node_ids)
    # 100 ms SYNC: 127 drives' PDOs fit the simulator's and the cycle's CPU
    d = rig.start(nodes=nodes, sync={"interval_ms": 100, "overflow": 0}, heartbeat=None)
    r = d.init()
    assert r.success, r.message
    for nid, _, name in nodes:
        a = d.joints[name]
        assert a.ready and a.held_state == State.OPERATION_ENABLED and not a.error, name
        assert rig.state(nid) == State.OPERATION_ENABLED, name
        # one DCF for all: each drive still got its own $NODEID COB-IDs
        assert rig.read(0x1800, 1, node=nid) & 0x7FF == 0x180 + nid, name
    plan = d.joints["j127"].plan
    assert rig.until(lambda: len(_values(rig, plan, CONTROLWORD)) >= 2)
    for nid, _, name in nodes:
        assert set(_values(rig, d.joints[name].plan, CONTROLWORD)) == {0x000F}, name


def _sdo_requests(frames, node_id):
    """(command, (index, sub)) of every SDO request to ``node_id``, in bus order:
    'read' for an upload initiate, 'write' for a download initiate."""
    out = []
    for m in frames:
        data = bytes(m.data)
        if m.arbitration_id != 0x600 + node_id or len(data) != 8:
            continue
        ccs = data[0] >> 5
        if ccs in (1, 2):  # download or upload initiate
            out.append(("write" if ccs == 1 else "read", (int.from_bytes(data[1:3], "little"), data[3])))
    return out


def test_init_reads_nothing_it_writes_and_each_state_once(rig):
    d, before_sync = _init_until_first_sync(rig, nodes=((1, DCF1, J1), (2, DCF2, J2)))
    for nid, name in ((1, J1), (2, J2)):
        requests = _sdo_requests(before_sync, nid)
        written = {key for command, key in requests if command == "write"}
        read = {key for command, key in requests if command == "read"}
        # a value init writes is known: reading it, before (a target about
        # to be set to hold the drive) or after (a DCF value), only costs a
        # transfer on a bus all drives share
        assert not read & written, (nid, ["0x%04X:%d" % k for k in sorted(read & written)])
        reads = [key for command, key in requests if command == "read"]
        # the position once (the hold target), the statusword only where the
        # walk through the CiA 402 states needs the drive's answer
        assert reads.count((0x6064, 0)) == 1, (nid, reads)
        controlwords = sum(1 for command, key in requests if command == "write" and key == (0x6040, 0))
        assert reads.count((0x6041, 0)) == controlwords + 1, (nid, reads)
        # and the first RxPDOs still carry what the drive holds: the DCF's
        # values of the objects they map, read by an independent client
        plan = d.joints[name].plan
        assert rig.until(lambda: all(rig.sent(m.cob_id) for m in plan.rx if m.enabled))
        for m in plan.rx:
            if not m.enabled:
                continue
            for key, _bits in m.entries:
                if key in DRIVER_OWNED:
                    continue  # commanded by the driver
                carried = _values(rig, plan, key, signed=key == MODES_OF_OPERATION)
                assert carried and set(carried) == {rig.read(key.index, key.subindex, node=nid)}, (nid, key, carried)


def test_a_pdo_the_plan_leaves_off_is_only_invalidated(rig):
    d, before_sync = _init_until_first_sync(rig, defaults={"pdo_layout": "compact", "modes": ["CSP"]})
    writes = [key for command, key in _sdo_requests(before_sync, 1) if command == "write"]
    plan = d.joints[J1].plan
    off = [(0x1400 + m.number - 1, 0x1600 + m.number - 1) for m in plan.rx if not m.enabled] + \
          [(0x1800 + m.number - 1, 0x1A00 + m.number - 1) for m in plan.tx if not m.enabled]
    assert off, "the compact CSP layout leaves PDOs off"
    for comm, mapping in off:
        # one write: the COB-ID with bit 31 (not valid); no mapping, no timing
        assert [k for k in writes if k[0] in (comm, mapping)] == [(comm, 1)], hex(comm)
        assert rig.read(comm, 1) & 0x80000000, hex(comm)
    for m in plan.tx:
        if m.enabled:
            assert not rig.read(0x1800 + m.number - 1, 1) & 0x80000000
    # what runs is exactly the planned TxPDOs
    rig.drain()
    assert rig.until(lambda: len(rig.sent(SYNC)) >= 3)
    got = {m.arbitration_id for m in rig._collect() if 0x180 <= m.arbitration_id < 0x500 and m.arbitration_id & 0x7F == 1}
    assert {m.cob_id for m in plan.tx if m.enabled} <= got
    assert not got & {m.cob_id for m in plan.tx if not m.enabled}

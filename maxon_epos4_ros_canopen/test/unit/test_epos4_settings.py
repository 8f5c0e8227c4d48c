"""epos4_settings in process: backup, diff and restore against the virtual
EPOS4 over python-can's ``virtual`` bus, with maxon's unedited DCF where the
machine has it (../shared/vendor_dcf), the project's own DCF otherwise.
What the tests look at: the tool's exit status and output, the SDO frames
on the bus, and the drive's values read by an independent canopen client.
The tool runs on the rig's stepped clock (its listen window, notifier and
SDO waits are virtual time); one test proves the listen window's real-time
notifier on the wall clock."""
import io
import os
import struct
import threading

import can
import pytest

from maxon_epos4_ros_canopen import settings
from maxon_epos4_ros_canopen.can_device import open_device
from maxon_epos4_ros_canopen.config import load_config
from maxon_epos4_ros_canopen.driver.plan import plan_node
from sim_support import NODE1, VENDOR_DIR, NodeConfig

import canopen

UNEDITED = os.path.join(VENDOR_DIR, "epos4_50_15_can_ec90flat_gp52c_mile800_node1_unedited_boolean.dcf")
NODE2_VENDOR = os.path.join(VENDOR_DIR, "epos4_50_15_can_ec90flat_gp52c_mile800_node2.dcf")
# maxon's DCF exported by EPOS Studio, unedited, where the machine has it (test
# data beside the repository); a fresh clone has only the project's own DCF.
DCF = UNEDITED if os.path.isfile(UNEDITED) else NODE1
MARKER = 0x67F  # an SDO request to node 127, which the bus does not have: nobody answers it
LISTEN = "0.05"  # s; the tests that need a master to be heard put its frames in the queue first

# The three settings the tests change by SDO, one in each area 0x1010 stores:
# communication (a PDO mapping entry), manufacturer, application.
MAPPING = (0x1A01, 1)      # TxPDO2's 1st entry: velocity demand value -> current actual value
HOMING_CURRENT = (0x30B2, 0)  # current threshold for homing mode
ACCELERATION = (0x6083, 0)  # profile acceleration
CHANGED = {MAPPING: 0x30D10220, HOMING_CURRENT: 750, ACCELERATION: 20000}


@pytest.fixture
def rig(sim_rig):
    """The simulated drive on a stepped clock, which the tool runs on too."""
    return sim_rig([NodeConfig(1, DCF)])


def run(rig, command, *args, opener=open_device, listen=LISTEN):
    out, err = io.StringIO(), io.StringIO()
    argv = [command, "virtual:" + rig.channel, "1"] + list(args) + ["--listen", listen, "--sdo-timeout", "2"]
    code = settings.main(argv, out, err, opener, clock=rig.clock)
    settle(rig)
    return code, out.getvalue(), err.getvalue()


def settle(rig):
    """Wait until the test's canopen client has received every frame the
    tool's transfers caused (it hears them all: a late SDO answer of the
    tool's must not be taken for its own): a marker frame sent now is
    received after them."""
    seen = []
    callback = lambda *_: seen.append(True)  # noqa: E731
    rig.net.subscribe(MARKER, callback)
    try:
        rig.send(MARKER, bytes(8))
        assert rig.wait(lambda: bool(seen)), "the test's client did not receive the marker frame"
    finally:
        rig.net.unsubscribe(MARKER, callback)


def backup(rig, path):
    code, out, err = run(rig, "backup", "--dcf", DCF)
    assert code == 0, err
    with open(str(path), "w") as fp:
        fp.write(out)
    return str(path)


def sdo_requests(frames, node_id=1):
    """(command, index, sub, value) of each SDO request to ``node_id`` among ``frames``."""
    out = []
    for f in frames:
        if f.arbitration_id == 0x600 + node_id and len(f.data) == 8:
            ccs, index, sub = f.data[0] >> 5, struct.unpack_from("<H", f.data, 1)[0], f.data[3]
            out.append(({1: "write", 2: "read"}.get(ccs, "segment"), index, sub,
                        struct.unpack_from("<I", f.data, 4)[0]))
    return out


def taken(rig):
    """Every frame the rig's recorder has seen and not handed out yet: up
    to a marker frame the test's canopen client sends now (the recorder
    has then seen everything before it)."""
    rig.net.send_message(MARKER, bytes(8))
    frames = []
    while True:
        msg = rig.recorder.next(10.0)
        assert msg is not None, "the recorder did not see the marker frame"
        if msg.arbitration_id == MARKER:
            return frames
        frames.append(msg)


def change_by_sdo(node):
    """What a user would do with any SDO client: three settings changed,
    the mapping the CiA 301 way (the PDO off while it is remapped)."""
    node.sdo[ACCELERATION[0]].raw = CHANGED[ACCELERATION]
    node.sdo[HOMING_CURRENT[0]].raw = CHANGED[HOMING_CURRENT]
    cob = node.sdo[0x1801][1].raw
    node.sdo[0x1801][1].raw = cob | 0x80000000
    count = node.sdo[0x1A01][0].raw
    node.sdo[0x1A01][0].raw = 0
    node.sdo[0x1A01][1].raw = CHANGED[MAPPING]
    node.sdo[0x1A01][0].raw = count
    node.sdo[0x1801][1].raw = cob


def read(node, key):
    obj = node.sdo[key[0]]
    return obj.raw if key[1] == 0 and not hasattr(obj, "__getitem__") else obj[key[1]].raw


def differing(out):
    """(index, sub) of each line diff printed."""
    keys = []
    for line in out.splitlines():
        index, _, sub = line.split()[:3]
        keys.append((int(index, 16), int(sub)))
    return keys


def test_round_trip_and_power_cycle(rig, tmp_path):
    node = rig.remote(1, DCF)
    original = {key: read(node, key) for key in CHANGED}
    assert all(original[key] != CHANGED[key] for key in CHANGED)
    b0 = backup(rig, tmp_path / "node1.dcf")

    change_by_sdo(node)
    code, out, err = run(rig, "diff", b0)
    assert code == 1, err
    assert sorted(differing(out)) == sorted(CHANGED), out
    assert "Profile acceleration: drive 20000 (0x00004E20), file %d" % original[ACCELERATION] in out
    b1 = backup(rig, tmp_path / "changed.dcf")

    taken(rig)
    code, out, err = run(rig, "restore", b0)
    assert code == 0, out + err
    frames = taken(rig)
    requests = sdo_requests(frames)
    nmt = [i for i, f in enumerate(frames) if f.arbitration_id == 0 and bytes(f.data) == b"\x80\x01"]
    first_write = [i for i, f in enumerate(frames) if sdo_requests([f]) and sdo_requests([f])[0][0] == "write"][0]
    assert nmt and nmt[0] < first_write, "restore wrote before sending the node to pre-operational"
    assert "not stored" in out
    assert not [r for r in requests if r[0] == "write" and r[1] == 0x1010], "0x1010 written without --store"
    # TxPDO2 rewritten the CiA 301 way: COB-ID invalid, count 0, entries, count, COB-ID valid
    pdo = [(r[1], r[2], r[3]) for r in requests if r[0] == "write" and r[1] in (0x1801, 0x1A01)]
    cob = 0x281
    assert pdo[0] == (0x1801, 1, cob | 0x80000000)
    assert pdo.index((0x1A01, 0, 0)) < pdo.index((0x1A01, 1, original[MAPPING])) < pdo.index((0x1A01, 0, 2))
    assert pdo[-1] == (0x1801, 1, cob)
    assert pdo.index((0x1A01, 0, 2)) == len(pdo) - 2
    assert all(r[0] == "read" or r[1] in (0x1801, 0x1A01, ACCELERATION[0], HOMING_CURRENT[0]) for r in requests), \
        "restore wrote objects that did not differ"
    assert {key: read(node, key) for key in CHANGED} == original
    code, out, err = run(rig, "diff", b0)
    assert (code, out) == (0, ""), err

    # --store keeps the changed settings; a later restore without it does not survive
    code, out, err = run(rig, "restore", b1, "--store")
    assert code == 0, out + err
    assert "stored with 0x1010" in out
    assert run(rig, "diff", b1)[:2] == (0, "")
    code, out, err = run(rig, "restore", b0)
    assert code == 0, out + err
    assert run(rig, "diff", b0)[:2] == (0, "")

    rig.sim.inject_fault(1, "reboot")  # a power cycle: the drive starts from what it stored
    assert {key: read(node, key) for key in CHANGED} == CHANGED
    assert run(rig, "diff", b1)[:2] == (0, "")
    code, out, _ = run(rig, "diff", b0)
    assert code == 1 and sorted(differing(out)) == sorted(CHANGED), out


def test_power_cycle_without_store_loses_a_restore(rig, tmp_path):
    node = rig.remote(1, DCF)
    original = read(node, ACCELERATION)
    b0 = backup(rig, tmp_path / "node1.dcf")
    change_by_sdo(node)
    b1 = backup(rig, tmp_path / "changed.dcf")
    run(rig, "restore", b0)
    assert run(rig, "restore", b1)[0] == 0
    assert read(node, ACCELERATION) == CHANGED[ACCELERATION]
    rig.sim.inject_fault(1, "reboot")
    assert read(node, ACCELERATION) == original
    assert run(rig, "diff", b0)[:2] == (0, "")


def test_backup_is_a_dcf_the_driver_accepts(rig, tmp_path):
    node = rig.remote(1, DCF)
    change_by_sdo(node)
    code, out, err = run(rig, "backup", "--dcf", DCF)
    assert code == 0, err
    assert out.startswith("[FileInfo]") and "backup node 1" in err, "stdout carries only the DCF"
    assert "522/522" in err or DCF == NODE1  # maxon's DCF: 522 readable objects, each read once
    path = tmp_path / "node1.dcf"
    path.write_text(out)
    cfg = load_config({"sync": {"interval_ms": 10}, "nodes": {"n1": {"id": 1, "eds_file": str(path)}}}, "test")
    plan = plan_node(cfg.nodes[0], canopen.import_od(cfg.nodes[0].eds_file, 1), cfg.sync, "test")
    assert plan.source == "dcf"
    written = {(w.key.index, w.key.subindex): w.data for w in plan.writes}
    assert written[ACCELERATION] == struct.pack("<I", CHANGED[ACCELERATION])
    assert written[HOMING_CURRENT] == struct.pack("<H", CHANGED[HOMING_CURRENT])
    tx2 = [m for m in plan.tx if m.number == 2][0]
    assert [(k.index, k.subindex) for k, _ in tx2.entries] == [(0x30D1, 2), (0x606C, 0)]
    od = canopen.import_od(str(path), 1)
    assert od[0x6098].value == read(node, (0x6098, 0))  # a signed value reads back as written
    assert od[0x1008].value == "EPOS4"  # a segmented upload
    if DCF == UNEDITED:
        assert od[0x2200][2].value == read(node, (0x2200, 2))  # the BOOLEAN object


def test_refuses_while_a_master_sends_sync(rig):
    def with_a_master(device, bitrate):
        bus = open_device(device, bitrate)
        rig.send(0x080)  # queued for the tool before it listens: it must hear it
        return bus
    taken(rig)
    code, out, err = run(rig, "backup", "--dcf", DCF, opener=with_a_master)
    assert code == 2 and out == ""
    assert "another CANopen master is active" in err and "SYNC (COB-ID 0x080)" in err
    assert "Ctrl-C" in err
    assert sdo_requests(taken(rig)) == [], "the tool talked to the drive"


def test_a_master_that_starts_within_the_window_is_heard(rig):
    rig.clock.after(0.8 * float(LISTEN), lambda: rig.send(0x080))  # late in the listen window
    taken(rig)
    code, out, err = run(rig, "diff", DCF)
    assert code == 2 and "SYNC (COB-ID 0x080) 1 times" in err, err
    assert sdo_requests(taken(rig)) == [], "the tool talked to the drive"


def test_refuses_while_the_drivers_master_heartbeat_is_heard(rig, tmp_path):
    def with_a_master(device, bitrate):
        bus = open_device(device, bitrate)
        rig.send(0x77F, b"\x05")
        return bus
    code, out, err = run(rig, "restore", NODE1 if DCF == NODE1 else DCF, opener=with_a_master)
    assert code == 2
    assert "heartbeat of node 127 (COB-ID 0x77F)" in err


def test_refuses_while_the_master_the_drive_watches_is_heard(rig):
    node = rig.remote(1, DCF)
    node.sdo[0x1016][1].raw = 0x00050064  # the drive watches node 5, 100 ms

    def with_a_master(device, bitrate):
        bus = open_device(device, bitrate)
        rig.send(0x705, b"\x05")
        return bus
    code, out, err = run(rig, "diff", DCF, opener=with_a_master)
    assert code == 2
    assert "heartbeat of node 5 (COB-ID 0x705)" in err and "0x1016" in err
    # another drive's heartbeat is no master's
    def with_a_drive(device, bitrate):
        bus = open_device(device, bitrate)
        rig.send(0x702, b"\x7f")
        return bus
    code, out, err = run(rig, "diff", DCF, opener=with_a_drive)
    assert code == 1, err  # ran: 0x1016 sub 1 differs from the file


def test_node_that_does_not_answer(rig):
    out, err = io.StringIO(), io.StringIO()
    code = settings.main(["backup", "virtual:" + rig.channel, "5", "--dcf", DCF, "--listen", LISTEN,
                          "--sdo-timeout", "0.2"], out, err, clock=rig.clock)
    assert code == 2 and out.getvalue() == ""
    assert "node 5 does not answer on virtual:%s" % rig.channel in err.getvalue()
    assert "node-ID 5" in err.getvalue()


def test_file_for_another_product_is_refused(rig, tmp_path):
    other = tmp_path / "epos4_other.dcf"
    text = open(DCF).read().replace("0x65520000", "0x64520000")
    assert "0x64520000" in text
    other.write_text(text)
    for command in ("diff", "restore"):
        taken(rig)
        code, out, err = run(rig, command, str(other))
        assert code == 2, err
        assert "product code 0x64520000" in err and "0x65520000" in err
        assert [r for r in sdo_requests(taken(rig)) if r[0] == "write"] == []


def test_restore_refuses_another_nodes_file(rig, tmp_path):
    if not os.path.isfile(NODE2_VENDOR):
        pytest.skip("maxon's node 2 DCF is test data in ../shared/vendor_dcf, absent here")
    taken(rig)
    code, out, err = run(rig, "restore", NODE2_VENDOR)
    assert code == 2 and "made for node 2" in err
    assert [r for r in sdo_requests(taken(rig)) if r[0] == "write"] == []


def test_restore_refuses_while_the_power_stage_is_on(rig, tmp_path):
    b0 = backup(rig, tmp_path / "node1.dcf")
    node = rig.remote(1, DCF)
    for cw in (0x0006, 0x0007, 0x000F):
        node.sdo[0x6040].raw = cw
    taken(rig)
    code, out, err = run(rig, "restore", b0)
    assert code == 2 and "power stage is on" in err
    assert [r for r in sdo_requests(taken(rig)) if r[0] == "write"] == []


def test_refused_objects_are_reported_and_the_rest_written(rig, tmp_path):
    node = rig.remote(1, DCF)
    original = {key: read(node, key) for key in CHANGED}
    b0 = backup(rig, tmp_path / "node1.dcf")
    change_by_sdo(node)
    # a file whose profile velocity the drive refuses (above its limit)
    text = (tmp_path / "node1.dcf").read_text()
    section = text.index("[6081]")
    start = text.index("ParameterValue=", section)
    end = text.index("\n", start)
    bad = tmp_path / "bad.dcf"
    bad.write_text(text[:start] + "ParameterValue=0x0000EA60" + text[end:])  # 60000 rpm
    code, out, err = run(rig, "restore", str(bad))
    assert code == 1, out + err
    assert "refused 0x6081 sub 0 Profile velocity = 60000 (0x0000EA60): abort 0x06090031 " \
           "Value of parameter written too high" in out
    assert {key: read(node, key) for key in CHANGED} == original
    assert run(rig, "diff", b0)[:2] == (0, ""), "the other settings were not restored"


def test_bad_arguments(tmp_path):
    err = io.StringIO()
    assert settings.main(["diff", "vcan0", "1", str(tmp_path / "missing.dcf")], io.StringIO(), err) == 2
    assert "no such file" in err.getvalue()
    err = io.StringIO()
    assert settings.main(["backup", "nosuch:x", "1"], io.StringIO(), err) == 2
    assert "unknown interface" in err.getvalue()
    assert settings.main(["backup", "vcan0", "300"], io.StringIO(), io.StringIO()) == 2


def test_a_failing_adapter_is_a_clear_error(clock):
    class Broken(can.BusABC):
        """An adapter that stops sending once the tool has listened."""

        def __init__(self):
            super().__init__(channel="broken")

        def send(self, msg, timeout=None):
            raise can.CanOperationError("Transmit buffer full")

        def _recv_internal(self, timeout):
            return None, False

    err = io.StringIO()
    code = settings.main(["diff", "virtual:x", "1", DCF, "--listen", "0"], io.StringIO(), err,
                         lambda device, bitrate: Broken(), clock=clock)
    assert code == 2
    assert "CAN error on virtual:x after 1 SDO transfers: Transmit buffer full" in err.getvalue()


def test_listen_ends_on_a_bus_that_never_runs_dry():
    """On the wall clock: python-can's notifier thread reads for the
    window, then the tool takes at most DRAIN_LIMIT queued frames itself."""
    class Busy(can.BusABC):
        """A bus with a PDO waiting at every read."""

        def __init__(self):
            super().__init__(channel="busy")
            self.caller = threading.get_ident()
            self.reads_by_caller = 0
            self.reads = 0

        def send(self, msg, timeout=None):
            pass

        def _recv_internal(self, timeout):
            self.reads += 1
            if threading.get_ident() == self.caller:
                self.reads_by_caller += 1
            return can.Message(arbitration_id=0x181, data=b"\x00\x00", is_extended_id=False), False

    bus = Busy()
    heard = settings.listen(bus, 0.05)
    assert (heard.syncs, heard.heartbeats) == (0, {})
    # the window's reads are the notifier thread's (as many as the host let it make)
    assert bus.reads_by_caller == settings.DRAIN_LIMIT


def replace_value(text, section, value):
    """``text`` (a DCF) with the ParameterValue of ``section`` replaced."""
    start = text.index("ParameterValue=", text.index("[%s]" % section))
    return text[:start] + "ParameterValue=" + value + text[text.index("\n", start):]


def test_a_value_the_type_cannot_hold_is_reported_and_the_rest_written(rig, tmp_path):
    node = rig.remote(1, DCF)
    original = {key: read(node, key) for key in CHANGED}
    b0 = backup(rig, tmp_path / "node1.dcf")
    change_by_sdo(node)
    bad = tmp_path / "bad.dcf"
    bad.write_text(replace_value((tmp_path / "node1.dcf").read_text(), "30B2", "70000"))  # UNSIGNED16
    code, out, err = run(rig, "restore", str(bad))
    assert code == 1, out + err
    assert "not written 0x30B2 sub 0 Current threshold for homing mode = 70000: the file's value does not " \
           "fit its data type" in out
    assert read(node, HOMING_CURRENT) == CHANGED[HOMING_CURRENT]
    assert {key: read(node, key) for key in (MAPPING, ACCELERATION)} == \
        {key: original[key] for key in (MAPPING, ACCELERATION)}
    code, out, _ = run(rig, "diff", b0)
    assert (code, differing(out)) == (1, [HOMING_CURRENT])


def test_backup_reports_objects_the_drive_does_not_have(rig, tmp_path):
    listing = tmp_path / "more.dcf"
    extra = ("\n[5FFF]\nParameterName=An object this drive lacks\nObjectType=0x7\nDataType=0x0007\n"
             "AccessType=rw\nDefaultValue=0\nPDOMapping=0\n")
    listing.write_text(open(DCF).read() + extra)
    code, out, err = run(rig, "backup", "--dcf", str(listing))
    assert code == 1
    assert "not read, 0x5FFF sub 0 An object this drive lacks: abort 0x06020000 Object does not exist" in err
    assert out.startswith("[FileInfo]")
    backed = tmp_path / "backup.dcf"
    backed.write_text(out)
    od = canopen.import_od(str(backed), 1)
    assert od[0x5FFF].value is None and od[0x6083].value == read(rig.remote(1, DCF), ACCELERATION)


def test_backup_keeps_the_files_object_flags(rig, tmp_path):
    path = backup(rig, tmp_path / "node1.dcf")
    def flagged(dcf):
        return {key: flags for key, flags in settings.load_file(dcf, 1).flags.items() if flags}
    assert flagged(path) == flagged(DCF)
    if DCF == UNEDITED:
        assert flagged(path)[(0x6040, 0)] == settings.REFUSE_WRITE

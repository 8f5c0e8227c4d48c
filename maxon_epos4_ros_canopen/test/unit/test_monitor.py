"""canopen_monitor: every frame type decoded, from frames the virtual EPOS4
and an independent canopen client put on a bus, and from hand-made ones
(malformed included: the monitor never stops on a frame)."""
from __future__ import annotations

import io
import itertools
import os
import random
import struct
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import can
import pytest

from sim_support import NODE1, NodeConfig
from maxon_epos4_ros_canopen import monitor as mon
from maxon_epos4_ros_canopen import monitor_cli as cli
from maxon_epos4_ros_canopen.objects import load_dictionary

PKG = Path(__file__).resolve().parents[2]
SCRIPT = PKG / "scripts" / "canopen_monitor"


def frame(cob: int, data: bytes = b"", **kw) -> can.Message:
    return can.Message(arbitration_id=cob, data=data, is_extended_id=kw.pop("extended", False), **kw)


@pytest.fixture(scope="module")
def decoder() -> mon.Decoder:
    return mon.Decoder({1: load_dictionary(NODE1, 1)}, cli.default_dictionary())


# --- frames the virtual EPOS4 and a canopen client produce -------------------------

def test_simulator_traffic_decodes_to_states_objects_and_values(sim_rig):
    rig = sim_rig([NodeConfig(1, NODE1)])
    try:
        node = rig.remote(1)
        rig.drain()
        node.sdo[0x1017].raw = 50                       # expedited write, heartbeat on
        assert node.sdo[0x1008].raw == "EPOS4"          # segmented read
        assert node.sdo[0x6041].raw & 0x4F == 0x40      # expedited read: switch on disabled
        with pytest.raises(Exception):
            node.sdo.upload(0x5FFF, 0)                  # abort: object does not exist
        node.nmt.state = "OPERATIONAL"                  # NMT start node 1 (the observer hears the client)
        frames = []

        def seen(cob_id, data=None):
            frames.extend(rig.collect(0.01))
            return any(f.arbitration_id == cob_id and data in (None, bytes(f.data)) for f in frames)
        assert rig.wait(lambda: seen(0x701, b"\x05"))  # the drive says it is operational
        rig.net.sync.transmit()                         # SYNC: the synchronous TPDOs answer
        rig.sim.inject_fault(1, "emcy", error_code=0x8611)
        assert rig.wait(lambda: seen(0x181) and seen(0x081))
    finally:
        rig.close()
    d = mon.Decoder({1: load_dictionary(NODE1, 1)})
    texts = [d.decode(f).text for f in frames]
    joined = "\n".join(texts)
    assert "node 1 SDO write Producer heartbeat time (1017) = 50 (0x32)" in joined
    assert "node 1 SDO write Producer heartbeat time (1017) done" in joined
    assert "node 1 SDO value Manufacturer device name (1008) follows in segments, 5 bytes" in joined
    assert "node 1 SDO value Manufacturer device name (1008) = 'EPOS4' (segmented)" in joined
    assert "node 1 SDO read Statusword (6041)" in joined
    assert any(t.startswith("node 1 SDO value Statusword (6041) = ") for t in texts)
    assert "node 1 SDO abort from drive 5FFF: 0x06020000 Object does not exist" in joined
    assert "NMT start -> node 1" in joined
    assert "SYNC" in texts
    assert "node 1 heartbeat: operational" in joined
    assert any(t.startswith("node 1 TPDO1: Statusword (6041) = ") and "Modes of operation display (6061) = " in t
               for t in texts), joined
    assert "node 1 EMCY 0x8611 Following error, error register 0x81 (generic, manufacturer (EPOS4: motion))" \
        in joined
    assert not any("MALFORMED" in d.decode(f).kind for f in frames)


def test_pdo_mapping_read_from_the_drive(sim_rig):
    rig = sim_rig([NodeConfig(1, NODE1)])
    try:
        node = rig.remote(1)
        d = mon.Decoder({}, cli.default_dictionary())  # no DCF: names only
        lines = mon.read_pdo_mapping(node.sdo.upload, 1, d)
        rig.drain()
        rig.send(0x000, b"\x01\x01")
        rig.send(0x080)
        tpdo1 = rig.expect(lambda m: m.arbitration_id == 0x181)
    finally:
        rig.close()
    assert "node 1 TPDO1 (COB-ID 0x181): Statusword (6041), Modes of operation display (6061)" in lines
    assert d.decode(tpdo1).text.startswith("node 1 TPDO1: Statusword (6041) = ")


# --- hand-made frames -------------------------------------------------------------

@pytest.mark.parametrize("msg, text", [
    (frame(0x000, b"\x01\x00"), "NMT start -> all nodes"),
    (frame(0x000, b"\x02\x05"), "NMT stop -> node 5"),
    (frame(0x000, b"\x80\x01"), "NMT enter pre-operational -> node 1"),
    (frame(0x000, b"\x81\x01"), "NMT reset node -> node 1"),
    (frame(0x000, b"\x82\x01"), "NMT reset communication -> node 1"),
    (frame(0x000, b"\x07\x01"), "NMT unknown command 0x07 -> node 1"),
    (frame(0x080, b"\x05"), "SYNC counter 5"),
    (frame(0x100, bytes(6)), "TIME stamp"),
    # maxon's troubleshooting notes: candump's "81#2081100000000000" is CAN passive
    (frame(0x081, bytes.fromhex("2081100000000000")),
     "node 1 EMCY 0x8120 CAN passive mode error, error register 0x10 (communication)"),
    (frame(0x082, bytes(8)), "node 2 EMCY error reset (no error), error register 0x00 (no error)"),
    (frame(0x081, bytes.fromhex("3232050102030405")),
     "node 1 EMCY 0x3232 unknown EPOS4 error, error register 0x05 (generic, voltage), "
     "manufacturer data 01 02 03 04 05"),
    (frame(0x701, b"\x00"), "node 1 boot-up"),
    (frame(0x701, b"\x04"), "node 1 heartbeat: stopped"),
    (frame(0x701, b"\x7f"), "node 1 heartbeat: pre-operational"),
    (frame(0x701, b"\x85"), "node 1 heartbeat: operational (node-guarding answer, toggle 1)"),
    (frame(0x701, is_remote_frame=True), "node 1 node-guarding request (RTR)"),
    (frame(0x601, bytes.fromhex("2B40600006000000")), "node 1 SDO write Controlword (6040) = 6 (0x6)"),
    (frame(0x601, bytes.fromhex("237A600010270000")), "node 1 SDO write Target position (607A) = 10000 (0x2710)"),
    (frame(0x601, bytes.fromhex("237A6000F0D8FFFF")),
     "node 1 SDO write Target position (607A) = -10000 (0xFFFFD8F0)"),
    (frame(0x601, bytes.fromhex("4000180100000000")), "node 1 SDO read Transmit PDO 1 parameter: COB-ID used by "),
    (frame(0x581, bytes.fromhex("6040600000000000")), "node 1 SDO write Controlword (6040) done"),
    (frame(0x581, bytes.fromhex("8040600002000106")),
     "node 1 SDO abort from drive Controlword (6040): 0x06010002 Attempt to write a read only object"),
    (frame(0x181, b"\x37\x06\x01"), "node 1 TPDO1: Statusword (6041) = 1591 (0x637), "
                                    "Modes of operation display (6061) = 1 (0x1)"),
    (frame(0x181, b"\x37"), "node 1 TPDO1: Statusword (6041): missing (frame has 1 bytes)"),
    (frame(0x185, bytes(8)), "node 5 TPDO1: 00 00 00 00 00 00 00 00 (mapping unknown"),
    (frame(0x7E5, b"\x04\x01"), "LSS request command 0x04"),
    (frame(0x7FF, b""), "COB-ID 0x7FF: not in CANopen's predefined connection set"),
    (frame(0x18FF0000, b"\x01", extended=True), "29-bit identifier: not CANopen"),
    (frame(0x000, b"\x01"), "NMT malformed: 1 bytes (expected 2)"),
    (frame(0x080, b"\x01\x02"), "SYNC malformed: 2 bytes"),
    (frame(0x081, b"\x20"), "node 1 EMCY malformed: 1 bytes (expected 8): 20"),
    (frame(0x081, b""), "node 1 EMCY malformed: no data"),
    (frame(0x701, b""), "node 1 heartbeat malformed: 0 bytes"),
    (frame(0x701, b"\x05\x05"), "node 1 heartbeat malformed: 2 bytes"),
    (frame(0x581, b"\x4b\x41"), "node 1 SDO answer malformed: 2 bytes (expected 8): 4B 41"),
    (frame(0x601, b""), "node 1 SDO request malformed: 0 bytes (expected 8)"),
    (frame(0x581, bytes.fromhex("0041424300000000")), "node 1 SDO segment 41 42 43 00 00 00 00 (no transfer started)"),
    (frame(0x601, bytes.fromhex("E000000000000000")), "node 1 SDO request with unknown command 0xE0"),
    (frame(0x100, b"\x01"), "TIME malformed: 1 bytes"),
    (frame(0x7E4, b""), "LSS malformed: no data"),
])
def test_hand_made_frames(decoder, msg, text):
    assert text in decoder.decode(msg).text


def test_any_frame_at_all_decodes_to_a_line():
    rng = random.Random(1234)
    d = mon.Decoder({1: load_dictionary(NODE1, 1)}, cli.default_dictionary())
    kinds = set()
    for cob in itertools.chain(range(0x800), (0x1FFFFFFF, 0x18FEF100)):
        for length in range(9):
            for remote in (False, True):
                data = bytes(rng.randrange(256) for _ in range(length))
                msg = can.Message(arbitration_id=cob, data=b"" if remote else data, dlc=length,
                                  is_remote_frame=remote, is_extended_id=cob > 0x7FF)
                decoded = d.decode(msg)
                assert decoded.text, msg
                kinds.add(decoded.kind)
                mon.format_line(msg, decoded, 0.0)
    d.decode(can.Message(is_error_frame=True))
    # every odd frame is handled on purpose, none by the last-resort catch
    assert "MALFORMED" not in kinds
    assert {"NMT", "SYNC", "TIME", "EMCY", "TPDO1", "RPDO4", "SDO", "HEARTBEAT", "GUARD", "LSS",
            "EXTENDED"} <= kinds


def test_decoder_survives_a_type_that_cannot_hold_the_value(decoder):
    # a 1-byte value written to a 4-byte object: shown as bytes, not an exception
    text = decoder.decode(frame(0x601, bytes.fromhex("2F7A600005000000"))).text
    assert text.startswith("node 1 SDO write Target position (607A) = ")


# --- filters, load, record ----------------------------------------------------------

def test_filters_by_node_and_object(decoder):
    frames = [frame(0x181, b"\x37\x06\x01"), frame(0x182, b"\x37\x06\x01"), frame(0x080),
              frame(0x601, bytes.fromhex("4041600000000000")), frame(0x601, bytes.fromhex("4064600000000000"))]
    decoded = [decoder.decode(f) for f in frames]
    by_node = mon.Filter(nodes=[1])
    assert [by_node(x) for x in decoded] == [True, False, False, True, True]
    by_object = mon.Filter(objects=[mon.parse_object("6041")])
    assert [by_object(x) for x in decoded] == [True, False, False, True, False]
    both = mon.Filter(nodes=[1], objects=[mon.parse_object("6064sub0")])
    assert [both(x) for x in decoded] == [False, False, False, False, True]
    with pytest.raises(ValueError, match="expected INDEX or INDEXsubSUB"):
        mon.parse_object("statusword")


def test_bus_load_line_counts_bits_like_canbusload():
    load = cli.BusLoad("can0", 1000000)
    for _ in range(1000):
        load.add(frame(0x181, bytes(8)))  # 47 + 64 = 111 bits
    line = load.line(1.0)
    assert line.startswith("can0  1000 frames/s  111000 bit/s  11% of 1000000 bit/s |XX")
    assert load.line(1.0).startswith("can0  0 frames/s  0 bit/s  0%")


def test_candump_log_lines_round_trip():
    msgs = [frame(0x181, b"\x37\x06", timestamp=1700000000.25), frame(0x701, is_remote_frame=True, timestamp=1.0),
            frame(0x18FF0001, b"\x01", extended=True, timestamp=2.0), frame(0x080, timestamp=3.5)]
    lines = [cli.candump_line(m, "can0") for m in msgs]
    assert lines == ["(1700000000.250000) can0 181#3706", "(1.000000) can0 701#R",
                     "(2.000000) can0 18FF0001#01", "(3.500000) can0 080#"]
    for m, line in zip(msgs, lines):
        back, device = cli.parse_candump_line(line)
        assert device == "can0" and back.arbitration_id == m.arbitration_id and bytes(back.data) == bytes(m.data)
        assert back.is_remote_frame == m.is_remote_frame and back.is_extended_id == m.is_extended_id
    for bad in ("", "181#00", "(1.0) can0 181#0", "(1.0) can0 181#000102030405060708"):
        with pytest.raises(ValueError):
            cli.parse_candump_line(bad)


def test_live_session_on_virtual_bus_prints_and_records(tmp_path):
    channel = "monitor_" + uuid.uuid4().hex[:8]
    record = tmp_path / "bus.log"
    out, stop = io.StringIO(), threading.Event()
    argv = ["virtual:" + channel, "--dcf", "1:" + NODE1, "--node", "1", "--record", str(record),
            "--load-interval", "0.2"]
    session = threading.Thread(target=cli.main, args=(argv, out, stop))
    session.start()
    sender = can.Bus(interface="virtual", channel=channel)
    try:
        def wait(condition):
            end = time.monotonic() + 10
            while time.monotonic() < end and not condition():
                time.sleep(0.05)
            return condition()
        # the monitor has opened its bus once it prints the first load line
        assert wait(lambda: "frames/s" in out.getvalue())
        sender.send(frame(0x701, b"\x05"))
        sender.send(frame(0x702, b"\x05"))      # another node: recorded, not shown
        sender.send(frame(0x081, bytes.fromhex("2081100000000000")))
        assert wait(lambda: "EMCY" in out.getvalue() and len(record.read_text().splitlines()) == 3)
    finally:
        stop.set()
        session.join(10)
        sender.shutdown()
    assert not session.is_alive()
    text = out.getvalue()
    assert "node 1 heartbeat: operational" in text and "node 2" not in text
    assert "node 1 EMCY 0x8120 CAN passive mode error" in text
    logged = record.read_text().splitlines()
    assert [line.split(" ", 1)[1] for line in logged] == [
        "virtual:%s 701#05" % channel, "virtual:%s 702#05" % channel, "virtual:%s 081#2081100000000000" % channel]


def test_script_decodes_a_candump_log_and_rejects_bad_arguments(tmp_path):
    log = tmp_path / "field.log"
    log.write_text("(1700000000.000000) can0 081#2081100000000000\n"
                   "garbage line\n"
                   "(1700000000.010000) can0 581#4B41600037060000\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(PKG / "src"), os.environ.get("PYTHONPATH", "")]))
    run = subprocess.run([sys.executable, str(SCRIPT), "--log", str(log), "--dcf", "1:" + NODE1],
                         capture_output=True, text=True, env=env, timeout=60)
    assert run.returncode == 0, run.stderr
    lines = run.stdout.splitlines()
    assert "node 1 EMCY 0x8120 CAN passive mode error, error register 0x10 (communication)" in lines[0]
    assert "field.log:2: not a candump log line" in lines[1]
    assert lines[2].endswith("node 1 SDO value Statusword (6041) = 1591 (0x637)")
    bad = subprocess.run([sys.executable, str(SCRIPT), "--log", str(log), "--dcf", "one:" + NODE1],
                         capture_output=True, text=True, env=env, timeout=60)
    assert bad.returncode == 2 and "--dcf 'one:" in bad.stderr
    missing = subprocess.run([sys.executable, str(SCRIPT), "nosuch:0"], capture_output=True, text=True, env=env,
                             timeout=60)
    assert missing.returncode == 1 and "CAN device 'nosuch:0': unknown interface 'nosuch'" in missing.stderr

"""NMT, heartbeat, node guarding, SYNC and PDOs of the virtual EPOS4, on the bus."""
import struct

import pytest

from sim_support import NODE1, NODE2, NodeConfig, enable


@pytest.fixture
def rig(sim_rig):
    return sim_rig([NodeConfig(1, NODE1), NodeConfig(2, NODE2)])


def test_boot_up_after_reset_node_and_reset_communication(rig):
    node = rig.remote(1)
    node.sdo[0x6081].raw = 777
    node.sdo[0x1400][2].raw = 255  # communication object: reset by 0x82
    rig.drain()
    rig.send(0x000, bytes([0x82, 1]))
    assert rig.expect(lambda m: m.arbitration_id == 0x701 and bytes(m.data) == b"\x00")
    assert node.sdo[0x1400][2].raw == 1
    assert node.sdo[0x6081].raw == 777  # application object survives reset communication
    rig.send(0x000, bytes([0x81, 0]))  # reset node: both nodes boot
    seen = set()
    assert rig.wait(lambda: seen.update(m.arbitration_id for m in rig.collect(0.01) if bytes(m.data) == b"\x00")
                    or {0x701, 0x702} <= seen), seen
    assert node.sdo[0x6081].raw == 1000  # power-on value


def test_heartbeat_producer_reports_nmt_state(rig):
    node = rig.remote(2, NODE2)
    node.sdo[0x1017].raw = 50
    rig.drain()
    assert rig.expect(lambda m: m.arbitration_id == 0x702 and m.data[0] == 0x7F)
    rig.send(0x000, bytes([0x01, 2]))
    assert rig.expect(lambda m: m.arbitration_id == 0x702 and m.data[0] == 0x05)
    rig.send(0x000, bytes([0x02, 2]))
    assert rig.expect(lambda m: m.arbitration_id == 0x702 and m.data[0] == 0x04)
    beats = [m for m in rig.collect(0.5) if m.arbitration_id == 0x702]
    assert 3 <= len(beats) <= 15  # 50 ms period over 0.5 s


def test_stopped_node_answers_no_sdo_but_node_guarding(rig):
    rig.send(0x000, bytes([0x02, 1]))
    rig.drain()
    rig.send(0x601, bytes([0x40, 0x41, 0x60, 0, 0, 0, 0, 0]))
    assert not [m for m in rig.handled() if m.arbitration_id == 0x581]  # the request was handled: no answer
    rig.send(0x701, remote=True)
    first = rig.expect(lambda m: m.arbitration_id == 0x701)
    rig.send(0x701, remote=True)
    second = rig.expect(lambda m: m.arbitration_id == 0x701)
    assert first.data[0] & 0x7F == 0x04 and second.data[0] & 0x7F == 0x04
    assert (first.data[0] ^ second.data[0]) == 0x80  # toggle bit


def test_pdos_only_in_operational(rig):
    rig.drain()
    rig.send(0x080)
    assert not [m for m in rig.handled() if m.arbitration_id == 0x181]  # the SYNC was handled: no TxPDO
    rig.send(0x000, bytes([0x01, 1]))
    rig.send(0x080)
    msg = rig.expect(lambda m: m.arbitration_id == 0x181)
    sw, mode = struct.unpack("<Hb", msg.data)
    assert sw == 0x0250 and mode == 1


def test_sync_tpdo_every_nth_sync_and_rtr(rig):
    node = rig.remote(1)
    node.sdo[0x1802][1].raw = 0x80000381
    node.sdo[0x1802][2].raw = 3  # every third SYNC
    node.sdo[0x1802][1].raw = 0x00000381
    rig.send(0x000, bytes([0x01, 1]))
    rig.drain()
    for _ in range(2):
        rig.send(0x080)
        assert rig.expect(lambda m: m.arbitration_id == 0x181)  # TxPDO1 answers every SYNC
    assert not [m for m in rig.handled() if m.arbitration_id == 0x381]
    rig.send(0x080)
    assert rig.expect(lambda m: m.arbitration_id == 0x381)  # the third SYNC
    for _ in range(2):
        rig.send(0x080)
        assert rig.expect(lambda m: m.arbitration_id == 0x181)
    assert not [m for m in rig.handled() if m.arbitration_id == 0x381]
    rig.send(0x281, remote=True)  # TPDO2 on request
    msg = rig.expect(lambda m: m.arbitration_id == 0x281)
    assert len(msg.data) == 8


def test_remap_tpdo_at_run_time_with_canopen_client(rig):
    node = rig.remote(1)
    node.tpdo.read()
    tpdo = node.tpdo[4]
    tpdo.clear()
    tpdo.add_variable(0x6064)
    tpdo.add_variable(0x6041)
    tpdo.trans_type = 254
    tpdo.inhibit_time = 100  # 10 ms
    tpdo.enabled = True
    tpdo.save()  # disable, sub0=0, entries, sub0=n, enable
    assert node.sdo[0x1A03][0].raw == 2
    assert node.sdo[0x1A03][1].raw == 0x60640020
    rig.send(0x000, bytes([0x01, 1]))
    msg = rig.expect(lambda m: m.arbitration_id == 0x481)  # event: first value on start
    position, sw = struct.unpack("<iH", msg.data)
    assert sw == 0x0250 and position == node.sdo[0x6064].raw


def test_sync_rpdo_applies_at_next_sync_async_at_once(rig):
    node = rig.remote(1)
    rig.send(0x000, bytes([0x01, 1]))
    rig.send(0x201, struct.pack("<Hi", 0x0006, 0))  # RxPDO1 is synchronous (type 1)
    rig.handled()
    assert node.sdo[0x6040].raw == 0 and node.sdo[0x6041].raw & 0x6F == 0x40
    rig.send(0x080)
    assert rig.wait(lambda: node.sdo[0x6041].raw & 0x6F == 0x21)
    node.sdo[0x1401][1].raw = 0x80000301
    node.sdo[0x1401][2].raw = 255
    node.sdo[0x1401][1].raw = 0x00000301
    rig.send(0x301, struct.pack("<iI", 4321, 555))
    assert rig.wait(lambda: node.sdo[0x607A].raw == 4321 and node.sdo[0x6081].raw == 555)


def test_short_rpdo_raises_pdo_length_emcy(rig):
    rig.send(0x000, bytes([0x01, 1]))
    rig.drain()
    rig.send(0x201, b"\x06")
    msg = rig.expect(lambda m: m.arbitration_id == 0x081)
    assert struct.unpack_from("<HB", msg.data) == (0x8210, 0x11)


def test_sync_many_nodes_one_frame_each(rig):
    rig.send(0x000, bytes([0x01, 0]))
    rig.drain()
    rig.send(0x080)
    frames = []
    rig.wait(lambda: frames.extend(rig.collect(0.05)) or len(frames) >= 6)
    frames += rig.handled()  # and nothing more: the SYNC was handled
    ids = sorted(m.arbitration_id for m in frames)
    assert ids == [0x181, 0x182, 0x281, 0x282, 0x381, 0x382]


def test_enable_sequence_statuswords(rig):
    node = rig.remote(1)
    node.sdo[0x6040].raw = 0x0006
    assert node.sdo[0x6041].raw == 0x0231
    node.sdo[0x6040].raw = 0x0007
    assert node.sdo[0x6041].raw == 0x0233
    node.sdo[0x6040].raw = 0x000F
    assert node.sdo[0x6041].raw == 0x0637  # PPM without set-point: target reached
    node.sdo[0x6040].raw = 0x000B
    assert node.sdo[0x6041].raw & 0x2FF == 0x0217  # quick stop active (option 6 stays)
    node.sdo[0x6040].raw = 0x0000
    assert node.sdo[0x6041].raw == 0x0250
    enable(node, 3)
    assert node.sdo[0x6061].raw == 3


def test_event_tpdo_respects_inhibit_time(rig):
    node = rig.remote(1)
    enable(node, 3)
    node.sdo[0x1802][1].raw = 0x80000381
    node.sdo[0x1802][2].raw = 255
    node.sdo[0x1802][3].raw = 500  # 50 ms
    node.sdo[0x1802][1].raw = 0x00000381
    node.sdo[0x60FF].raw = 500  # position changes at every simulation step
    rig.send(0x000, bytes([0x01, 1]))
    assert rig.expect(lambda m: m.arbitration_id == 0x381)
    frames = [m for m in rig.collect(1.0) if m.arbitration_id == 0x381]
    # at most one per 50 ms, not one per 2 ms simulation step
    assert 2 <= len(frames) <= 21


def test_nodes_of_one_dcf_keep_their_own_node_id_values_through_resets(sim_rig):
    """Three nodes read from one file share its dictionary, yet each answers
    with its own $NODEID values (TxPDO COB-IDs, EMCY COB-ID) at power-on and
    after a reset, and a value written to one does not reach the others."""
    r = sim_rig([NodeConfig(n, NODE1) for n in (1, 2, 3)])
    try:
        nodes = {n: r.remote(n) for n in (1, 2, 3)}

        def cob_ids():
            return {n: (node.sdo[0x1800][1].raw & 0x7FF, node.sdo[0x1014].raw & 0x7FF)
                    for n, node in nodes.items()}
        expected = {n: (0x180 + n, 0x080 + n) for n in nodes}
        assert cob_ids() == expected
        nodes[2].sdo[0x6081].raw = 777
        assert [nodes[n].sdo[0x6081].raw for n in (1, 2, 3)] == [1000, 777, 1000]
        r.send(0x000, bytes([0x81, 0]))  # reset node, all of them
        assert r.wait(lambda: nodes[2].sdo[0x6081].raw == 1000)
        assert cob_ids() == expected
    finally:
        r.close()

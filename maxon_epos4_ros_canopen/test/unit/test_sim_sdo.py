"""SDO server of the virtual EPOS4: transfers and every abort code, seen on the bus."""
import struct

import pytest
from canopen.sdo.exceptions import SdoAbortedError

from sim_support import NODE1, NodeConfig


@pytest.fixture
def rig(sim_rig):
    return sim_rig([NodeConfig(1, NODE1)])


def abort_code(rig, node, index, sub, value=None):
    with pytest.raises(SdoAbortedError) as info:
        if value is None:
            node.sdo.upload(index, sub)
        else:
            node.sdo.download(index, sub, value)
    return info.value.code


def test_expedited_and_segmented_upload(rig):
    node = rig.remote(1)
    assert node.sdo.upload(0x1008, 0) == b"EPOS4"  # 5 bytes: segmented
    assert node.sdo[0x1018][1].raw == 0xFB
    assert node.sdo[0x2200][2].raw is True  # BOOLEAN object


def test_segmented_download_stores_value(rig):
    node = rig.remote(1)
    node.sdo.download(0x607A, 0, struct.pack("<i", -12345), force_segment=True)
    assert node.sdo[0x607A].raw == -12345


@pytest.mark.parametrize("index, sub, value, code", [
    (0x1234, 0, None, 0x06020000),
    (0x6041, 7, None, 0x06090011),
    (0x6041, 0, b"\x01\x00", 0x06010002),
    (0x6040, 0, b"\x01", 0x06070010),
    (0x6040, 0, b"\x01\x00\x00\x00", 0x06070010),
    (0x6081, 0, struct.pack("<I", 60000), 0x06090031),
    (0x6081, 0, struct.pack("<I", 0), 0x06090032),
    (0x6060, 0, struct.pack("<b", 2), 0x06090030),
    (0x1003, 0, b"\x03", 0x06090030),
    (0x1010, 1, b"abcd", 0x08000020),
])
def test_abort_codes(rig, index, sub, value, code):
    node = rig.remote(1)
    assert abort_code(rig, node, index, sub, value) == code


def test_write_only_abort_and_general_error_frames(sim_rig):
    # a raw client: upload of a write-only object needs an object that is
    # write-only; the project DCF has none, so patch one in the OD at run time.
    r = sim_rig([NodeConfig(1, NODE1)])
    try:
        var = r.sim.nodes[1].store.vars[(0x6040, 0)]
        r.sim.call(lambda: setattr(var, "access_type", "wo"))
        node = r.remote(1)
        assert abort_code(r, node, 0x6040, 0) == 0x06010001
        r.drain()
        r.send(0x601, bytes([0xA0, 0x41, 0x60, 0, 0, 0, 0, 0]))  # block download: not supported
        msg = r.expect(lambda m: m.arbitration_id == 0x581)
        assert msg.data[0] == 0x80 and struct.unpack_from("<I", msg.data, 4)[0] == 0x05040001
    finally:
        r.close()


def test_toggle_error_and_timeout_abort(rig):
    rig.drain()
    rig.send(0x601, bytes([0x21, 0x7A, 0x60, 0, 4, 0, 0, 0]))  # segmented download of 0x607A
    assert rig.expect(lambda m: m.arbitration_id == 0x581 and m.data[0] == 0x60)
    rig.send(0x601, bytes([0x10, 1, 2, 3, 4, 0, 0, 0]))  # toggle 1 first: wrong
    msg = rig.expect(lambda m: m.arbitration_id == 0x581)
    assert msg.data[0] == 0x80 and struct.unpack_from("<I", msg.data, 4)[0] == 0x05030000
    rig.send(0x601, bytes([0x21, 0x7A, 0x60, 0, 4, 0, 0, 0]))
    assert rig.expect(lambda m: m.arbitration_id == 0x581 and m.data[0] == 0x60)
    # no segment follows: the server gives up after its 1 s timeout
    msg = rig.expect(lambda m: m.arbitration_id == 0x581, timeout=5.0)
    assert msg is not None and struct.unpack_from("<I", msg.data, 4)[0] == 0x05040000


def test_pdo_mapping_aborts(rig):
    node = rig.remote(1)
    # mapping of a valid PDO may not change (CiA 301: disable first)
    assert abort_code(rig, node, 0x1A00, 1, struct.pack("<I", 0x60640020)) == 0x08000022
    node.sdo[0x1800][1].raw = 0x80000181
    node.sdo[0x1A00][0].raw = 0
    assert abort_code(rig, node, 0x1A00, 1, struct.pack("<I", 0x10080008)) == 0x06040041  # not mappable
    assert abort_code(rig, node, 0x1A00, 1, struct.pack("<I", 0x12340020)) == 0x06020000
    for sub, entry in enumerate([0x60640020, 0x606C0020, 0x60410010], 1):
        node.sdo[0x1A00][sub].raw = entry
    assert abort_code(rig, node, 0x1A00, 0, b"\x03") == 0x06040042  # 80 bits
    # a valid PDO's COB-ID cannot move
    node.sdo[0x1801][1].raw = 0x00000281
    assert abort_code(rig, node, 0x1801, 1, struct.pack("<I", 0x00000282)) == 0x06090030


def test_segmented_download_out_of_range_aborts_instead_of_confirming(rig):
    node = rig.remote(1)
    with pytest.raises(SdoAbortedError) as info:
        node.sdo.download(0x6081, 0, struct.pack("<I", 60000), force_segment=True)
    assert info.value.code == 0x06090031
    assert node.sdo[0x6081].raw == 1000

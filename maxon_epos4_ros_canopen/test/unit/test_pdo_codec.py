"""The driver's PDO codec (prepared structs, driver/pdo.py) against
python-canopen's PDO maps: the same bytes for the same values, and the same
values from the same bytes, for every map the plans make (DCF layout and
every compact mode combination) and for every integer type a map can carry.
A wrong byte moves a motor."""
import random

import canopen
import pytest

from maxon_epos4_ros_canopen.driver.pdo import PdoLayoutError, RxPdo, TxPdo, enabled_maps
from maxon_epos4_ros_canopen.driver.plan import MapPlan
from maxon_epos4_ros_canopen.objects import ObjectKey, find_variable, load_dictionary

from test_pdo_layout import CASES, DCF1, plan

OD = load_dictionary(DCF1, 1)
# (signed, bits) of CANopen's INTEGER8/16/32 and UNSIGNED8/16/32
INTEGER_TYPES = {0x2: (True, 8), 0x3: (True, 16), 0x4: (True, 32), 0x5: (False, 8), 0x6: (False, 16),
                 0x7: (False, 32)}
# an object of each type in the project's DCF: (signed, bits) -> object
OF_TYPE = {
    (True, 8): ObjectKey(0x6060), (True, 16): ObjectKey(0x30D2, 1), (True, 32): ObjectKey(0x30B0),
    (False, 8): ObjectKey(0x1001), (False, 16): ObjectKey(0x30B2), (False, 32): ObjectKey(0x3001, 1),
}

PLANS = [("dcf", plan())] + [("compact " + ",".join(map(str, modes)), plan({"pdo_layout": "compact", "modes": modes}))
                             for modes, _, _ in CASES]


def value_sets(entries, rng):
    """Values for a map's entries: each type's extremes, 0, -1 and random ones."""
    ranges = []
    for key, bits in entries:
        signed, _ = INTEGER_TYPES[find_variable(OD, key).data_type]
        ranges.append((-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if signed else (0, (1 << bits) - 1))
    sets = [[lo for lo, _ in ranges], [hi for _, hi in ranges], [0] * len(ranges),
            [-1 if lo < 0 else hi for lo, hi in ranges]]
    sets += [[rng.randint(lo, hi) for lo, hi in ranges] for _ in range(50)]
    return sets


def canopen_map(pdo_node, plan_map):
    """python-canopen's map with the plan's entries, as write_with_canopen maps them."""
    m = pdo_node[plan_map.number]
    m.clear()
    for key, bits in plan_map.entries:
        m.add_variable(key.index, key.subindex, bits)
    assert [(v.index, v.subindex, v.length) for v in m.map] == [(k.index, k.subindex, b) for k, b in plan_map.entries]
    assert len(m.data) == plan_map.length
    return m


def check_rx(m, plan_map, rng):
    codec = RxPdo(OD, plan_map)
    for values in value_sets(plan_map.entries, rng):
        for var, v in zip(m.map, values):
            var.raw = v
        assert codec.pack(values) == bytes(m.data), (plan_map.entries, values)
        assert codec.pack_args(*values) == bytes(m.data)


def check_tx(m, plan_map, rng):
    codec = TxPdo(OD, plan_map)
    assert codec.length == plan_map.length
    for values in value_sets(plan_map.entries, rng):
        for var, v in zip(m.map, values):  # canopen encodes, the codec decodes
            var.raw = v
        data = bytes(m.data)
        assert codec.decode(data) == tuple(values) == codec.unpack(data)
        assert tuple(var.raw for var in m.map) == tuple(values)
    for _ in range(50):  # and any bytes at all decode alike
        data = bytes(rng.getrandbits(8) for _ in range(plan_map.length))
        m.data = bytearray(data)
        assert codec.decode(data) == tuple(var.raw for var in m.map)
    assert codec.decode(bytes(plan_map.length + 1)) is None  # a frame of another length is no reading


@pytest.mark.parametrize("name,p", PLANS, ids=[n for n, _ in PLANS])
def test_every_planned_map_encodes_and_decodes_as_canopen_does(name, p):
    rng = random.Random(name)
    node = canopen.RemoteNode(1, OD)
    rx, tx = enabled_maps(p.rx), enabled_maps(p.tx)
    assert rx and tx
    for plan_map in rx:
        check_rx(canopen_map(node.rpdo, plan_map), plan_map, rng)
    for plan_map in tx:
        check_tx(canopen_map(node.tpdo, plan_map), plan_map, rng)


def test_the_plans_map_only_whole_integer_objects():
    for _, p in PLANS:
        for plan_map in enabled_maps(p.rx) + enabled_maps(p.tx):
            for key, bits in plan_map.entries:
                assert INTEGER_TYPES[find_variable(OD, key).data_type][1] == bits, (key, bits)


@pytest.mark.parametrize("entries", [
    [OF_TYPE[(True, 8)], OF_TYPE[(False, 8)], OF_TYPE[(True, 16)], OF_TYPE[(False, 16)]],
    [OF_TYPE[(True, 32)], OF_TYPE[(False, 32)]],
    [OF_TYPE[(False, 16)], OF_TYPE[(True, 32)], OF_TYPE[(True, 8)]],
    [OF_TYPE[(False, 8)]] * 8,
], ids=["8-and-16-bit", "32-bit", "mixed", "eight-bytes"])
def test_every_integer_type_encodes_and_decodes_as_canopen_does(entries):
    for key in entries:  # the table names the types it claims
        signed, bits = INTEGER_TYPES[find_variable(OD, key).data_type]
        assert OF_TYPE[(signed, bits)] == key
    mapped = tuple((key, INTEGER_TYPES[find_variable(OD, key).data_type][1]) for key in entries)
    rng = random.Random(repr(entries))
    node = canopen.RemoteNode(1, OD)
    rx_map = MapPlan(1, 0x201, True, 1, None, False, mapped)
    tx_map = MapPlan(1, 0x181, True, 1, None, False, mapped)
    check_rx(canopen_map(node.rpdo, rx_map), rx_map, rng)
    check_tx(canopen_map(node.tpdo, tx_map), tx_map, rng)


@pytest.mark.parametrize("key,bits", [
    (ObjectKey(0x6040), 8), (ObjectKey(0x6040), 1), (ObjectKey(0x6060), 4), (ObjectKey(0x607A), 16),
    (ObjectKey(0x6060), 16),
])
def test_a_partial_or_wrong_width_entry_is_refused_not_packed(key, bits):
    """Entries not of their object's whole width (bit fields) are refused:
    the codec packs whole little-endian integers only."""
    m = MapPlan(1, 0x201, True, 1, None, False, ((key, bits),))
    with pytest.raises(PdoLayoutError):
        RxPdo(OD, m)
    with pytest.raises(PdoLayoutError):
        TxPdo(OD, m)

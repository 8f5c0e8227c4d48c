"""``readings_every: N`` (node layer, with ``pdo_layout: compact``): the
statusword and position every SYNC, the other readings in TxPDOs of
transmission type N (CiA 301); the age of each reading in the snapshot and
in diagnostics; the bus budget of that layout counted by hand."""
import math
import os
import struct

import canopen
import pytest

from maxon_epos4_ros_canopen.config import ConfigError, load_config
from maxon_epos4_ros_canopen.driver.axis import Axis, Binding
from maxon_epos4_ros_canopen.driver.budget import bus_budget, check_budget, main, plan_config, wire_bits
from maxon_epos4_ros_canopen.driver.pdo import RxPdo, TpdoReceiver, TxPdo, enabled_maps
from maxon_epos4_ros_canopen.driver.plan import (CONTROLWORD, POSITION_ACTUAL, STATUSWORD, TARGET_POSITION,
                                                 TARGET_TORQUE, TARGET_VELOCITY, VELOCITY_ACTUAL, plan_node)
from maxon_epos4_ros_canopen.limits import JointLimits
from maxon_epos4_ros_canopen.objects import ObjectKey, load_dictionary

HERE = os.path.dirname(os.path.abspath(__file__))
PKG = os.path.normpath(os.path.join(HERE, "..", ".."))
DCF1 = os.path.join(PKG, "config", "epos4_node1.dcf")
CW, SW, POS, VEL = CONTROLWORD, STATUSWORD, POSITION_ACTUAL, VELOCITY_ACTUAL
TP, TV, TT = TARGET_POSITION, TARGET_VELOCITY, TARGET_TORQUE
TORQUE_ACTUAL = ObjectKey(0x6077)


def config(node=None, sync=None, axes=1, heartbeat=False):
    defaults = {"eds_file": DCF1, "modes": ["CSP"], "pdo_layout": "compact", "readings_every": 5}
    defaults.update(node or {})
    params = {"sync": sync or {"interval_ms": 10}, "defaults": defaults,
              "nodes": [{"id": i, "name": "j%d" % i} for i in range(1, axes + 1)]}
    if heartbeat:
        params["heartbeat"] = {"rate": 20, "msg": "77f#05"}
    return load_config(params, "test")


def plan(node=None, sync=None):
    cfg = config(node, sync)
    n = cfg.nodes[0]
    return cfg, plan_node(n, load_dictionary(n.eds_file, n.node_id), cfg.sync, "test")


def frames(maps):
    return [([k for k, _ in m.entries], m.trans_type) for m in maps if m.enabled]


CASES = [
    ({"modes": [8]}, [([CW, TP], 1)], [([SW, POS], 1), ([VEL], 5)]),
    ({"modes": [9]}, [([CW, TV], 1)], [([SW, POS], 1), ([VEL], 5)]),
    ({"modes": [1, 3, 6, 8, 9, 10]}, [([CW, TP, TT], 1), ([TV], 1)], [([SW, POS], 1), ([VEL], 5)]),
    # the 16-bit torque would fit beside the statusword and position, but is a reading: it waits for the Nth SYNC
    ({"modes": [10], "eff_from_device": "obj6077"}, [([CW, TT], 1)], [([SW, POS], 1), ([VEL, TORQUE_ACTUAL], 5)]),
    ({"modes": [8], "vel_from_device": "0"}, [([CW, TP], 1)], [([SW, POS], 1)]),
    ({"modes": [8], "readings_every": 1}, [([CW, TP], 1)], [([SW, POS], 1), ([VEL], 1)]),
]


@pytest.mark.parametrize("node,rx,tx", CASES, ids=[str(i) for i in range(len(CASES))])
def test_statusword_and_position_every_sync_the_rest_every_nth(node, rx, tx):
    _, p = plan(node)
    assert (frames(p.rx), frames(p.tx)) == (rx, tx)
    for m in p.rx + p.tx:
        assert sum(bits for _, bits in m.entries) <= 64  # every frame at most 8 bytes
        assert m.event_timer is None


def test_planned_age_of_each_reading():
    cfg, p = plan()
    assert p.tx_period_ms(SW, cfg.sync) == 10 and p.tx_period_ms(POS, cfg.sync) == 10
    assert p.tx_period_ms(VEL, cfg.sync) == 50
    assert p.tx_period_ms(TORQUE_ACTUAL, cfg.sync) is None  # not mapped
    # without SYNC the drive's event timer paces the TxPDOs: N cycles for the readings
    cfg, p = plan(sync={"interval_ms": 0, "update_ms": 20})
    assert [(m.trans_type, m.event_timer) for m in p.tx if m.enabled] == [(255, 20), (255, 100)]
    assert p.tx_period_ms(VEL, cfg.sync) == 100 and p.tx_period_ms(POS, cfg.sync) == 20


@pytest.mark.parametrize("node,key,text", [
    ({"readings_every": 0}, "nodes[0]/readings_every", "out of range"),
    ({"readings_every": 241}, "nodes[0]/readings_every", "out of range"),
    ({"readings_every": "5"}, "nodes[0]/readings_every", "expected an integer"),
    ({"pdo_layout": "dcf"}, "nodes[0]/readings_every", "needs pdo_layout: compact"),
])
def test_bad_readings_every_names_the_key(node, key, text):
    with pytest.raises(ConfigError) as e:
        config(node)
    assert e.value.key == key and text in e.value.problem


def test_budget_by_hand_for_readings_every_5():
    cfg = config(axes=2, heartbeat=True)
    b = bus_budget(cfg, plan_config(cfg))
    # RxPDO1 6 bytes every SYNC (115 bits), TxPDO1 6 bytes every SYNC (115),
    # TxPDO2 4 bytes every 5th SYNC (95 / 5 = 19)
    assert (wire_bits(6), wire_bits(4)) == (115, 95)
    for a in b.axes:
        assert [(f.name, f.data_bytes, f.per_sync) for f in a.frames] == [
            ("RxPDO1", 6, 1.0), ("TxPDO1", 6, 1.0), ("TxPDO2", 4, 0.2)]
        assert a.bits_per_sync == pytest.approx(249)
        assert a.pdo_frames_per_sync == pytest.approx(2.2)
    # SYNC 55 bits, master heartbeat 0.2 x 65 = 13
    assert b.bits_per_sync == pytest.approx(2 * 249 + 68)
    assert b.max_axes(1.0) == 39      # (10000 - 68) / 249 = 39.9
    assert b.max_axes(0.8) == 31      # (8000 - 68) / 249 = 31.9
    # every 6th SYNC: 95 / 6 = 15.8 bits, 245.8 per axis
    cfg = config({"readings_every": 6}, axes=2, heartbeat=True)
    b = bus_budget(cfg, plan_config(cfg))
    assert b.axes[0].bits_per_sync == pytest.approx(230 + 95 / 6)
    assert (b.max_axes(0.8), b.max_axes(1.0)) == (32, 40)


def test_warning_counts_transmission_types():
    cfg = config(axes=33)           # 33 x 249 + 55 = 8272 bits in 10 ms
    warning = check_budget(cfg, plan_config(cfg))
    assert warning and "83 %" in warning and "at most 31" in warning and "readings_every" in warning
    cfg = config(axes=31)           # 7774 bits
    assert check_budget(cfg, plan_config(cfg)) is None
    cfg = config({"readings_every": 1}, axes=31)   # 31 x 325 + 55 = 10130 bits
    assert "101 %" in check_budget(cfg, plan_config(cfg))


def test_tool_prints_the_40_axis_budget(tmp_path, capsys):
    layer = tmp_path / "node_layer_40.yaml"
    lines = ["nodes:"] + ["  - {id: %d, name: joint%d}" % (i, i) for i in range(1, 41)]
    lines += ["defaults:", "  eds_file: %s" % DCF1, "  modes: [CSP]", "  pdo_layout: compact",
              "  readings_every: 6"]
    layer.write_text("\n".join(lines) + "\n")
    bus = os.path.join(PKG, "config", "canopen_bus_layer.yaml")
    assert main([bus, str(layer)], resolver=lambda pkg: PKG) == 1   # over 80 %
    out = capsys.readouterr().out
    assert out.count(" compact  CSP") == 40
    assert "  joint1: RxPDO1 6 B every period, TxPDO1 6 B every period, TxPDO2 4 B every 6 periods" in out
    # 40 x (230 + 95/6) + 55 + 13 = 9901 bits in 10 ms
    assert "load 99.0 %" in out and "at most 32 under 80 % load, 40 at 100 %" in out
    assert "PDO frames per axis per period: 2.17 on average" in out
    assert "WARNING: CAN bus budget: 99 %" in out


class AgeHarness:
    """One CSP axis with readings_every 5 fed frames on a stepped clock."""

    def __init__(self):
        cfg, p = plan({"pos_from_device": "obj6064", "vel_from_device": "obj606C"})
        od = canopen.import_od(DCF1, 1)
        rx = tuple(RxPdo(od, m) for m in enabled_maps(p.rx))
        tx = tuple(TxPdo(od, m) for m in enabled_maps(p.tx))
        self.axis = Axis(cfg.nodes[0], od, p, JointLimits())
        self.axis.attach(Binding(rx, tx, {k: 0 for r in rx for k in r.keys}, {}, 0, 0, 0.0), 0, 0.0)
        self.t = 0.0
        self.receiver = TpdoReceiver({t.cob_id: t.length for t in tx}, lambda: (self.t, self.t))

    def sync(self, n, velocity):
        """SYNC number n at n x 10 ms: TxPDO1 every time, TxPDO2 every 5th;
        the cycle reads 3 ms after the SYNC."""
        self.t = n * 0.010 + 0.001
        self.receiver.on_frame(0x181, struct.pack("<Hi", 0x0637, 100 * n), 0.0)
        if n % 5 == 0:
            self.receiver.on_frame(0x281, struct.pack("<i", velocity), 0.0)
        self.axis.read(self.receiver, n * 0.010 + 0.003, n)
        return self.axis.snapshot()


def test_snapshot_carries_the_age_of_each_reading():
    h = AgeHarness()
    snap = h.sync(1, 7)
    assert snap.tpdo_keys == ((SW, POS), (VEL,))
    ages = snap.reading_ages
    assert ages[POS] == pytest.approx(0.002) and ages[SW] == pytest.approx(0.002)
    assert VEL not in ages and math.isnan(snap.velocity)   # no velocity yet: unknown, not zero
    assert snap.describe_ages() == "6041,6064: 2; 606C: -"
    for n in range(2, 16):
        snap = h.sync(n, 10 * n)
        assert snap.raw_position == 100 * n and snap.reading_ages[POS] == pytest.approx(0.002)
        since = n % 5                                     # SYNCs since the last velocity frame
        if n >= 5:
            assert snap.reading_ages[VEL] == pytest.approx(0.002 + 0.010 * since)
            assert snap.readings[VEL] == 10 * (n - since)  # the value the age belongs to
    snap = h.sync(19, 0)
    assert snap.describe_ages() == "6041,6064: 2; 606C: 42"
    assert snap.motion_age() == pytest.approx(0.042)  # the older of position and velocity


def test_motion_age_is_unknown_until_position_and_velocity_arrived():
    h = AgeHarness()
    assert math.isnan(h.sync(1, 7).motion_age())    # no velocity frame yet
    for n in range(2, 6):
        snap = h.sync(n, 10 * n)
    assert snap.motion_age() == pytest.approx(0.002)  # both arrived this SYNC


def test_csp_example_on_the_bus_and_in_diagnostics():
    """The shipped CSP example against two virtual EPOS4: per drive, TxPDO1
    (statusword, position) after every SYNC, TxPDO2 (velocity) after every
    5th; the diagnostics name each TxPDO's age."""
    import re
    from csp_rig import CspRig, wait
    rig = CspRig()
    try:
        rig.start()
        rig.listener.take()
        assert wait(lambda: sum(f.arbitration_id == 0x80 for f in rig.listener.frames) >= 52, 30.0)
        frames = rig.listener.take()
        for node_id in (1, 2):
            # the drive answers each SYNC with TxPDO1, then TxPDO2 when due, in
            # that order: between two velocity frames, exactly 5 of TxPDO1
            ids = [f.arbitration_id for f in frames if f.arbitration_id in (0x180 + node_id, 0x280 + node_id)]
            at = [i for i, cob in enumerate(ids) if cob == 0x280 + node_id]
            assert len(at) >= 8
            assert {b - a - 1 for a, b in zip(at, at[1:])} == {5}
            assert all(len(f.data) == 4 for f in frames if f.arbitration_id == 0x280 + node_id)
            assert all(len(f.data) == 6 for f in frames if f.arbitration_id == 0x180 + node_id)
        for status in rig.driver.status():
            assert re.match(r"^6041,6064: \d+; 606C: \d+$", status["reading_age_ms"]), status["reading_age_ms"]
    finally:
        rig.close()

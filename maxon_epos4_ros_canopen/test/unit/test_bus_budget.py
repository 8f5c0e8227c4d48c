"""The bus budget against frames counted by hand (worst-case stuffed CAN
2.0A lengths: 8n + 44 + floor((34 + 8n - 1) / 4), plus 3 bits intermission)."""
import os

import pytest

from maxon_epos4_ros_canopen.driver.budget import (bus_budget, check_budget, frame_bits, main, plan_config,
                                                wire_bits)
from maxon_epos4_ros_canopen.config import load_config

HERE = os.path.dirname(os.path.abspath(__file__))
PKG = os.path.normpath(os.path.join(HERE, "..", ".."))
DCF1 = os.path.join(PKG, "config", "epos4_node1.dcf")


def config(axes=2, layout=None, sync=None, heartbeat=True, node=None):
    defaults = {"eds_file": DCF1, "modes": ["CSP"]}
    if layout:
        defaults["pdo_layout"] = layout
    defaults.update(node or {})
    params = {"sync": sync or {"interval_ms": 10},
              "nodes": [{"id": i, "name": "j%d" % i} for i in range(1, axes + 1)], "defaults": defaults}
    if heartbeat:
        params["heartbeat"] = {"rate": 20, "msg": "77f#05"}
    return load_config(params, "test")


def test_frame_lengths_by_hand():
    # n = 0: 44 + floor(33/4) = 52; n = 8: 64 + 44 + floor(97/4) = 132
    assert [frame_bits(n) for n in (0, 1, 3, 4, 6, 8)] == [52, 62, 82, 92, 112, 132]
    assert wire_bits(8) == 135
    with pytest.raises(ValueError):
        frame_bits(9)


def test_compact_csp_two_axes():
    cfg = config(layout="compact")
    b = bus_budget(cfg, plan_config(cfg))
    # per axis: RxPDO1 6 bytes (115), TxPDO1 6 bytes (115), TxPDO2 4 bytes (95)
    for a in b.axes:
        assert [(f.name, f.data_bytes, f.per_sync) for f in a.frames] == [
            ("RxPDO1", 6, 1.0), ("TxPDO1", 6, 1.0), ("TxPDO2", 4, 1.0)]
        assert a.bits_per_sync == 325
    # SYNC without counter (55) and the master's heartbeat, 1 byte at 20 Hz: 0.2 x 65 = 13
    assert [(f.name, f.data_bytes) for f in b.shared] == [("SYNC", 0), ("master heartbeat", 1)]
    assert b.bits_per_sync == pytest.approx(2 * 325 + 55 + 13)
    assert b.frames_per_sync == pytest.approx(2 * 3 + 1.2)
    assert b.load == pytest.approx(718 / 10000)
    assert b.max_axes(1.0) == 30       # (10000 - 68) / 325 = 30.6
    assert b.max_axes(0.8) == 24       # (8000 - 68) / 325 = 24.4


def test_dcf_layout_csp_by_hand():
    cfg = config(axes=1)
    b = bus_budget(cfg, plan_config(cfg))
    a = b.axes[0]
    # RxPDO1 (6040, 60FF) and RxPDO2 (607A, 6081) every cycle; RxPDO3 (6083, 6084)
    # and RxPDO4 (6071, 6060) on change, refreshed every 50 cycles; TxPDO1-3 every SYNC
    assert [(f.name, f.data_bytes, f.per_sync) for f in a.frames] == [
        ("RxPDO1", 6, 1.0), ("RxPDO2", 8, 1.0), ("RxPDO3", 8, 0.02), ("RxPDO4", 3, 0.02),
        ("TxPDO1", 3, 1.0), ("TxPDO2", 8, 1.0), ("TxPDO3", 8, 1.0)]
    assert a.bits_per_sync == pytest.approx(115 + 135 + 2.7 + 1.7 + 85 + 135 + 135)
    assert a.pdo_frames_per_sync == pytest.approx(5.04)
    assert b.max_axes(1.0) == 16       # (10000 - 68) / 609.4


def test_counter_drive_heartbeat_and_period():
    cfg = config(axes=1, layout="compact", sync={"interval_ms": 5, "overflow": 16},
                 node={"dcf_overlay": {"1017": "100"}}, heartbeat=False)
    b = bus_budget(cfg, plan_config(cfg), bitrate=500000)
    assert [(f.name, f.data_bytes, f.bits) for f in b.shared] == [("SYNC", 1, 65)]
    hb = [f for f in b.axes[0].frames if f.name == "heartbeat"][0]
    assert (hb.cob_id, hb.data_bytes, hb.per_sync) == (0x701, 1, pytest.approx(0.05))
    assert b.bits_per_sync == pytest.approx(65 + 325 + 0.05 * 65)
    assert b.load == pytest.approx(b.bits_per_sync / 2500)


def test_without_sync_pdos_follow_the_cycle():
    cfg = config(axes=1, layout="compact", sync={"interval_ms": 0, "update_ms": 20}, heartbeat=False)
    b = bus_budget(cfg, plan_config(cfg))
    assert b.shared == () and b.period_s == 0.02
    assert [f.per_sync for f in b.axes[0].frames] == [1.0, 1.0, 1.0]


def test_check_budget_warns_over_80_percent():
    cfg = config(axes=16)          # DCF layout: 16 x 609 bits in 10 ms, 98 %
    warning = check_budget(cfg, plan_config(cfg))
    assert warning and "98 %" in warning and "at most 13" in warning
    cfg = config(axes=12)          # 74 %
    assert check_budget(cfg, plan_config(cfg)) is None
    cfg = config(axes=16, layout="compact")
    assert check_budget(cfg, plan_config(cfg)) is None
    assert check_budget(cfg, plan_config(cfg), bitrate=500000) is not None
    # plans in the order of the nodes work as well as by name
    assert check_budget(cfg, list(plan_config(cfg).values()), bitrate=500000) is not None


def test_tool_prints_the_budget_of_the_shipped_layers(capsys):
    layers = [os.path.join(PKG, "config", f) for f in
              ("canopen_bus_layer.yaml", "node_layer_2dof_csp.yaml", "controller_2dof_csp.yaml")]
    assert main(layers, resolver=lambda pkg: PKG) == 0
    out = capsys.readouterr().out
    # the CSP example's compact layout with the velocity every 5th SYNC:
    # 2 x (115 + 115 + 95 / 5) bits + SYNC 55 + heartbeat 13 in 10 ms
    assert "base_link1_joint          1 compact  CSP                 2.20" in out
    assert "load 5.7 %" in out and "at most 31 under 80 % load, 39 at 100 %" in out
    assert main(layers + ["--bitrate", "60000"], resolver=lambda pkg: PKG) == 1
    assert "WARNING: CAN bus budget" in capsys.readouterr().out
    assert main([os.path.join(PKG, "config", "no_such.yaml")]) == 2

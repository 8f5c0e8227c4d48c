"""Operation modes of the virtual EPOS4, driven over SDO/PDO by a canopen client."""
import struct

import pytest

from sim_support import NODE1, NODE1_HM, NodeConfig, enable


@pytest.fixture
def rig(sim_rig):
    return sim_rig([NodeConfig(1, NODE1)])


def sw(node):
    return node.sdo[0x6041].raw


def test_ppm_needs_new_set_point_edge(rig):
    node = rig.remote(1)
    enable(node, 1)
    start = node.sdo[0x6064].raw
    assert sw(node) & 0x0400  # idle: target reached
    node.sdo[0x607A].raw = start + 2000
    rig.handled(0.3)
    assert abs(node.sdo[0x6064].raw - start) < 5  # no edge, no motion
    node.sdo[0x6040].raw = 0x001F
    assert sw(node) & 0x1400 == 0x1000  # acknowledged, not reached
    node.sdo[0x6040].raw = 0x000F
    assert sw(node) & 0x1000 == 0
    assert rig.wait(lambda: sw(node) & 0x0400)
    assert abs(node.sdo[0x6064].raw - (start + 2000)) <= 100  # position window
    assert node.sdo[0x6062].raw == start + 2000


def test_ppm_relative_and_change_immediately(rig):
    node = rig.remote(1)
    enable(node, 1)
    start = node.sdo[0x6064].raw
    node.sdo[0x6081].raw = 300
    node.sdo[0x607A].raw = 6000
    node.sdo[0x6040].raw = 0x005F  # relative
    node.sdo[0x6040].raw = 0x004F
    assert rig.wait(lambda: node.sdo[0x606C].raw > 100)
    node.sdo[0x607A].raw = start - 1000
    node.sdo[0x6040].raw = 0x003F  # absolute, change set immediately
    node.sdo[0x6040].raw = 0x000F
    assert rig.wait(lambda: sw(node) & 0x0400, timeout=15)
    assert node.sdo[0x6062].raw == start - 1000


def test_ppm_profile_is_trapezoidal(rig):
    node = rig.remote(1)
    enable(node, 1)
    node.sdo[0x6081].raw = 600
    node.sdo[0x6083].raw = 2000
    node.sdo[0x607A].raw = node.sdo[0x6064].raw + 20000
    node.sdo[0x6040].raw = 0x001F
    node.sdo[0x6040].raw = 0x000F
    demands = []
    rig.wait(lambda: demands.append(node.sdo[0x606B].raw) or sw(node) & 0x0400)
    assert max(demands) == 600  # cruise at profile velocity
    assert any(0 < d < 600 for d in demands)  # ramps, not steps


def test_ppm_halt_stops_and_reports_target_reached(rig):
    node = rig.remote(1)
    enable(node, 1)
    node.sdo[0x607A].raw = node.sdo[0x6064].raw + 7000
    node.sdo[0x6040].raw = 0x001F
    node.sdo[0x6040].raw = 0x000F
    assert rig.wait(lambda: node.sdo[0x606C].raw > 200)
    node.sdo[0x6040].raw = 0x010F
    assert rig.wait(lambda: sw(node) & 0x0400)
    assert node.sdo[0x606B].raw == 0
    stopped_at = node.sdo[0x6062].raw
    target = node.sdo[0x607A].raw
    assert stopped_at < target
    node.sdo[0x6040].raw = 0x000F  # release halt: the move goes on
    assert rig.wait(lambda: node.sdo[0x6062].raw > stopped_at)
    assert rig.wait(lambda: sw(node) & 0x0400 and node.sdo[0x6062].raw == target)


def test_software_position_limit_clamps_target(rig):
    node = rig.remote(1)
    node.sdo[0x607D][1].raw = -1000
    node.sdo[0x607D][2].raw = 1500
    enable(node, 1)
    node.sdo[0x607A].raw = 5000
    node.sdo[0x6040].raw = 0x001F
    assert sw(node) & 0x0800  # internal limit active
    node.sdo[0x6040].raw = 0x000F
    assert rig.wait(lambda: sw(node) & 0x0400)
    assert node.sdo[0x6062].raw == 1500


def test_pvm_reaches_velocity_and_speed_bit(rig):
    node = rig.remote(1)
    enable(node, 3)
    assert sw(node) & 0x1000  # speed = 0
    node.sdo[0x60FF].raw = -500
    assert rig.wait(lambda: abs(node.sdo[0x606C].raw + 500) <= 5)
    assert rig.wait(lambda: sw(node) & 0x0400)
    assert abs(node.sdo[0x30D1][1].raw) > 0  # friction current
    assert sw(node) & 0x1000 == 0
    node.sdo[0x6040].raw = 0x010F  # halt
    assert rig.wait(lambda: abs(node.sdo[0x606C].raw) <= 10)


def test_velocity_changes_over_time_not_instantly(rig):
    node = rig.remote(1)
    enable(node, 3)
    node.sdo[0x6083].raw = 1000
    node.sdo[0x60FF].raw = 1000
    first = node.sdo[0x606C].raw
    assert first < 500
    assert rig.wait(lambda: node.sdo[0x606C].raw > 900)


def test_homing_37_sets_home_position(rig):
    node = rig.remote(1)
    node.sdo[0x6098].raw = 37  # the project's DCFs ship 0: no homing required
    node.sdo[0x30B0].raw = 1234
    enable(node, 6)
    node.sdo[0x6040].raw = 0x001F
    assert rig.wait(lambda: sw(node) & 0x9400 == 0x9400)  # referenced, target reached
    assert sw(node) & 0x1000  # homing attained
    assert node.sdo[0x6064].raw == 1234


def test_homing_unsupported_method_reports_error(rig):
    node = rig.remote(1)
    node.sdo[0x6098].raw = 1
    enable(node, 6)
    node.sdo[0x6040].raw = 0x001F
    assert rig.wait(lambda: sw(node) & 0x2000)


def test_homing_minus3_current_threshold_against_hard_stop(sim_rig):
    r = sim_rig([NodeConfig(1, NODE1_HM, hard_stop=(-5000.0, 1600.0))])
    try:
        node = r.remote(1, NODE1_HM)
        assert node.sdo[0x6098].raw == -3
        enable(node, 6)
        node.sdo[0x6040].raw = 0x001F
        assert r.wait(lambda: sw(node) & 0x1000, timeout=20)
        assert node.sdo[0x30B0].raw == 0
        assert abs(node.sdo[0x6064].raw) <= 2
        assert sw(node) & 0x8000
        # home offset move distance: standing 0x30B1 increments below the stop
        node.sdo[0x6060].raw = 1
        node.sdo[0x607A].raw = 800
        node.sdo[0x6040].raw = 0x003F  # bit 4 still high from homing: no edge, no move
        r.handled(0.2)
        assert node.sdo[0x6062].raw == 0
        node.sdo[0x6040].raw = 0x000F
        node.sdo[0x6040].raw = 0x003F
        node.sdo[0x6040].raw = 0x000F
        assert r.wait(lambda: sw(node) & 0x0400 and node.sdo[0x6062].raw == 800)
        # a move beyond the stop stalls: following error fault 0x8611
        node.sdo[0x607A].raw = 1500
        node.sdo[0x6065].raw = 200
        node.sdo[0x6040].raw = 0x003F
        assert r.wait(lambda: sw(node) & 0x6F == 0x08, timeout=15)
        assert node.sdo[0x603F].raw == 0x8611
    finally:
        r.close()


def test_csp_follows_target_each_sync_with_interpolation(rig):
    node = rig.remote(1)
    enable(node, 8)
    assert sw(node) & 0x1000  # drive follows the command value
    start = node.sdo[0x6064].raw
    node.sdo[0x1400][1].raw = 0x80000201
    rig.send(0x000, bytes([0x01, 1]))
    target = start
    for _ in range(60):  # 600 ms ramp at 10 ms SYNC: 20 inc per cycle
        target += 20
        rig.send(0x301, struct.pack("<iI", target, 1000))
        rig.send(0x080)
        rig.collect(0.01)
    assert rig.wait(lambda: node.sdo[0x6062].raw == target and abs(node.sdo[0x6064].raw - target) < 30)


def test_csp_target_without_sync_is_not_applied(rig):
    node = rig.remote(1)
    enable(node, 8)
    start = node.sdo[0x6064].raw
    node.sdo[0x607A].raw = start + 500
    rig.handled(0.2)
    assert node.sdo[0x6062].raw == start


def test_csv_and_cst(rig):
    node = rig.remote(1)
    enable(node, 9)
    node.sdo[0x1400][1].raw = 0x80000201  # keep RxPDO1 from writing 0x60FF
    rig.send(0x000, bytes([0x01, 1]))
    node.sdo[0x60FF].raw = 300
    assert rig.wait(lambda: abs(node.sdo[0x606C].raw - 300) <= 5)
    node.sdo[0x6071].raw = 0
    node.sdo[0x6060].raw = 10
    assert node.sdo[0x6061].raw == 10
    node.sdo[0x6071].raw = 100  # 10 % of rated torque accelerates the free rotor
    assert rig.wait(lambda: node.sdo[0x606C].raw > 1000)
    assert 80 <= node.sdo[0x6077].raw <= 100


def test_quick_stop_decelerates_with_0x6085(rig):
    node = rig.remote(1)
    enable(node, 3)
    node.sdo[0x60FF].raw = 1000
    assert rig.wait(lambda: node.sdo[0x606C].raw > 950)
    node.sdo[0x6085].raw = 2000  # 1000 rpm -> 0 in 0.5 s
    node.sdo[0x6040].raw = 0x000B
    assert sw(node) & 0x6F == 0x07
    speeds = []
    assert rig.wait(lambda: speeds.append(node.sdo[0x606C].raw) or sw(node) & 0x0400)  # done
    assert any(200 < v < 800 for v in speeds)  # a ramp, not a jump to zero
    assert sw(node) & 0x6F == 0x07


def test_max_profile_velocity_limits_ppm(rig):
    node = rig.remote(1)
    node.sdo[0x607F].raw = 400
    node.sdo[0x6081].raw = 900
    enable(node, 1)
    node.sdo[0x607A].raw = node.sdo[0x6064].raw + 15000
    node.sdo[0x6040].raw = 0x001F
    node.sdo[0x6040].raw = 0x000F
    demands = []
    assert rig.wait(lambda: demands.append((node.sdo[0x606B].raw, sw(node))) or sw(node) & 0x0400, timeout=20)
    assert max(d for d, _ in demands) == 400
    assert any(s & 0x0800 for _, s in demands)  # internal limit active while limited


def test_homing_minus4_needs_the_current_threshold(sim_rig):
    r = sim_rig([NodeConfig(1, NODE1_HM, hard_stop=(-1500.0, 5000.0))])
    try:
        node = r.remote(1, NODE1_HM)
        node.sdo[0x6098].raw = -4  # negative direction
        node.sdo[0x30B2].raw = 30000  # above the 9520 mA current limit: never reached
        enable(node, 6)
        node.sdo[0x6040].raw = 0x001F
        # pressed against the stop at the current limit
        assert r.wait(lambda: node.sdo[0x6064].raw <= -1499 and abs(node.sdo[0x30D1][1].raw) >= 9000)
        r.handled(0.5)
        assert sw(node) & 0x1000 == 0  # still searching: not attained
        node.sdo[0x30B2].raw = 1500
        assert r.wait(lambda: sw(node) & 0x1000)
        assert abs(node.sdo[0x6064].raw) <= 2  # home position 0 after backing off 0x30B1
    finally:
        r.close()

"""Helpers for the driver tests (no tests here): the DCFs and joints of the
rig, its timeouts, and a PPM-ready driver. The rig itself (simulator,
driver and a frame recorder on one virtual channel, on a stepped clock
unless a test proves real-time threading) is conftest.py's DriverRig."""
import os

HERE = os.path.dirname(os.path.abspath(__file__))
PKG = os.path.normpath(os.path.join(HERE, "..", ".."))
REPO = os.path.dirname(PKG)
DCF1 = os.path.join(PKG, "config", "epos4_node1.dcf")
DCF1_HM = os.path.join(PKG, "config", "epos4_node1_hm.dcf")
DCF2 = os.path.join(PKG, "config", "epos4_node2.dcf")
VENDOR = os.path.join(os.path.dirname(REPO), "shared", "vendor_dcf")
J1, J2 = "base_link1_joint", "link1_link2_joint"
SEED_UNITS = {"pos_to_device": "pos", "pos_from_device": "obj6064", "vel_to_device": "vel",
              "vel_from_device": "obj606C", "eff_to_device": "rint(eff)", "eff_from_device": "0"}


# The rig's drives watch the master's heartbeat (node 0x7F) for 2000 ms, not
# the 150 ms init derives from the rig's 20 Hz heartbeat: a busy process on
# a loaded host can hold the heartbeat thread (python-can's, on the virtual
# bus) from the GIL longer than 150 ms, and the drive would then rightly
# stop. A test of master loss asks for the derived one (master_consumer=None).
GENEROUS_MASTER_CONSUMER = {"1016sub1": "0x007F07D0"}


SYNC_MS = 10  # the rig's SYNC period (and cycle)
# How long a wait for a condition may take before the test fails: generous,
# it only bounds how long a failure takes on a loaded host.
TIMEOUT = 5.0
# A check that something did NOT happen first lets the driver and the drive
# have this many cycles (SYNC periods) to do it (Rig.had_the_chance).
CHANCE_CYCLES = 20
# Long enough for an RxPDO that did not change to be sent again (every
# REFRESH_CYCLES = 50 cycles of 10 ms), with room for a loaded host.
REFRESH_WAIT = 10.0


def ppm_ready(rig, **kw):
    d = rig.start(**kw)
    r = d.init()
    assert r.success, r.message
    assert d.switch_mode([J1], 1).success
    return d


def moving_in(rig, mode: int, command: str, value: float, actual: int, **kw):
    """A started driver, its drive in ``mode`` at ``value`` (``command``:
    "position" or "velocity"), once the drive's ``actual`` object (0x6064,
    0x606C) is within 20 of it."""
    d = rig.start(**kw)
    assert d.init().success
    assert d.switch_mode([J1], mode).success
    assert d.set_command(J1, command, value).success
    assert rig.until(lambda: abs(rig.read(actual) - value) < 20)
    return d

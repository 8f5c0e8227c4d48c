"""The same stepped scenario, run twice, puts the same frames on the bus at
the same virtual times: byte-identical frame logs. (No thread decides
anything in a stepped run; a difference here is a defect of the clock or
of something that still reads real time.)"""
import can

from driver_support import DCF1, DCF2, J1, J2
from sim_support import NODE1, NODE2, NodeConfig, enable


def _simulator_scenario(sim_rig) -> bytes:
    rig = sim_rig([NodeConfig(1, NODE1), NodeConfig(2, NODE2)])
    node1, node2 = rig.remote(1), rig.remote(2, NODE2)
    rig.send(0x000, bytes([0x01, 0]))  # start every node: PDOs flow
    sync = rig.send_periodic(can.Message(arbitration_id=0x080, data=b"", is_extended_id=False), 0.01)
    enable(node1, 1)  # PPM
    node1.sdo[0x607A].raw = 20000
    node1.sdo[0x6040].raw = 0x003F  # new set-point, change immediately
    enable(node2, 3)  # PVM
    node2.sdo[0x60FF].raw = 800
    assert rig.wait(lambda: node1.sdo[0x6041].raw & 0x0400, timeout=30.0)  # target reached
    rig.sim.inject_fault(2, "emcy", error_code=0x8611)
    rig.collect(0.2)
    sync.stop()
    rig.collect(0.05)
    text = rig.recorder.text()
    assert text.count(b" 181 ") > 50 and b" 082 " in text  # TPDOs at SYNCs, the EMCY: it ran
    return text


def test_a_simulator_scenario_gives_the_same_frames_twice(sim_rig):
    first = _simulator_scenario(sim_rig)
    second = _simulator_scenario(sim_rig)
    assert first == second


def _driver_scenario(rig) -> bytes:
    d = rig.start(nodes=((1, DCF1, J1), (2, DCF2, J2)))
    assert d.init().success
    assert d.switch_mode([J1], 1).success and d.switch_mode([J2], 3).success
    assert d.set_command(J1, "position", 30000).success
    assert d.set_command(J2, "velocity", 600.0).success
    assert rig.until(lambda: abs(rig.read(0x6064) - 30000) < 20, 30.0)
    assert d.set_object(J1, "6083", "12345").success
    assert d.get_object(J2, "6041").success
    assert d.halt().success
    assert d.recover().success
    rig.sim.inject_fault(2, "emcy", error_code=0x8611)
    assert rig.until(lambda: d.joints[J2].error is not None)
    assert d.recover().success
    assert d.shutdown().success
    text = rig.recorder.text()
    assert text.count(b" 080 ") > 100 and b" 082 " in text  # SYNCs, the EMCY: the scenario ran
    return text


def test_a_driver_scenario_gives_the_same_frames_twice(make_driver_rig):
    first = _driver_scenario(make_driver_rig())
    second = _driver_scenario(make_driver_rig())
    assert first == second

"""The driver's watchdog of a drive's heartbeat (0x1017), judged by when
the heartbeats arrived: driver/inputs.py, without a bus or a thread."""
from maxon_epos4_ros_canopen.driver.inputs import Inputs
from maxon_epos4_ros_canopen.driver.snapshot import Counters

HEARTBEAT_MS = 200
PERIOD = 0.010
LIMIT = 1.5 * HEARTBEAT_MS / 1000.0 + 2 * PERIOD  # 320 ms
OPERATIONAL = b"\x05"


def watched() -> Inputs:
    inputs = Inputs("j1", 1, Counters())
    inputs.set_heartbeat(HEARTBEAT_MS, 0.95)  # its first heartbeat comes at 1.0
    return inputs


def silence(inputs: Inputs, now: float, read_at: float, arrived: float):
    """What the cycle at ``now`` says, the latest frame read at ``read_at``
    having arrived at ``arrived``; statusword TxPDOs keep coming."""
    inputs.status_seen, inputs.status_seen_cycle = now, 1000
    return inputs.silence(now, 1000, PERIOD, 1.0, 100, (read_at, arrived))


def test_a_silence_longer_than_the_heartbeat_time_is_lost_though_the_next_heartbeat_was_read_first():
    """A notifier behind reads the heartbeat that ended a 417 ms silence
    before any frame that came after the silence began: the silence is on
    the record (the arrival stamps) all the same."""
    inputs = watched()
    inputs.on_heartbeat(OPERATIONAL, 1.000, ready=True)
    inputs.on_heartbeat(OPERATIONAL, 1.417, ready=True)
    problem = silence(inputs, now=1.600, read_at=1.599, arrived=1.417)
    assert problem is not None and problem.startswith("heartbeat lost"), problem
    assert "417 ms" in problem, problem


def test_heartbeats_read_late_but_regular_are_no_silence():
    inputs = watched()
    for k in range(10):
        inputs.on_heartbeat(OPERATIONAL, 1.0 + k * 0.2, ready=True)
    # read a second late: the gaps on the record are 200 ms
    assert silence(inputs, now=3.0, read_at=2.999, arrived=2.8) is None


def test_a_restart_of_the_watchdog_forgets_a_silence_before_it():
    """recover restarts the watchdogs: the silence it recovered from is not
    reported again."""
    inputs = watched()
    inputs.on_heartbeat(OPERATIONAL, 1.000, ready=True)
    inputs.on_heartbeat(OPERATIONAL, 1.500, ready=True)
    assert silence(inputs, now=1.51, read_at=1.505, arrived=1.5) is not None
    inputs.restart(2.0)
    inputs.on_heartbeat(OPERATIONAL, 2.1, ready=True)
    assert silence(inputs, now=2.2, read_at=2.19, arrived=2.1) is None


def test_a_silence_within_the_limit_is_no_loss():
    inputs = watched()
    inputs.on_heartbeat(OPERATIONAL, 1.000, ready=True)
    inputs.on_heartbeat(OPERATIONAL, 1.000 + LIMIT - 0.005, ready=True)
    assert silence(inputs, now=1.4, read_at=1.39, arrived=1.3) is None

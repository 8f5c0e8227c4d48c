"""A virtual EPOS4 on simulated time for the simulator's unit tests: no
bus, no thread; the test advances time by whole steps and commands the
drive with the SDO frames a master sends."""
import struct
from typing import List

from maxon_epos4_ros_canopen.sim.drive import VirtualEpos4
from maxon_epos4_ros_canopen.sim.objects import load_od


class SteppedNode:
    """One virtual EPOS4 fed SDO frames, advanced by whole steps."""

    def __init__(self, dcf: str, step: float = 0.005, hard_stop=None):
        self.step_s = step
        self.now = 0.0
        self.answers: List[bytes] = []
        self.frames: List[tuple] = []  # (cob_id, data) of everything the node sent
        self.node = VirtualEpos4(1, load_od(dcf, 1), self._transport, self.now, hard_stop=hard_stop)

    def _transport(self, cob_id: int, data: bytes, remote: bool) -> None:
        self.frames.append((cob_id, bytes(data)))
        if cob_id == 0x581:
            self.answers.append(bytes(data))

    def read(self, index: int, sub: int = 0):
        """Expedited SDO upload, as a master sends it; the decoded value."""
        self.answers.clear()
        self.node.on_frame(0x601, struct.pack("<BHB4x", 0x40, index, sub), False, self.now)
        assert self.answers and self.answers[-1][0] & 0xE0 == 0x40, \
            "0x%04X:%d not read: %s" % (index, sub, self.answers)
        answer = self.answers[-1]
        size = 4 - ((answer[0] >> 2) & 3) if answer[0] & 0x01 else 4
        return self.node.store.variable(index, sub).decode_raw(answer[4:4 + size])

    def write(self, index: int, sub: int, value: int) -> None:
        """Expedited SDO download, as a master sends it; the answer must not be an abort."""
        raw = self.node.store.variable(index, sub).encode_raw(value)
        command = 0x23 | ((4 - len(raw)) << 2)
        request = struct.pack("<BHB", command, index, sub) + raw.ljust(4, b"\x00")
        self.answers.clear()
        self.node.on_frame(0x601, request, False, self.now)
        assert self.answers and self.answers[-1][0] == 0x60, \
            "0x%04X:%d = %d refused: %s" % (index, sub, value, self.answers)

    def tick(self, count: int = 1) -> None:
        for _ in range(count):
            self.now += self.step_s
            self.node.tick(self.now)

    def run_until(self, condition, seconds: float = 10.0) -> bool:
        """Step until ``condition()`` holds (True) or ``seconds`` of simulated time pass (False)."""
        end = self.now + seconds
        while self.now < end:
            if condition():
                return True
            self.tick()
        return condition()

    @property
    def shaft(self) -> float:
        """Where the rotor is, in the drive's position units."""
        return self.node.position

    def statusword(self) -> int:
        return self.node.statusword()



"""EPOS4 error codes (EMCY bytes 0-1, object 0x603F, error history 0x1003).

Public API
----------
``ERRORS``: code -> (name, error register bits of 0x1001).
``describe(code) -> str``: readable text for any 16-bit code, e.g.
``describe(0x8611) == "0x8611 Following error"``.
``error_register(code) -> int``: the 0x1001 bits the drive sets for ``code``.
``ER_*``: error register (0x1001) bit masks.
``FOLLOWING_ERROR``, ``OVERVOLTAGE`` ...: the codes the simulator raises itself.

Names follow the error code table of the maxon EPOS4 Firmware Specification
(chapter "Error Handling"); the register bits follow the CiA 301 error class
of each code (the high nibble: 2 current, 3 voltage, 4 temperature,
8 communication / motion) plus the EPOS4's motion error bit 7.
"""
from __future__ import annotations

from typing import Dict, Tuple

ER_GENERIC = 0x01
ER_CURRENT = 0x02
ER_VOLTAGE = 0x04
ER_TEMPERATURE = 0x08
ER_COMMUNICATION = 0x10
ER_DEVICE_PROFILE = 0x20
ER_MOTION = 0x80  # EPOS4: manufacturer-specific bit used for motion errors

_G = ER_GENERIC
ERRORS: Dict[int, Tuple[str, int]] = {
    0x0000: ("No error", 0),
    0x1000: ("Generic error", _G),
    0x1080: ("Generic initialization error", _G),
    0x1081: ("Generic initialization error", _G),
    0x1082: ("Generic initialization error", _G),
    0x1083: ("Generic initialization error", _G),
    0x1090: ("Firmware incompatibility error", _G),
    0x2310: ("Overcurrent error", _G | ER_CURRENT),
    0x2320: ("Power stage protection error", _G | ER_CURRENT),
    0x3210: ("Overvoltage error", _G | ER_VOLTAGE),
    0x3220: ("Undervoltage error", _G | ER_VOLTAGE),
    0x4210: ("Thermal overload error", _G | ER_TEMPERATURE),
    0x4380: ("Thermal motor overload error", _G | ER_TEMPERATURE),
    0x5113: ("Logic supply voltage too low error", _G | ER_VOLTAGE),
    0x5280: ("Hardware defect error", _G),
    0x5281: ("Hardware incompatibility error", _G),
    0x5480: ("Hardware error", _G),
    0x5481: ("Hardware error", _G),
    0x5482: ("Hardware error", _G),
    0x5483: ("Hardware error", _G),
    0x6080: ("Sign of life error", _G),
    0x6081: ("Extension 1 watchdog error", _G),
    0x6180: ("Internal software error", _G),
    0x6320: ("Software parameter error", _G),
    0x6380: ("Persistent parameter corrupt error", _G),
    0x7320: ("Position sensor error", _G | ER_DEVICE_PROFILE),
    0x7380: ("Position sensor breach error", _G | ER_DEVICE_PROFILE),
    0x7381: ("Position sensor resolution error", _G | ER_DEVICE_PROFILE),
    0x7382: ("Position sensor index error", _G | ER_DEVICE_PROFILE),
    0x7388: ("Hall sensor error", _G | ER_DEVICE_PROFILE),
    0x7389: ("Hall sensor not found error", _G | ER_DEVICE_PROFILE),
    0x738A: ("Hall angle detection error", _G | ER_DEVICE_PROFILE),
    0x738C: ("SSI sensor error", _G | ER_DEVICE_PROFILE),
    0x738D: ("SSI sensor frame error", _G | ER_DEVICE_PROFILE),
    0x7390: ("Missing main sensor error", _G | ER_DEVICE_PROFILE),
    0x7391: ("Missing commutation sensor error", _G | ER_DEVICE_PROFILE),
    0x7392: ("Main sensor direction error", _G | ER_DEVICE_PROFILE),
    0x8110: ("CAN overrun error (object lost)", _G | ER_COMMUNICATION),
    0x8111: ("CAN overrun error", _G | ER_COMMUNICATION),
    0x8120: ("CAN passive mode error", _G | ER_COMMUNICATION),
    0x8130: ("CAN heartbeat error", _G | ER_COMMUNICATION),
    0x8150: ("CAN PDO COB-ID collision", _G | ER_COMMUNICATION),
    0x81FD: ("CAN bus turned off", _G | ER_COMMUNICATION),
    0x81FE: ("CAN Rx queue overflow", _G | ER_COMMUNICATION),
    0x81FF: ("CAN Tx queue overflow", _G | ER_COMMUNICATION),
    0x8210: ("CAN PDO length error", _G | ER_COMMUNICATION),
    0x8250: ("RPDO timeout", _G | ER_COMMUNICATION),
    0x8611: ("Following error", _G | ER_MOTION),
    0x8A80: ("Negative limit switch error", _G | ER_MOTION),
    0x8A81: ("Positive limit switch error", _G | ER_MOTION),
    0x8A82: ("Software position limit error", _G | ER_MOTION),
    0x8A88: ("STO error", _G | ER_MOTION),
    0xFF01: ("System overloaded error", _G),
    0xFF02: ("Watchdog error", _G),
    0xFF0B: ("System peak overloaded error", _G),
    0xFF10: ("Controller gain error", _G),
    0xFF12: ("Auto tuning current limit error", _G),
    0xFF13: ("Auto tuning identification current error", _G),
    0xFF14: ("Auto tuning data sampling error", _G),
    0xFF15: ("Auto tuning sample mismatch error", _G),
    0xFF16: ("Auto tuning parameter error", _G),
    0xFF17: ("Auto tuning amplitude mismatch error", _G),
    0xFF19: ("Auto tuning timeout error", _G),
    0xFF20: ("Auto tuning standstill error", _G),
    0xFF21: ("Auto tuning torque invalid error", _G),
    0xFF22: ("Auto tuning max system speed error", _G),
    0xFF23: ("Auto tuning motor connection error", _G),
    0xFF24: ("Auto tuning sensor signal error", _G),
}

FOLLOWING_ERROR = 0x8611
OVERVOLTAGE = 0x3210
SOFTWARE_POSITION_LIMIT = 0x8A82
CAN_HEARTBEAT = 0x8130
CAN_PDO_LENGTH = 0x8210

# CiA 301 error class (high byte) -> register bits, for codes not in ERRORS.
_CLASS_BITS = {0x2: ER_CURRENT, 0x3: ER_VOLTAGE, 0x4: ER_TEMPERATURE,
               0x8: ER_COMMUNICATION}


def error_register(code: int) -> int:
    """Error register (0x1001) bits an EPOS4 reports together with ``code``."""
    if code in ERRORS:
        return ERRORS[code][1]
    if code == 0:
        return 0
    return ER_GENERIC | _CLASS_BITS.get((code >> 12) & 0xF, 0)


def describe(code: int) -> str:
    """Human-readable description of an EPOS4 error code."""
    code &= 0xFFFF
    if code in ERRORS:
        return "0x%04X %s" % (code, ERRORS[code][0])
    return "0x%04X unknown EPOS4 error" % code

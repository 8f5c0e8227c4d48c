"""The answer of every driver operation: what a std_srvs/Trigger or a
ros_canopen GetObject/SetObject service sends back."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Result:
    success: bool
    message: str = ""
    value: str = ""

    def __bool__(self) -> bool:
        return self.success


OK = Result(True)  # immutable: the plain success is shared (every command in the cycle answers it)


def ok(message: str = "", value: str = "") -> Result:
    if not message and not value:
        return OK
    return Result(True, message, value)


def fail(message: str) -> Result:
    return Result(False, message)

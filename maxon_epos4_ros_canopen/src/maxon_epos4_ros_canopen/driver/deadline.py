"""One deadline that several steps share (shutdown's overall bound): the
time left, fair shares of it, and the steps it cut short.

A step given a ``Deadline`` starts no SDO attempt after it and waits for
no answer past it (access.py); the SDO transfer then raises
``DeadlinePassed``, an ``SdoCommunicationError``, so every handler of a
missing answer handles it too, and the step is noted on the deadline for
the report."""
from __future__ import annotations

from typing import List, Optional

from canopen.sdo.exceptions import SdoCommunicationError

from ..clock import Clock


class DeadlinePassed(SdoCommunicationError):
    """An SDO transfer not tried (again): its deadline has passed."""


class Deadline:
    """``seconds`` from now on ``clock``. Shares (``share``, ``earlier``)
    end sooner; they report to the same list of steps cut short."""

    def __init__(self, clock: Clock, seconds: float, what: str = "shutdown deadline") -> None:
        self.clock = clock
        self.seconds = seconds
        self.what = what
        self.at = clock.now() + seconds
        self.cut: List[str] = []  # steps skipped or cut short, shared with every share
        self.is_share = False  # ends before the whole: a step's turn ran out, not the deadline

    def _sub(self, at: float, is_share: bool) -> "Deadline":
        sub = Deadline.__new__(Deadline)
        sub.clock, sub.seconds, sub.what, sub.cut = self.clock, self.seconds, self.what, self.cut
        sub.at = min(at, self.at)
        sub.is_share = self.is_share or (is_share and sub.at < self.at)
        return sub

    def left(self) -> float:
        return max(0.0, self.at - self.clock.now())

    @property
    def passed(self) -> bool:
        return self.clock.now() >= self.at

    def share(self, ways: int) -> "Deadline":
        """A deadline ``1/ways`` of the time left from now: what one of
        ``ways`` steps still to run one after the other may take, so that
        one that gets no answer leaves the others their turn."""
        return self._sub(self.clock.now() + self.left() / max(1, ways), True)

    def earlier(self, seconds: float) -> "Deadline":
        """This deadline less ``seconds``: kept for what must run after."""
        return self._sub(self.at - seconds, False)

    def note(self, step: str) -> None:
        """A step this deadline skipped or cut short, for the report."""
        if step not in self.cut:
            self.cut.append(step)

    def report(self) -> Optional[str]:
        """Which steps the deadline cut short, or None."""
        if not self.cut:
            return None
        return "%s reached: cut short or skipped: %s" % (self, "; ".join(self.cut))

    def passed_error(self, why: str) -> DeadlinePassed:
        if self.is_share:
            return DeadlinePassed("its share of the %s ran out: %s" % (self, why))
        return DeadlinePassed("%s passed: %s" % (self, why))

    def __str__(self) -> str:
        return "%s (%g s)" % (self.what, self.seconds)

"""How much of their search space the searching tests cover in this run.

Some tests search a space case by case, or repeat one piece of work many
times over: every interleaving of a command with the cycle's lines
(test_driver_interleaving.py), random command sequences against the
reference simulator (test_sim_differential.py), random frames into the
simulator (test_sim_fuzz.py), threads storming the driver for a counted
amount of work (test_driver_adversary.py), and a driver of every node-ID
from 1 to 127 (test_driver_init.py). Their outcome is a property of the
code, not of the interpreter, and each case runs the same code paths as
the others.

``SEARCH_SHARE=N`` in the environment has them take every N-th case
(``share``, ``every_nth``); unset, they take all. tools/run_tests.sh sets 4
for the Python 3.8 pass, which proves the code runs on Noetic's Python:
there the searches still run each of their code paths, the main
interpreter's pass covers the whole space.
"""
from __future__ import annotations

import os
from typing import Sequence, TypeVar

T = TypeVar("T")


def share() -> int:
    """N of SEARCH_SHARE (1: every case); a value that is no whole number
    from 1 up is an error, not a silent default."""
    text = os.environ.get("SEARCH_SHARE", "1")
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise ValueError("SEARCH_SHARE must be a whole number from 1 up, not %r" % text)
    return n


def every_nth(cases: Sequence[T], phase: int = 0) -> Sequence[T]:
    """Every share()-th of ``cases``, from the one at ``phase`` (taken
    modulo the share: searches that call this several times cover other
    cases with other phases)."""
    n = share()
    return cases[phase % n::n]

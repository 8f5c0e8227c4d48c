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

The parametrized cases of one test function are such a space too.

``SEARCH_SHARE=N`` in the environment has them take every N-th case
(``share``, ``every_nth``), and each parametrized test function one case
in N, at least one (``every_nth_parametrization``, which conftest.py
applies at collection); unset, they take all. tools/run_tests.sh
sets 4 for the Python 3.8 pass, which proves the code runs on Noetic's
Python: there the searches still run each of their code paths, the main
interpreter's pass covers the whole space.
"""
from __future__ import annotations

import os
from typing import Any, Dict, List, Sequence, Tuple, TypeVar

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


def every_nth_parametrization(items: Sequence[Any]) -> Tuple[List[Any], List[Any]]:
    """(kept, left out) of pytest's collected ``items``: every test without
    parameters, and of each parametrized test function one case in
    share(), at least one. The cases of a product of parameters come in
    rows; a step of share() would take one column of them, a step of
    share() + 1 takes a diagonal, so each parameter still takes several of
    its values. The k-th such function starts at its case k, so that
    functions with few cases do not all take their first."""
    n = share()
    if n == 1:
        return list(items), []
    cases: Dict[str, List[Any]] = {}
    for item in items:
        if getattr(item, "callspec", None) is not None:
            cases.setdefault(item.nodeid.split("[", 1)[0], []).append(item)
    taken = set()
    for k, group in enumerate(cases.values()):
        count = len(group)
        taken.update(id(group[(k + j * (n + 1)) % count]) for j in range(-(-count // n)))
    kept = [item for item in items if getattr(item, "callspec", None) is None or id(item) in taken]
    left = [item for item in items if getattr(item, "callspec", None) is not None and id(item) not in taken]
    return kept, left

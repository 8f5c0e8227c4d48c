"""SEARCH_SHARE: the searching tests' share of their space (search_share.py)."""
import itertools
from types import SimpleNamespace

import pytest

from search_share import every_nth, every_nth_parametrization, share


def collected(function: str, *params) -> list:
    """pytest items as the hook sees them: one per case of ``function``, or
    one without parameters."""
    if not params:
        return [SimpleNamespace(nodeid="t.py::" + function, callspec=None)]
    return [SimpleNamespace(nodeid="t.py::%s[%s]" % (function, "-".join(map(str, p))), callspec=p)
            for p in itertools.product(*params)]


def test_unset_every_case(monkeypatch):
    monkeypatch.delenv("SEARCH_SHARE", raising=False)
    assert share() == 1
    assert list(every_nth(range(10), phase=3)) == list(range(10))


def test_every_nth_with_phases_covering_the_whole_space(monkeypatch):
    monkeypatch.setenv("SEARCH_SHARE", "4")
    assert list(every_nth(range(1, 11))) == [1, 5, 9]
    assert list(every_nth(range(1, 11), phase=1)) == [2, 6, 10]
    covered = sorted(c for phase in range(4) for c in every_nth(range(1, 11), phase=phase))
    assert covered == list(range(1, 11))


@pytest.mark.parametrize("text", ["0", "-2", "four", ""])
def test_a_share_that_is_no_whole_number_from_1_is_an_error(monkeypatch, text):
    monkeypatch.setenv("SEARCH_SHARE", text)
    with pytest.raises(ValueError, match="SEARCH_SHARE"):
        share()


def test_unset_every_parametrized_case(monkeypatch):
    monkeypatch.delenv("SEARCH_SHARE", raising=False)
    items = collected("plain") + collected("grid", range(3), "abcd")
    assert every_nth_parametrization(items) == (items, [])


def test_a_share_of_each_parametrized_function_and_every_plain_test(monkeypatch):
    monkeypatch.setenv("SEARCH_SHARE", "4")
    grid = collected("grid", range(3), "abcd")   # rows of 4: a step of 4 would take one column
    pair = collected("pair", "xy")
    single = collected("single", [7])
    plain = collected("plain")
    items = plain + grid + pair + single
    kept, left = every_nth_parametrization(items)
    assert sorted(map(id, kept + left)) == sorted(map(id, items))
    assert plain[0] in kept and single[0] in kept
    taken = [item.callspec for item in grid if item in kept]
    assert len(taken) == 3
    assert len({p[0] for p in taken}) == 3 and len({p[1] for p in taken}) == 3   # a diagonal
    assert sum(item in kept for item in pair) == 1
    assert [item for item in items if item in kept] == kept   # collection order kept

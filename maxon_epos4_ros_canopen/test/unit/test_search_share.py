"""SEARCH_SHARE: the searching tests' share of their space (search_share.py)."""
import pytest

from search_share import every_nth, share


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

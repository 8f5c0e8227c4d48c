"""The end-to-end suite's shard count from the host's idle cores
(tools/idle_cores.py)."""
import importlib.util
import os

import pytest

_spec = importlib.util.spec_from_file_location(
    "idle_cores", os.path.join(os.path.dirname(__file__), "..", "..", "tools", "idle_cores.py"))
idle_cores = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(idle_cores)


def _stat(user, idle, iowait=0, steal=0):
    return ("cpu  %d 0 0 %d %d 0 0 %d 0 0\ncpu0 1 2 3 4 5 6 7 8 9 10\nintr 5\n"
            % (user, idle, iowait, steal))


def test_a_quiet_two_core_host_has_two_idle_cores():
    assert idle_cores.idle_cores(_stat(100, 100), _stat(110, 290), 2) == pytest.approx(1.9)


def test_two_cpu_hogs_leave_no_idle_core_and_one_shard():
    idle = idle_cores.idle_cores(_stat(100, 100), _stat(300, 101), 2)
    assert idle == pytest.approx(0.01, abs=0.001)
    assert idle_cores.shards_for(idle, 2) == 1


def test_one_hog_leaves_one_shard_and_iowait_counts_as_idle():
    idle = idle_cores.idle_cores(_stat(0, 0, 0), _stat(100, 60, 40), 2)
    assert idle == pytest.approx(1.0)
    assert idle_cores.shards_for(idle, 2) == 1


def test_stolen_time_is_not_idle():
    assert idle_cores.idle_cores(_stat(0, 0), _stat(0, 100, steal=100), 2) == pytest.approx(1.0)


@pytest.mark.parametrize("idle, most, shards", [(1.9, 2, 2), (1.75, 2, 2), (1.7, 2, 1), (0.0, 2, 1),
                                                 (3.9, 2, 2), (3.9, 8, 4)])
def test_a_shard_needs_a_core_at_least_three_quarters_idle(idle, most, shards):
    assert idle_cores.shards_for(idle, most) == shards


def test_readings_without_time_between_them_count_every_core_idle():
    assert idle_cores.idle_cores(_stat(1, 1), _stat(1, 1), 2) == 2.0


def test_a_stat_without_a_cpu_line_is_an_error():
    with pytest.raises(ValueError):
        idle_cores.cpu_times("intr 5\n")

"""The fuzz frame generator and tools/can_fuzz.py: deterministic, bounded,
aimed at the given nodes and ids, and never sending what a test excludes."""
import os
import subprocess
import sys

import can
import pytest

from maxon_epos4_ros_canopen import fuzz

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
CLI = os.path.join(REPO, "tools", "can_fuzz.py")


def _frames(seed=1, count=5000, **kwargs):
    return [fuzz.describe(m) for m in fuzz.FrameFuzzer(seed, **kwargs).frames(count)]


def test_same_seed_same_frames_other_seed_other_frames():
    assert _frames(4, node_ids=[1, 2]) == _frames(4, node_ids=[1, 2])
    assert _frames(4, node_ids=[1, 2]) != _frames(5, node_ids=[1, 2])


def test_count_lengths_and_id_widths_stay_in_can_limits():
    msgs = list(fuzz.FrameFuzzer(9, node_ids=[1], cob_ids=[0x0A1]).frames(20000))
    assert len(msgs) == 20000
    assert {len(m.data) for m in msgs if not m.is_remote_frame} == set(range(9))
    assert all(m.arbitration_id <= 0x7FF for m in msgs if not m.is_extended_id)
    assert all(m.arbitration_id <= 0x1FFFFFFF for m in msgs)
    assert any(m.is_extended_id and m.arbitration_id > 0x7FF for m in msgs)
    assert any(m.is_remote_frame for m in msgs)


def test_every_kind_with_weight_appears_aimed_at_the_nodes():
    fuzzer = fuzz.FrameFuzzer(2, node_ids=[3], cob_ids=[0x0B2],
                              weights=fuzz.parse_weights("sdo_request=5"))
    msgs = list(fuzzer.frames(20000))
    assert all(fuzzer.counts[k] > 0 for k in fuzz.KINDS)
    ids = {m.arbitration_id for m in msgs if not m.is_extended_id}
    for cob in (0x183, 0x283, 0x383, 0x483, 0x203, 0x303, 0x403, 0x503, 0x083, 0x583, 0x603,
                0x703, 0x000, 0x080, 0x0B2):
        assert cob in ids, hex(cob)
    heartbeat_states = {m.data[0] for m in msgs if m.arbitration_id == 0x703 and len(m.data) == 1}
    assert len(heartbeat_states) > 200  # any state byte, not only the four NMT states
    sdo_headers = {m.data[0] for m in msgs if m.arbitration_id == 0x583 and m.data}
    assert {0x43, 0x4F, 0x60, 0x80} <= sdo_headers  # answers of every kind, none asked for


def test_weight_zero_kinds_are_not_sent():
    fuzzer = fuzz.FrameFuzzer(1, node_ids=[1], weights=fuzz.parse_weights("nmt=0,sync=0,random=0"))
    msgs = list(fuzzer.frames(5000))
    assert not [m for m in msgs if m.arbitration_id in (0x000, 0x080) and not m.is_extended_id]
    assert fuzzer.counts["sdo_request"] == 0  # off unless asked for: requests write objects


def test_exclusions_are_replaced_not_sent():
    rules = [fuzz.NMT_STOP_ALL, fuzz.Exclusion.parse("700-77F#05"), fuzz.Exclusion.parse("1ABx")]
    msgs = list(fuzz.FrameFuzzer(3, node_ids=[1, 2], weights=fuzz.parse_weights("nmt=200"),
                                 exclude=rules).frames(10000))
    assert len(msgs) == 10000
    assert not [m for m in msgs if any(r.matches(m) for r in rules)]
    assert not [m for m in msgs if m.arbitration_id == 0 and bytes(m.data[:2]) == b"\x02\x00"]
    assert [m for m in msgs if m.arbitration_id == 0 and bytes(m.data[:2]) == b"\x02\x01"]


@pytest.mark.parametrize("text", ["", "xyz", "800", "10-5", "000#0", "20000000x#00", "0x7FF-0x800"])
def test_bad_exclusions_and_weights_are_refused(text):
    with pytest.raises(ValueError):
        fuzz.Exclusion.parse(text)


@pytest.mark.parametrize("weights", ["bogus=1", "nmt=-1", "nmt=abc"])
def test_bad_weights_are_refused(weights):
    with pytest.raises(ValueError):
        fuzz.parse_weights(weights)


def test_bad_targets_are_refused():
    with pytest.raises(ValueError):
        fuzz.FrameFuzzer(1, node_ids=[0])
    with pytest.raises(ValueError):
        fuzz.FrameFuzzer(1, cob_ids=[0x800])
    with pytest.raises(ValueError):
        fuzz.FrameFuzzer(1, weights={k: 0 for k in fuzz.KINDS})


def test_send_delivers_every_frame_and_counts_them():
    channel = "fuzz_send_%d" % os.getpid()
    tx = can.Bus(interface="virtual", channel=channel)
    rx = can.Bus(interface="virtual", channel=channel)
    try:
        sent = list(fuzz.FrameFuzzer(8, node_ids=[1]).frames(300))
        report = fuzz.send(tx, sent, rate=20000)
        got = []
        while True:
            msg = rx.recv(timeout=0)  # send() returned: the virtual bus queued every frame already
            if msg is None:
                break
            got.append(fuzz.describe(msg))
    finally:
        tx.shutdown()
        rx.shutdown()
    assert report.sent == 300 and report.dropped == 0
    assert got == [fuzz.describe(m) for m in sent]
    with pytest.raises(ValueError):
        fuzz.send(tx, [], rate=0)


def test_cli_dry_run_is_deterministic_and_bad_arguments_exit_2():
    cmd = [sys.executable, CLI, "--count", "50", "--seed", "11", "--node", "1", "--exclude", "000#0200",
           "--dry-run"]
    first = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout.split()
    second = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout.split()
    assert first == second and len(first) == 50
    bad = subprocess.run([sys.executable, CLI, "--node", "200", "--dry-run"], capture_output=True, text=True)
    assert bad.returncode == 2 and "outside 1..127" in bad.stderr

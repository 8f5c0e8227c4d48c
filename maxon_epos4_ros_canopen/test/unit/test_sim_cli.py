"""The virtual_epos4 command line and the ROS node's parameter parsing
(ROS-free parts): bad input gives a clear error, good input the right nodes."""
import os
import subprocess
import sys

import pytest

from sim_support import CONFIG, NODE1
from maxon_epos4_ros_canopen.sim.runner import node_configs_from_param, parse_node_spec

SCRIPT = os.path.join(os.path.dirname(CONFIG), "scripts", "virtual_epos4")


def run_cli(*args):
    env = dict(os.environ, PYTHONPATH=os.path.join(os.path.dirname(CONFIG), "src"))
    return subprocess.run([sys.executable, SCRIPT, *args], capture_output=True, text=True,
                          timeout=60, env=env)


def test_cli_rejects_bad_node_specs():
    for spec, message in [("x:a.dcf", "expected ID:PATH"), ("200:%s" % NODE1, "outside 1..127"),
                          ("1:/nonexistent.dcf", "no such file"), ("1:%s:5:1" % NODE1, "MIN must be below MAX")]:
        result = run_cli("--interface", "virtual", "--channel", "cli_test", "--node", spec)
        assert result.returncode == 2
        assert message in result.stderr


def test_cli_without_nodes():
    result = run_cli("--interface", "virtual")
    assert result.returncode == 2 and "at least one --node" in result.stderr


def test_parse_node_spec_with_hard_stop():
    cfg = parse_node_spec("0x05:%s:-100:2000" % NODE1)
    assert (cfg.node_id, cfg.dcf, cfg.hard_stop) == (5, NODE1, (-100.0, 2000.0))


def test_nodes_param_string_and_list():
    configs = node_configs_from_param("1:epos4_node1.dcf 2:epos4_node2.dcf:-5:5", CONFIG)
    assert [(c.node_id, os.path.basename(c.dcf), c.hard_stop) for c in configs] == \
        [(1, "epos4_node1.dcf", None), (2, "epos4_node2.dcf", (-5.0, 5.0))]
    configs = node_configs_from_param(
        [{"id": 3, "eds_pkg": "pkg", "eds_file": "config/epos4_node1.dcf", "hard_stop": [-1, 1]}],
        "/nowhere", find_package=lambda name: os.path.dirname(CONFIG))
    assert configs[0].node_id == 3 and configs[0].dcf == NODE1 and configs[0].hard_stop == (-1.0, 1.0)


@pytest.mark.parametrize("value, message", [
    ("", "empty"),
    (42, "must be a string"),
    ([{"id": 1}], "expected {id, eds_file"),
    ([{"id": 0, "eds_file": "epos4_node1.dcf"}], "id must be an integer"),
    ([{"id": 1, "eds_file": "epos4_node1.dcf", "hard_stop": [3, 1]}], "hard_stop"),
    ("1:missing.dcf", "no such DCF"),
    ("1:__import__('os').system('true')", "no such DCF"),  # never evaluated
])
def test_nodes_param_errors(value, message):
    with pytest.raises(ValueError, match=message.replace("{", r"\{")):
        node_configs_from_param(value, CONFIG)

"""What every node does at start: parameters are checked (a bad one is
reported by name and replaced by its default), the configuration comes from
~config, the 'mani' parameters or the package file, the CAN device from the
configuration unless overridden."""
import os

import pytest
import yaml

from mani_ros.config import ConfigError, load_config
from mani_ros.node_support import can_settings, node_config, read_param

CONFIG = load_config()


def getter(params):
    return lambda name, default: params.get(name, default)


@pytest.mark.parametrize("value, kind, limits, expected, error", [
    (2.5, float, {}, 2.5, None),
    (3, float, {}, 3.0, None),
    (True, float, {}, 1.0, "is not a number"),
    (float("inf"), float, {}, 1.0, "is not finite"),
    ("fast", float, {}, 1.0, "is not a number"),
    (-1.0, float, {"minimum": 0.0}, 1.0, "is below 0.0"),
    (7, int, {"maximum": 5}, 1.0, "is above 5"),
    ("yes", bool, {}, 1.0, "is not true/false"),
    ("diag", str, {"choices": ("can", "topic")}, 1.0, "is not one of 'can', 'topic'"),
])
def test_parameters_are_checked_and_named(value, kind, limits, expected, error):
    errors = []
    result = read_param(getter({"~rate": value}), "~rate", 1.0, kind, log_error=errors.append, **limits)
    assert result == expected
    if error is None:
        assert errors == []
    else:
        assert errors == ["parameter ~rate: %r %s; using 1.0" % (value, error)]


def test_configuration_sources_in_order(tmp_path):
    with open(CONFIG.source) as stream:
        data = yaml.safe_load(stream)
    assert os.path.samefile(node_config(getter({})).source, CONFIG.source)
    assert node_config(getter({"mani": data})).source == "the ROS parameters under 'mani'"
    data["MAX_VEL"] = 1.5
    path = tmp_path / "mine.yaml"
    path.write_text(yaml.safe_dump(data))
    assert node_config(getter({"~config": str(path), "mani": {}})).MAX_VEL == 1.5
    del data["MAX_VEL"]
    with pytest.raises(ConfigError, match="missing key MAX_VEL in the ROS parameters under 'mani'"):
        node_config(getter({"mani": data}))


def test_can_device_from_configuration_or_parameters():
    assert can_settings(getter({}), CONFIG) == ("socketcan", "can0")
    assert can_settings(getter({"~use_sim_device": True}), CONFIG) == ("socketcan", "vcan0")
    assert can_settings(getter({"~can_device": "can1", "~can_interface": "virtual"}), CONFIG) == \
        ("virtual", "can1")
    errors = []
    assert can_settings(getter({"~can_device": 5}), CONFIG, errors.append) == ("socketcan", "can0")
    assert errors == ["parameter ~can_device: 5 is not a string; using 'can0'"]

"""config/mani.yaml loads into a typed object; mistakes name the key and file."""
import copy
import math
import os

import pytest
import yaml

from mani_ros.config import ConfigError, config_from_dict, default_config_path, load_config

PACKAGE_YAML = os.path.join(os.path.dirname(__file__), "..", "..", "config", "mani.yaml")


def raw():
    with open(PACKAGE_YAML) as stream:
        return yaml.safe_load(stream)


def write(tmp_path, data, text=None):
    path = tmp_path / "mani.yaml"
    path.write_text(text if text is not None else yaml.safe_dump(data))
    return str(path)


def test_the_package_yaml_loads_with_its_values():
    config = load_config()
    assert os.path.samefile(config.source, PACKAGE_YAML)
    assert os.path.samefile(default_config_path(), PACKAGE_YAML)
    assert config.rover.wheel_base == 0.436 and config.rover.track == 0.4467
    assert config.DRIVE_ENC_PPR == 8384 and config.STEER_ENC_PPR == 8384
    assert config.MAX_VEL == pytest.approx(math.pi)
    assert config.can.device == "can0" and config.can.sim_device == "vcan0"
    assert config.frames.odom == "odom" and config.frames.base_link == "base_link"
    assert config.power.overcurrent_switch_off is True
    assert set(config.steering.offsets) == {"front_left", "rear_left", "rear_right", "front_right"}


def test_derived_figures():
    config = load_config()
    # MAX_VEL pi rad/s of a wheel of 0.13677 m diameter: half a revolution a second
    assert config.max_wheel_speed == pytest.approx(math.pi * 0.13677 / 2)
    assert config.max_velocity_pulses == 4192
    assert config.wheel_positions()["rear_right"] == (-0.218, -0.22335)


def test_unknown_key_names_key_and_file(tmp_path):
    data = raw()
    data["rover"]["wheelbase"] = 0.5
    path = write(tmp_path, data)
    with pytest.raises(ConfigError) as error:
        load_config(path)
    assert "unknown key rover.wheelbase in %s" % path in str(error.value)
    assert "wheel_base" in str(error.value)   # the known keys are listed


@pytest.mark.parametrize("edit, message", [
    (lambda d: d.pop("MAX_VEL"), "missing key MAX_VEL in"),
    (lambda d: d["timeouts"].pop("locomotion"), "missing key timeouts.locomotion in"),
    (lambda d: d.__setitem__("MAX_VEL", 40.0), "MAX_VEL in .* is 53374 drive encoder pulses/s, beyond an int16"),
    (lambda d: d.__setitem__("MAX_VEL", 0), "MAX_VEL in .* must be > 0"),
    (lambda d: d["can"].__setitem__("command_data_length", 8), "can.command_data_length in .* must be 2"),
    (lambda d: d["power"]["max_current"].pop("battery"), "power.max_current in .* must give one current"),
    (lambda d: d["power"]["max_current"].__setitem__("rear_left", -1), "power.max_current.rear_left in .* must be > 0"),
    (lambda d: d.__setitem__("DRIVE_ENC_PPR", 0), "DRIVE_ENC_PPR in .* must be in 1..32767"),
    (lambda d: d.__setitem__("STEER_ENC_PPR", 4096.5), "STEER_ENC_PPR in .* must be an integer"),
    (lambda d: d["rover"].__setitem__("wheel_radius", -0.1), "rover.wheel_radius in .* must be > 0"),
    (lambda d: d["rover"].__setitem__("track", "wide"), "rover.track in .* must be a number, got 'wide'"),
    (lambda d: d["rover"].__setitem__("track", float("nan")), "rover.track in .* must be a number"),
    (lambda d: d["steering"].__setitem__("min_angle", 0.5), "must include 0"),
    (lambda d: d["steering"].__setitem__("max_angle", 4.0), "must satisfy -pi <= min_angle < max_angle <= pi"),
    (lambda d: d["steering"]["offsets"].pop("rear_left"), "steering.offsets in .* must give one angle"),
    (lambda d: d["steering"]["offsets"].__setitem__("rear_left", "x"),
     "steering.offsets.rear_left in .* must be a number"),
    (lambda d: d["power"].__setitem__("overcurrent_switch_off", "yes"),
     "power.overcurrent_switch_off in .* must be true or false"),
    (lambda d: d["can"].__setitem__("device", ""), "can.device in .* must be a non-empty string"),
    (lambda d: d.__setitem__("frames", ["odom"]), "frames in .* must be a mapping"),
    (lambda d: d["timeouts"].__setitem__("locomotion", 0), "timeouts.locomotion in .* must be > 0"),
    (lambda d: d["simulation"].__setitem__("steer_rate", 0.0), "simulation.steer_rate in .* must be > 0"),
])
def test_bad_values_are_refused_with_key_and_file(tmp_path, edit, message):
    data = raw()
    edit(data)
    path = write(tmp_path, data)
    with pytest.raises(ConfigError, match=message) as error:
        load_config(path)
    assert path in str(error.value)


def test_a_dictionary_from_ros_parameters_is_named_in_errors():
    data = copy.deepcopy(raw())
    assert config_from_dict(data, "ROS parameter /mani").source == "ROS parameter /mani"
    data["frames"]["map"] = "map"
    with pytest.raises(ConfigError, match="unknown key frames.map in ROS parameter /mani"):
        config_from_dict(data, "ROS parameter /mani")


def test_missing_and_broken_files(tmp_path):
    with pytest.raises(ConfigError, match="cannot read .*nowhere.yaml"):
        load_config(str(tmp_path / "nowhere.yaml"))
    with pytest.raises(ConfigError, match="is not valid YAML"):
        load_config(write(tmp_path, None, text="rover: [1, 2\n"))
    with pytest.raises(ConfigError, match="the top level in .* must be a mapping"):
        load_config(write(tmp_path, None, text="- 1\n"))


def test_yaml_is_never_evaluated_as_python(tmp_path):
    text = "!!python/object/apply:os.system ['echo pwned']\n"
    with pytest.raises(ConfigError, match="is not valid YAML"):
        load_config(write(tmp_path, None, text=text))

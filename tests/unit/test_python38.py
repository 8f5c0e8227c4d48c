"""Python 3.8 (ROS Noetic's): requirements.txt resolves there, the harness
picks the ROS-free unit tests by their imports, and the summary gives their
3.8 run a line of its own that counts its failures."""
import importlib.util
import os
import sys

import pytest
from packaging.requirements import Requirement

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _load(name):
    spec = importlib.util.spec_from_file_location(name, os.path.join(REPO, "tools", name + ".py"))
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up here
    spec.loader.exec_module(module)
    return module


testreport = _load("testreport")
ros_free_tests = _load("ros_free_tests")


def _pins(python_version):
    """name -> pinned version of requirements.txt for an interpreter of ``python_version``."""
    env = {"python_version": python_version, "python_full_version": python_version + ".0"}
    pins = {}
    with open(os.path.join(REPO, "requirements.txt")) as f:
        for line in f:
            line = line.split("#", 1)[0].strip()
            if not line:
                continue
            req = Requirement(line)
            if req.marker is None or req.marker.evaluate(env):
                assert req.name not in pins, "%s pinned twice for Python %s" % (req.name, python_version)
                (spec,) = req.specifier
                pins[req.name] = spec.version
    return pins


def test_requirements_give_python38_a_python_can_that_supports_it():
    assert _pins("3.8")["python-can"].startswith("4.5.")  # 4.6 requires Python >= 3.9
    assert _pins("3.11")["python-can"] == "4.6.1"
    assert set(_pins("3.8")) == set(_pins("3.11"))  # every package, on both


def _tree(tmp_path, files):
    for name, text in files.items():
        path = tmp_path / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return str(tmp_path / "unit")


def test_ros_free_tests_follow_imports_through_local_modules(tmp_path):
    unit = _tree(tmp_path, {
        "unit/test_plain.py": "import math\nfrom helper_plain import x\n",
        "unit/helper_plain.py": "x = 1\ndef later():\n    import rospy  # only when called\n",
        "unit/test_rospy.py": "import rospy\n",
        "unit/test_via_helper.py": "import helper_ros\n",
        "unit/helper_ros.py": "from std_msgs.msg import String\n",
        "unit/test_generated.py": "from my_pkg.srv import Trigger\n",
        "unit/test_skips.py": "import pytest\ngenpy = pytest.importorskip('genpy.generator')\n",
        "unit/test_guarded.py": "try:\n    import actionlib\nexcept ImportError:\n    actionlib = None\n",
    })
    chosen = [os.path.basename(p) for p in ros_free_tests.ros_free([unit])]
    assert chosen == ["test_plain.py"]


def test_ros_free_tests_of_this_repository():
    folders = [os.path.join(REPO, d) for d in ("maxon_epos4_ros_canopen/test/unit", "mani_ros/test/unit")]
    chosen = {os.path.relpath(p, REPO) for p in ros_free_tests.ros_free(folders)}
    assert "maxon_epos4_ros_canopen/test/unit/test_cia402.py" in chosen
    assert "maxon_epos4_ros_canopen/test/unit/test_sim_ppm_braking.py" in chosen
    assert "mani_ros/test/unit/test_kinematics.py" in chosen
    # rospy, generated services, and a test that imports one of those
    for ros in ("maxon_epos4_ros_canopen/test/unit/test_canopen_motor_node.py",
                "maxon_epos4_ros_canopen/test/unit/test_compat_cli.py",
                "mani_ros/test/unit/test_original_interface_node.py"):
        assert ros not in chosen


PASS2 = ('<testsuite tests="2" failures="0" errors="0"><testcase classname="A" name="a"/>'
         '<testcase classname="A" name="b"/></testsuite>')
FAIL1 = ('<testsuite tests="2" failures="1" errors="0"><testcase classname="A" name="a"/>'
         '<testcase classname="A" name="b"><failure message="boom">trace</failure></testcase></testsuite>')


def test_summary_has_a_python38_line_that_counts(tmp_path, capsys):
    ok, bad = tmp_path / "ok.xml", tmp_path / "bad.xml"
    ok.write_text(PASS2)
    bad.write_text(FAIL1)
    assert testreport.main(["--pytest", str(ok), "--pytest38", str(ok), "--pytest38", str(bad)]) == 1
    out = capsys.readouterr().out.splitlines()
    assert "ROS-free unit tests under Python 3.8: 3 passed, 1 failed, 0 skipped" in out
    assert "FAILED pytest (Python 3.8): A.b failed: boom" in out
    assert out[-1] == "5 passed, 1 failed"


@pytest.mark.parametrize("args, line", [
    (["--python38-absent"], "ROS-free unit tests under Python 3.8: not run (no Python 3.8 interpreter)"),
])
def test_summary_says_when_python38_did_not_run(tmp_path, capsys, args, line):
    ok = tmp_path / "ok.xml"
    ok.write_text(PASS2)
    assert testreport.main(["--pytest", str(ok)] + args) == 0
    assert line in capsys.readouterr().out.splitlines()


def test_a_python38_run_that_left_no_results_fails(tmp_path, capsys):
    ok = tmp_path / "ok.xml"
    ok.write_text(PASS2)
    assert testreport.main(["--pytest", str(ok), "--pytest38", str(tmp_path / "missing.xml")]) == 1
    assert "ROS-free unit tests under Python 3.8: 0 passed, 1 failed, 0 skipped" in capsys.readouterr().out

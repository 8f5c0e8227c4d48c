"""The compat message packages must be wire-identical to ROS Noetic's.

A client built against the real controller_manager_msgs or canopen_chain_node
(ROS Noetic's spawner, rqt_controller_manager, a C++ tool) only talks to our
node when the md5sums agree. The expected sums are those of the released
Noetic packages; the classes are generated here with genpy exactly as catkin
would generate them.
"""
from __future__ import annotations

import importlib
import os
import sys
from pathlib import Path

import pytest

genpy_generator = pytest.importorskip(
    "genpy.generator", reason="genpy (Debian python3-genpy) is needed to generate message classes")

REPO = Path(__file__).resolve().parents[3]
COMPAT = REPO / "compat"
STD_MSGS = Path("/usr/share/std_msgs/msg")

# md5sums of the ROS Noetic releases (controller_manager_msgs 0.20,
# canopen_chain_node 0.8): service, request, response.
EXPECTED = {
    ("controller_manager_msgs", "srv", "ListControllers"): "1341feb2e63fa791f855565d0da950d8",
    ("controller_manager_msgs", "srv", "ListControllerTypes"): "c1d4cd11aefa9f97ba4aeb5b33987f4e",
    ("controller_manager_msgs", "srv", "LoadController"): "647e5c54b8d6468952d8d31f1efe96c0",
    ("controller_manager_msgs", "srv", "UnloadController"): "647e5c54b8d6468952d8d31f1efe96c0",
    ("controller_manager_msgs", "srv", "ReloadControllerLibraries"): "40e8c411fd1797d2e2c486018f846040",
    ("controller_manager_msgs", "srv", "SwitchController"): "b29a7abc673b2c54c14b54e50f8d06a5",
    ("controller_manager_msgs", "msg", "ControllerState"): "aeb6b261d97793ab74099a3740245272",
    ("controller_manager_msgs", "msg", "HardwareInterfaceResources"): "f25b55cbf1d1f76e82e5ec9e83f76258",
    ("controller_manager_msgs", "msg", "ControllerStatistics"): "697780c372c8d8597a1436d0e2ad3ba8",
    ("controller_manager_msgs", "msg", "ControllersStatistics"): "a154c347736773e3700d1719105df29d",
    ("canopen_chain_node", "srv", "GetObject"): "acdd041126bee1cd6a04a75c17856af5",
    ("canopen_chain_node", "srv", "SetObject"): "274034f4defad2415049232c96e24954",
}
EXPECTED_PARTS = {
    ("canopen_chain_node", "GetObject"): ("1a2164c691b225d4aa9cfac9d5e53364", "e1a88c7d4083c941cbf57392015270b7"),
    ("canopen_chain_node", "SetObject"): ("4ecd0744a1b58ba666b2fdce9cfb8eb1", "937c9679a518e3a18d831e57125ea522"),
}


@pytest.fixture(scope="module")
def generated(tmp_path_factory):
    """Generate Python classes for both compat packages into a temp dir."""
    if not STD_MSGS.is_dir():
        pytest.fail("std_msgs message definitions (Debian ros-std-msgs) are not installed: run tools/setup.sh")
    out = tmp_path_factory.mktemp("gen")
    search = {
        "std_msgs": [str(STD_MSGS)],
        "controller_manager_msgs": [str(COMPAT / "controller_manager_msgs" / "msg")],
        "canopen_chain_node": [],
    }
    for pkg in ("controller_manager_msgs", "canopen_chain_node"):
        for kind, gen_cls in (("msg", genpy_generator.MsgGenerator), ("srv", genpy_generator.SrvGenerator)):
            src = COMPAT / pkg / kind
            if not src.is_dir():
                continue
            files = sorted(str(p) for p in src.glob("*." + kind))
            outdir = out / pkg / kind
            rc = gen_cls().generate_messages(pkg, files, str(outdir), search)
            assert rc == 0, "genpy failed for %s/%s" % (pkg, kind)
            # genpy writes _Name.py modules; expose them as the package does.
            (outdir / "__init__.py").write_text(
                "".join("from ._%s import *\n" % Path(f).stem for f in files))
        (out / pkg / "__init__.py").write_text("")
    for name in list(sys.modules):
        if name.split(".")[0] in ("controller_manager_msgs", "canopen_chain_node"):
            del sys.modules[name]
    # the generated packages are importable for this module's tests only
    with pytest.MonkeyPatch.context() as patch:
        patch.syspath_prepend(str(out))
        yield out
    for name in list(sys.modules):
        if name.split(".")[0] in ("controller_manager_msgs", "canopen_chain_node"):
            del sys.modules[name]


@pytest.mark.parametrize("key", sorted(EXPECTED), ids=lambda k: "%s/%s" % (k[0], k[2]))
def test_md5sum_matches_noetic(generated, key):
    pkg, kind, name = key
    module = importlib.import_module("%s.%s" % (pkg, kind))
    cls = getattr(module, name)
    assert cls._md5sum == EXPECTED[key]
    assert cls._type == "%s/%s" % (pkg, name)


@pytest.mark.parametrize("key", sorted(EXPECTED_PARTS), ids=lambda k: k[1])
def test_request_response_md5sums(generated, key):
    pkg, name = key
    module = importlib.import_module("%s.srv" % pkg)
    req_md5, resp_md5 = EXPECTED_PARTS[key]
    assert getattr(module, name + "Request")._md5sum == req_md5
    assert getattr(module, name + "Response")._md5sum == resp_md5


def test_switch_controller_constants(generated):
    from controller_manager_msgs.srv import SwitchControllerRequest
    assert SwitchControllerRequest.BEST_EFFORT == 1
    assert SwitchControllerRequest.STRICT == 2


def test_compat_is_ignored_by_catkin():
    # A user cloning the repository into a workspace must not get these
    # packages built on top of the real ones.
    assert (COMPAT / "CATKIN_IGNORE").exists()

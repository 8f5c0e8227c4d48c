"""compat/control_msgs must be wire-identical to ROS Noetic's control_msgs.

MoveIt's FollowJointTrajectory controller handler (and any rospy/roscpp
client built against the real package) only connects to our action server
when the md5sums agree. The classes are generated here from the compat
sources with actionlib's genaction and genpy, as catkin would.
"""
from __future__ import annotations

import importlib
import subprocess
import sys
from pathlib import Path

import pytest

genpy_generator = pytest.importorskip(
    "genpy.generator", reason="genpy (Debian python3-genpy) is needed to generate message classes")

REPO = Path(__file__).resolve().parents[3]
SRC = REPO / "compat" / "control_msgs"
SHARE = Path("/usr/share")
GENACTION = Path("/usr/lib/actionlib_msgs/genaction.py")

# md5sums of ROS Noetic's control_msgs 1.5 (the ones MoveIt and
# ros_control's joint_trajectory_controller are built against).
EXPECTED = {
    ("msg", "FollowJointTrajectoryAction"): "bc4f9b743838566551c0390c65f1a248",
    ("msg", "FollowJointTrajectoryActionGoal"): "cff5c1d533bf2f82dd0138d57f4304bb",
    ("msg", "FollowJointTrajectoryActionResult"): "c4fb3b000dc9da4fd99699380efcc5d9",
    ("msg", "FollowJointTrajectoryActionFeedback"): "d8920dc4eae9fc107e00999cce4be641",
    ("msg", "FollowJointTrajectoryGoal"): "69636787b6ecbde4d61d711979bc7ecb",
    ("msg", "FollowJointTrajectoryResult"): "493383b18409bfb604b4e26c676401d2",
    ("msg", "FollowJointTrajectoryFeedback"): "10817c60c2486ef6b33e97dcd87f4474",
    ("msg", "JointTolerance"): "f544fe9c16cf04547e135dd6063ff5be",
    ("msg", "JointTrajectoryControllerState"): "10817c60c2486ef6b33e97dcd87f4474",
    ("srv", "QueryTrajectoryState"): "ec93cdecbd8062d761aa52b7c90cd44b",
    ("srv", "QueryTrajectoryStateRequest"): "556a4fb76023a469987922359d08a844",
    ("srv", "QueryTrajectoryStateResponse"): "1f1a6554ad060f44d013e71868403c1a",
}


def _drop_modules() -> None:
    for name in list(sys.modules):
        if name.split(".")[0] == "control_msgs":
            del sys.modules[name]


@pytest.fixture(scope="module")
def generated(tmp_path_factory):
    deps = ("std_msgs", "actionlib_msgs", "trajectory_msgs", "geometry_msgs")
    for dep in deps:
        if not (SHARE / dep / "msg").is_dir():
            pytest.skip("%s message definitions (Debian ros-%s) are not installed"
                        % (dep, dep.replace("_", "-")))
    if not GENACTION.is_file():
        pytest.skip("actionlib's genaction.py (Debian libactionlib-msgs-dev) is not installed")
    out = tmp_path_factory.mktemp("control_msgs_gen")
    action_msgs = out / "action_msg"
    subprocess.run([sys.executable, str(GENACTION), "-o", str(action_msgs),
                    str(SRC / "action" / "FollowJointTrajectory.action")],
                   check=True, stdout=subprocess.DEVNULL)
    search = {dep: [str(SHARE / dep / "msg")] for dep in deps}
    search["control_msgs"] = [str(SRC / "msg"), str(action_msgs)]
    jobs = (
        ("msg", genpy_generator.MsgGenerator,
         sorted(SRC.glob("msg/*.msg")) + sorted(action_msgs.glob("*.msg"))),
        ("srv", genpy_generator.SrvGenerator, sorted(SRC.glob("srv/*.srv"))),
    )
    for kind, gen_cls, files in jobs:
        outdir = out / "control_msgs" / kind
        rc = gen_cls().generate_messages("control_msgs", [str(f) for f in files], str(outdir), search)
        assert rc == 0, "genpy failed for control_msgs/%s" % kind
        (outdir / "__init__.py").write_text("".join("from ._%s import *\n" % f.stem for f in files))
    (out / "control_msgs" / "__init__.py").write_text("")
    _drop_modules()
    # the generated package is importable for this module's tests only
    with pytest.MonkeyPatch.context() as patch:
        patch.syspath_prepend(str(out))
        yield out
    _drop_modules()


@pytest.mark.parametrize("key", sorted(EXPECTED), ids=lambda k: k[1])
def test_md5sum_matches_noetic(generated, key):
    kind, name = key
    cls = getattr(importlib.import_module("control_msgs." + kind), name)
    assert cls._md5sum == EXPECTED[key]
    assert cls._type == "control_msgs/" + name


def test_result_codes_match_trajectory_core(generated):
    from control_msgs.msg import FollowJointTrajectoryResult as R
    from maxon_epos4_ros_canopen import trajectory
    assert (R.SUCCESSFUL, R.INVALID_GOAL, R.INVALID_JOINTS, R.OLD_HEADER_TIMESTAMP,
            R.PATH_TOLERANCE_VIOLATED, R.GOAL_TOLERANCE_VIOLATED) == (
        trajectory.SUCCESSFUL, trajectory.INVALID_GOAL, trajectory.INVALID_JOINTS,
        trajectory.OLD_HEADER_TIMESTAMP, trajectory.PATH_TOLERANCE_VIOLATED,
        trajectory.GOAL_TOLERANCE_VIOLATED)


def test_goal_round_trips_through_the_wire_format(generated):
    # What MoveIt serializes must come back field for field.
    import io
    from control_msgs.msg import FollowJointTrajectoryGoal, JointTolerance
    from trajectory_msgs.msg import JointTrajectoryPoint
    import genpy
    goal = FollowJointTrajectoryGoal()
    goal.trajectory.joint_names = ["base_link1_joint", "link1_link2_joint"]
    goal.trajectory.points = [JointTrajectoryPoint(positions=[0.5, -0.5], velocities=[0.0, 0.0],
                                                   time_from_start=genpy.Duration(2, 500))]
    goal.goal_tolerance = [JointTolerance(name="base_link1_joint", position=0.01)]
    goal.goal_time_tolerance = genpy.Duration(0, 250000000)
    buf = io.BytesIO()
    goal.serialize(buf)
    back = FollowJointTrajectoryGoal().deserialize(buf.getvalue())
    assert back.trajectory.joint_names == goal.trajectory.joint_names
    assert list(back.trajectory.points[0].positions) == [0.5, -0.5]
    assert back.trajectory.points[0].time_from_start == genpy.Duration(2, 500)
    assert back.goal_tolerance[0].position == 0.01
    assert back.goal_time_tolerance.to_sec() == 0.25

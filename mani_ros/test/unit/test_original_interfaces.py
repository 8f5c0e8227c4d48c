"""The rover's original interfaces (MoveControl, MotorControl, EncoderOdometry,
OdometryReset, the Locomotion action's goal) are wire-identical to the
original code's: ROS connects publishers, subscribers, services and action
clients by MD5 sum, so equal sums mean the original's clients work unchanged.
The sums below were computed with genmsg from the original definitions
(GitHub PTSSpace/MANIros, branch develop)."""
import os

import genmsg
import genmsg.gentools
import genmsg.msg_loader
import pytest

PACKAGE = os.path.normpath(os.path.join(os.path.dirname(__file__), "..", ".."))
STD_MSGS = "/usr/share/std_msgs/msg"

ORIGINAL_MD5 = {
    "MoveControl": "e5c6784c993645f74abc382b9f17b723",
    "MotorControl": "bc79e4fdcbb157706dfdc9900cf22d4d",
    "EncoderOdometry": "adbab603bfea18199619791d1ec5c993",
}


def context():
    search = {"mani_ros": [os.path.join(PACKAGE, "msg")], "std_msgs": [STD_MSGS]}
    return genmsg.MsgContext.create_default(), search


@pytest.mark.parametrize("name, md5", sorted(ORIGINAL_MD5.items()))
def test_messages_have_the_originals_md5(name, md5):
    ctx, search = context()
    spec = genmsg.msg_loader.load_msg_by_type(ctx, "mani_ros/" + name, search)
    genmsg.msg_loader.load_depends(ctx, spec, search)
    assert genmsg.gentools.compute_md5(ctx, spec) == md5


def test_odometry_reset_service_has_the_originals_md5():
    ctx, _ = context()
    spec = genmsg.msg_loader.load_srv_from_file(
        ctx, os.path.join(PACKAGE, "srv", "OdometryReset.srv"), "mani_ros/OdometryReset")
    assert genmsg.gentools.compute_md5(ctx, spec) == "afa8d177c45c93cfe2492a2d71303eb9"


def test_locomotion_action_goal_result_feedback_match_the_original():
    with open(os.path.join(PACKAGE, "action", "Locomotion.action")) as stream:
        parts = stream.read().split("\n---\n")
    ctx, search = context()
    sums = []
    for name, text in zip(("LocomotionGoal", "LocomotionResult", "LocomotionFeedback"), parts):
        spec = genmsg.msg_loader.load_msg_from_string(ctx, text, "mani_ros/" + name)
        genmsg.msg_loader.load_depends(ctx, spec, search)
        sums.append(genmsg.gentools.compute_md5(ctx, spec))
    # goal: MoveControl command; result and feedback: int32[] sequence
    assert sums == ["ce3daca1c1944e5b79f3997e802bdc50", "b81e37d2a31925a0e8ae261a8699cb79",
                    "b81e37d2a31925a0e8ae261a8699cb79"]

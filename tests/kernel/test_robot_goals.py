"""When a robot does not move to a goal (eqa.robot.goal_not_taken): the sim and the ROS 2 bridge refuse the same
goals with the same reasons."""

from __future__ import annotations

from eqa.messages import Pose2D
from eqa.robot import NO_POSE, goal_not_taken


def test_a_goal_without_pose_or_past_the_step_limit_is_not_taken() -> None:
    pose = Pose2D(x=1.0, y=2.0, yaw=0.0)
    assert goal_not_taken(pose, 0, 10) is None
    assert goal_not_taken(pose, 8, 10) is None  # step 9, the last one, is still made
    assert goal_not_taken(pose, 9, 10) == "step limit 10 reached"
    assert goal_not_taken(None, 0, 10) == NO_POSE == "goal has no pose and is not done"
    assert goal_not_taken(None, 9, 10) == NO_POSE  # no pose is said first

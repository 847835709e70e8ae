"""The simulated robot's body, one home for the numbers every service judges collisions and reach by.

* :data:`COLLISION_RADIUS_M` -- the robot's collision radius: a base motion collides when its path passes
  closer than this to a wall or furniture of the true scene (the sim's count, ``services.sim.skills``);
* :data:`MAP_MARGIN_M` -- the margin the planner keeps on top of that radius on its *mapped* occupancy (the map
  is built from depth and misses or misplaces obstacle edges by about a voxel, 0.05 m): paths, gaze points and
  skill poses of task episodes keep :func:`mapped_clearance_m` from mapped occupied cells;
* :data:`REACH_M` -- the oracle pick's reach, from the base centre to the object's box, horizontally;
* :data:`OBSTACLE_MIN_Z_M` -- what rises above this height is an obstacle the base collides with (lower is
  floor: rugs, thresholds): the sim's navigable grid and the task mapper's obstacle band both start here;
* :func:`goal_not_taken` -- when a robot (the sim, or a real one behind the ROS 2 bridge) does not move to a goal.

What counts as a collision against OVMM's definition is written in ``docs/results/helios-collisions.md``.
"""

from __future__ import annotations

COLLISION_RADIUS_M = 0.15  # robot body with a margin for the arm
MAP_MARGIN_M = 0.05  # one voxel of the mapper's occupancy
REACH_M = 0.9  # arm reach of a mobile manipulator base
OBSTACLE_MIN_Z_M = 0.05


NO_POSE = "goal has no pose and is not done"


def goal_not_taken(pose: object | None, step: int, max_steps: int) -> str | None:
    """Why a robot at step ``step`` of an episode of ``max_steps`` does not move to a goal that is not done: the
    goal has no ``pose``, or the next step would pass the limit; None when it moves."""
    if pose is None:
        return NO_POSE
    if step + 1 >= max_steps:
        return f"step limit {max_steps} reached"
    return None


def mapped_clearance_m() -> float:
    """Distance a planned pose keeps from mapped occupied cells: the collision radius plus the map margin."""
    return COLLISION_RADIUS_M + MAP_MARGIN_M

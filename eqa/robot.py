"""The simulated robot's body, one home for the numbers every service judges collisions and reach by.

* :data:`COLLISION_RADIUS_M` -- the robot's collision radius: a base motion collides when its path passes
  closer than this to a wall or furniture of the true scene (the sim's count, ``services.sim.skills``);
* :data:`MAP_MARGIN_M` -- the margin the planner keeps on top of that radius on its *mapped* occupancy: paths,
  gaze points and skill poses of task episodes keep :func:`mapped_clearance_m` from mapped occupied cells. The
  clearance is measured from cell centre to cell centre on the mapper's 2D grid (its voxel size, 0.1 m,
  ``services.mapper.tsdf.VolumeConfig``): an obstacle fills up to half a cell beyond its cell's centre and a path
  point lies up to half a cell from its own cell's centre, so along an axis the robot can be one cell closer to
  the obstacle's edge than the centre distance says. The margin is that cell: with half of it (0.05 m) a path
  kept 0.2 m from the centres may pass 0.1 m from the edge of mapped furniture or a wall, inside the collision
  radius (the collisions of the tuning seed 11 at mapped corners, docs/results/helios-collisions.md);
* :data:`REACH_M` -- the oracle pick's reach, from the base centre to the object's box, horizontally;
* :data:`OBSTACLE_MIN_Z_M` -- what rises above this height is an obstacle the base collides with (lower is
  floor: rugs, thresholds): the sim's navigable grid and the task mapper's obstacle band both start here;
* :func:`goal_not_taken` -- when a robot (the sim, or a real one behind the ROS 2 bridge) does not move to a goal.

What counts as a collision against OVMM's definition is written in ``docs/results/helios-collisions.md``.
"""

from __future__ import annotations

COLLISION_RADIUS_M = 0.15  # robot body with a margin for the arm
MAP_MARGIN_M = 0.1  # one cell of the mapper's 2D grid (its voxel size)
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

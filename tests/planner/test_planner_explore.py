"""Closed loop of pure cores in one process: sim renders, mapper maps, planner (FBE) moves the robot.

Every goal must be a pose the simulator accepts, and FBE must cover the house within the step limit
T = 3 sqrt(area) (Explore-EQA appendix B).

What "explored" means here: the share of the reachable floor (simulator ground truth) that the map has
*observed* (seen in a depth image, free-space carving included). The bar is >= 90 % of the reachable
floor within T. The map's appendix-B "explored" layer (middle 50 % HFOV x lower 50 % VFOV of a camera 30 deg
down from 1.5 m) marks at most a ~60 deg wedge out to ~2.6 m per step (about 3.5 m2), so 90 % of that layer
within T = 3 sqrt(area) steps is out of reach for any strategy (T * 3.5 m2 < 0.9 area for areas above
~100 m2 even with no overlap); it is reported, and asserted at a lower bar.

Measured on 20 generated houses of 100-140 m2 (160x120 frames): fbe observes 94 % (min 76 %) and marks 79 %
appendix-B explored; before the planner's 0.1 m clearance fallback (doorways narrowed on the map) and the
3 m distance decay, 82 % observed, with episodes ending early at 50 %.
"""

from __future__ import annotations

import numpy as np

from eqa.budget import max_steps_for
from eqa.messages import EpisodeStart, Frame, Pose2D, Question
from services.mapper.episode_map import EpisodeMap
from services.planner.sampling import step_rng
from services.planner.step import Memory, plan_step
from services.sim import camera
from services.sim.catalog import HouseLimits
from services.sim.housegen import generate_house
from services.sim.motion import pose_error, reachable_map, sample_start_pose
from services.sim.render import Renderer

W, H = 160, 120


def explored_share(
    emap: EpisodeMap, reach: np.ndarray, rox: float, roy: float, rres: float, layer: str = "explored"
) -> float:
    """Share of the reachable floor cells (sim ground truth) whose map cell is explored (or observed)."""
    assert emap.maps is not None
    mask = getattr(emap.maps, layer)
    ii, jj = np.nonzero(reach)
    x = rox + (jj + 0.5) * rres
    y = roy + (ii + 0.5) * rres
    ox, oy = emap.origin
    c = np.floor((x - ox) / emap.resolution).astype(int)
    r = np.floor((y - oy) / emap.resolution).astype(int)
    inside = (r >= 0) & (r < mask.shape[0]) & (c >= 0) & (c < mask.shape[1])
    seen = np.zeros(x.shape, dtype=bool)
    seen[inside] = mask[r[inside], c[inside]]
    return float(seen.mean())


def run_fbe(seed: int) -> tuple[int, int, bool, float, float]:
    """One closed-loop fbe episode; (T, steps taken, ended early, explored share, observed share)."""
    scene = generate_house(seed, HouseLimits(min_area_m2=100.0, max_area_m2=140.0, min_rooms=4, max_rooms=5))
    renderer = Renderer(scene)
    T = max_steps_for(scene.floor_area_m2)
    start_pose = sample_start_pose(scene, np.random.default_rng(seed))
    reach, rox, roy = reachable_map(scene, start_pose)
    q = Question(text="Where is the sofa?", choices=["kitchen", "bedroom"], scene=scene.id)
    start = EpisodeStart(episode_id="ep-loop", robot="r0", question=q, strategy="fbe", max_steps=T, seed=seed)
    emap = EpisodeMap(start)
    K = camera.intrinsics(W, H)
    pose: Pose2D = start_pose
    memory = Memory()
    done = False
    step = 0
    for step in range(T):
        cam = camera.camera_pose(pose)
        r = renderer.render(cam, K, W, H)
        frame = Frame(
            episode_id="ep-loop",
            step=step,
            pose=pose,
            camera_pose=cam,
            intrinsics=K,
            rgb=r.rgb,
            depth=r.depth,
        )
        emap.integrate(frame)
        frontiers = emap.compute_frontiers()
        update = emap.map_update()
        plan = plan_step(
            update.grid, update.free, update.occupied, update.pose, frontiers, "fbe", memory, step_rng(seed, step)
        )
        if plan.done:
            done = True
            break
        assert plan.pose is not None
        err = pose_error(scene, plan.pose)
        assert err is None, f"seed {seed} step {step}: the simulator would refuse {plan.pose}: {err}"
        memory, pose = plan.memory, plan.pose
    explored = explored_share(emap, reach, rox, roy, 0.05)
    observed = explored_share(emap, reach, rox, roy, 0.05, "observed")
    return T, step + 1, done, explored, observed


def test_fbe_closed_loop_covers_the_house_within_step_limit() -> None:
    seeds = range(1, 7)
    runs = [run_fbe(seed) for seed in seeds]
    for seed, (T, steps, done, explored, observed) in zip(seeds, runs, strict=True):
        print(f"house {seed}: fbe, T={T}, {steps} steps: {observed:.0%} observed, {explored:.0%} explored")
        # it never gives up while much of the house is unseen (doorways the map narrows must not stop it)
        assert not done or observed >= 0.9, f"house {seed}: ended after {steps}/{T} steps with {observed:.0%}"
        assert observed >= 0.7, f"house {seed}: observed {observed:.0%} of the reachable floor in T={T}"
    mean_observed = float(np.mean([r[4] for r in runs]))
    mean_explored = float(np.mean([r[3] for r in runs]))
    assert mean_observed >= 0.9, f"fbe observed {mean_observed:.0%} of the reachable floor on average"
    assert mean_explored >= 0.65, f"fbe marked {mean_explored:.0%} appendix-B explored on average"

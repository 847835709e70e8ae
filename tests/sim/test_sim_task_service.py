"""A task episode in the sim service over real Zenoh: the goal's skill runs on the frame at the goal pose, its
outcome rides on that frame, the phase metrics go to the store, and a restarted sim continues the task."""

from __future__ import annotations

import threading
import time

import numpy as np
from support.fleet import wait_for

from eqa import keys
from eqa.bus import Bus
from eqa.messages import EpisodeStart, Frame, Goal, Question
from eqa.store import open_store, task_metrics_key
from services.sim.housegen import generate_house
from services.sim.motion import reachable_map
from services.sim.service import SimService
from services.sim.skills import pick_poses
from services.sim.tasks import generate_tasks


def test_sim_task_episode_pick_metrics_and_restart(hub_settings, settings) -> None:
    scene = generate_house(115002)
    task = next(t for t in generate_tasks(scene, np.random.default_rng(115002)) if t.kind == "pick_place")
    reach, ox, oy = reachable_map(scene, task.start_pose)
    pose = next(p for oid in task.object_ids for p in pick_poses(scene, oid, reach, (ox, oy)))
    q = Question(text=task.text, scene=task.scene, start_pose=task.start_pose)
    start = EpisodeStart(episode_id="ep-task", robot="r0", question=q, max_steps=40, record=False, task=task,
                         pick_limit=5)
    frames: list[Frame] = []
    lock = threading.Lock()
    with Bus(hub_settings, "gateway", "test") as bus:
        def on_frame(k: str, m: Frame) -> None:
            with lock:
                frames.append(m)

        bus.subscribe(keys.any_robot(keys.SIM_FRAME), Frame, on_frame)
        svc = SimService(settings)
        svc.start()
        try:
            time.sleep(0.5)
            bus.publish(keys.stream("r0", keys.EPISODE_START), start)
            assert wait_for(lambda: any(f.step == 0 for f in frames), timeout=20.0)
            assert frames[0].skill is None
            bus.publish(keys.stream("r0", keys.PLANNER_GOAL),
                        Goal(episode_id="ep-task", step=0, pose=pose, skill="pick", target=99, phase="picking"))
            assert wait_for(lambda: any(f.step == 1 for f in frames), timeout=20.0)
            f1 = next(f for f in frames if f.step == 1)
            assert f1.skill is not None and f1.skill.skill == "pick" and f1.skill.success and f1.skill.target == 99
        finally:
            svc.stop()
        store = open_store(settings)
        m = store.get_json(task_metrics_key("ep-task"))
        assert m["FindObj"] == 1.0 and m["Pick"] == 1.0 and m["pick_attempts"] == 1.0 and m["Place"] == 0.0
        # a new sim process continues the task from the store: the next goal is served, the metrics kept
        svc2 = SimService(settings)
        svc2.start()
        try:
            time.sleep(0.5)
            bus.publish(keys.stream("r0", keys.PLANNER_GOAL), Goal(episode_id="ep-task", step=1, pose=pose))
            assert wait_for(lambda: any(f.step == 2 for f in frames), timeout=20.0)
            f2 = next(f for f in frames if f.step == 2)
            assert f2.skill is None
        finally:
            svc2.stop()
        m2 = store.get_json(task_metrics_key("ep-task"))
        assert m2["Pick"] == 1.0 and m2["pick_attempts"] == 1.0


def test_question_and_task_episodes_count_collisions_alike(hub_settings, settings) -> None:
    """One collision model: the same goal, a straight path through an obstacle, counts one collision in a
    question episode (the sim's episode state) and in a task episode (its metrics); a clear path counts none."""
    from eqa.messages import Pose2D
    from services.sim.motion import pose_error
    from services.sim.skills import motion_path, path_collides

    scene = generate_house(115002)
    task = next(t for t in generate_tasks(scene, np.random.default_rng(115002)) if t.kind == "pick_place")
    here = task.start_pose
    reach, ox, oy = reachable_map(scene, here)
    rows, cols = np.nonzero(reach)
    rng = np.random.default_rng(0)
    hit = clear = None
    for k in rng.permutation(len(rows))[:4000]:
        p = Pose2D(x=float(ox + (cols[k] + 0.5) * 0.05), y=float(oy + (rows[k] + 0.5) * 0.05))
        if pose_error(scene, p) is not None or not 1.0 < np.hypot(p.x - here.x, p.y - here.y) < 3.0:
            continue
        if path_collides(scene, motion_path((here.x, here.y), [], (p.x, p.y))):
            hit = hit or p
        else:
            clear = clear or p
        if hit and clear:
            break
    assert hit is not None and clear is not None
    frames: list[Frame] = []
    with Bus(hub_settings, "gateway", "test") as bus:
        bus.subscribe(keys.any_robot(keys.SIM_FRAME), Frame, lambda k, m: frames.append(m))
        svc = SimService(settings)
        svc.start()
        try:
            time.sleep(0.5)
            q = Question(text=task.text, scene=task.scene, start_pose=here)
            for eid, t in (("ep-q", None), ("ep-t", task)):
                bus.publish(keys.stream("r0" if t is None else "r1", keys.EPISODE_START),
                            EpisodeStart(episode_id=eid, robot="r0" if t is None else "r1", question=q,
                                         max_steps=10, record=False, task=t))
            assert wait_for(lambda: {f.episode_id for f in frames if f.step == 0} == {"ep-q", "ep-t"}, timeout=20)
            home = Pose2D(x=here.x, y=here.y, yaw=here.yaw)
            eps = (("ep-q", "r0"), ("ep-t", "r1"))
            for step, pose in enumerate((clear, home, hit)):  # out and back along a clear line, then the hit
                for eid, robot in eps:
                    bus.publish(keys.stream(robot, keys.PLANNER_GOAL), Goal(episode_id=eid, step=step, pose=pose))
                assert wait_for(lambda s=step: {f.episode_id for f in frames if f.step == s + 1} == {"ep-q", "ep-t"},
                                timeout=20)
                want = 1 if pose is hit else 0
                assert svc.episodes["ep-q"].collisions == want and svc.episodes["ep-t"].collisions == want, step
        finally:
            svc.stop()
        store = open_store(settings)
        assert store.get_json(task_metrics_key("ep-t"))["collisions"] == 1.0
        svc2 = SimService(settings)  # the count is part of the stored state
        assert svc2.episode("ep-q").collisions == 1

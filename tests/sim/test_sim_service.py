"""The sim service over real Zenoh: frames, refused goals, bad input, several robots."""

from __future__ import annotations

import math
import threading
import time

import numpy as np
from support.fleet import wait_for
from support.services import serving

from eqa import keys
from eqa.bus import Bus
from eqa.codec import packb
from eqa.messages import EpisodeStart, ErrorReply, Frame, Goal, Pose2D, Question
from services.sim.housegen import generate_house
from services.sim.motion import sample_start_pose
from services.sim.service import SimService

SCENE = "gen-00014"




def _start(ep: str, robot: str, scene: str, pose: Pose2D | None = None) -> EpisodeStart:
    q = Question(text="Where is the red box?", choices=["In the kitchen", "In the bedroom"], scene=scene,
                 start_pose=pose)
    return EpisodeStart(episode_id=ep, robot=robot, question=q, max_steps=30, seed=3, record=False)


def test_sim_service_serves_frames_and_refuses_bad_input(hub_settings, settings) -> None:
    (settings.scenes_path).mkdir(parents=True, exist_ok=True)
    (settings.scenes_path / "broken.ply").write_bytes(b"not a mesh at all")
    scene = generate_house(14)
    frames: list[tuple[str, Frame]] = []
    errors: list[tuple[str, ErrorReply]] = []
    lock = threading.Lock()
    with Bus(hub_settings, "gateway", "test") as bus:
        def on_frame(k: str, m: Frame) -> None:
            with lock:
                frames.append((keys.robot_of(k), m))

        bus.subscribe(keys.any_robot(keys.SIM_FRAME), Frame, on_frame)
        bus.subscribe(keys.any_robot(keys.SIM_ERROR), ErrorReply, lambda k, m: errors.append((keys.robot_of(k), m)))
        with serving(SimService(settings)):
            # unknown scene and a mesh that does not parse: error replies naming the problem
            bus.publish(keys.stream("r1", keys.EPISODE_START), _start("ep-bad", "r1", "no-such-scene"))
            bus.publish(keys.stream("r2", keys.EPISODE_START), _start("ep-broken", "r2", "broken"))
            assert wait_for(lambda: len(errors) >= 2, timeout=15.0)
            by_robot = {r: e for r, e in errors}
            assert by_robot["r1"].source == "sim" and by_robot["r1"].episode_id == "ep-bad"
            assert "unknown scene" in by_robot["r1"].reason and by_robot["r1"].step == 0
            assert "does not parse" in by_robot["r2"].reason

            # a good episode on r0: frame 0 at the sampled start pose
            bus.publish(keys.stream("r0", keys.EPISODE_START), _start("ep0", "r0", SCENE))
            assert wait_for(lambda: any(r == "r0" for r, _ in frames), timeout=15.0)
            f0 = next(f for r, f in frames if r == "r0")
            h, w = settings.sim_height, settings.sim_width
            assert f0.step == 0 and f0.rgb.shape == (h, w, 3) and f0.depth.shape == (h, w)
            assert f0.instances is not None and f0.instances.shape == (h, w)
            assert f0.scene == SCENE and f0.floor_area_m2 == scene.floor_area_m2
            assert f0.intrinsics.shape == (3, 3) and np.allclose(f0.camera_pose[:3, 3], [f0.pose.x, f0.pose.y, 1.5])
            assert {lab.id for lab in f0.labels} == set(np.unique(f0.instances[f0.instances >= 0]).tolist())

            # a goal inside a wall is refused with the step; a NaN pose is dropped as malformed
            room = scene.rooms[0]
            wall = Pose2D(x=room.rect[0] + 0.02, y=room.center[1], yaw=0.0)
            bus.publish(keys.stream("r0", keys.PLANNER_GOAL), Goal(episode_id="ep0", step=0, pose=wall))
            assert wait_for(lambda: any(e.episode_id == "ep0" for _, e in errors), timeout=15.0)
            err = next(e for _, e in errors if e.episode_id == "ep0")
            assert err.step == 0 and "collision" in err.reason
            nan_goal = {"kind": "goal", "schema_version": 1, "sent_at": time.time(), "episode_id": "ep0", "step": 0,
                        "pose": {"x": math.nan, "y": 1.0, "yaw": 0.0}}
            bus.publish_raw(keys.stream("r0", keys.PLANNER_GOAL), packb(nan_goal))
            bus.publish_raw(keys.stream("r0", keys.PLANNER_GOAL), b"\x00garbage")

            # meanwhile another robot is served in the same scene, and r0 goes on with a valid goal
            bus.publish(keys.stream("r3", keys.EPISODE_START), _start("ep3", "r3", SCENE))
            good = sample_start_pose(scene, np.random.default_rng(42), clearance=0.3)
            bus.publish(keys.stream("r0", keys.PLANNER_GOAL), Goal(episode_id="ep0", step=0, pose=good))
            assert wait_for(lambda: any(r == "r0" and f.step == 1 for r, f in frames), timeout=15.0)
            assert wait_for(lambda: any(r == "r3" for r, _ in frames), timeout=15.0)
            f1 = next(f for r, f in frames if r == "r0" and f.step == 1)
            assert f1.pose == good
            assert len([1 for r, f in frames if r == "r0"]) == 2  # nothing rendered for the refused goals


def test_a_restarted_sim_continues_the_episode_at_the_next_goal(hub_settings, settings) -> None:
    scene = generate_house(14)
    frames: list[Frame] = []
    with Bus(hub_settings, "gateway", "test") as bus:
        bus.subscribe(keys.stream("r0", keys.SIM_FRAME), Frame, lambda k, m: frames.append(m))
        first = SimService(settings)
        first.start()
        try:
            time.sleep(0.5)
            bus.publish(keys.stream("r0", keys.EPISODE_START), _start("ep-rs", "r0", SCENE))
            assert wait_for(lambda: len(frames) == 1, timeout=15.0)
        finally:
            first.stop()  # the process is gone: everything in memory is lost
        with serving(SimService(settings)):
            goal = sample_start_pose(scene, np.random.default_rng(11), 0.5)
            bus.publish(keys.stream("r0", keys.PLANNER_GOAL), Goal(episode_id="ep-rs", step=0, pose=goal))
            assert wait_for(lambda: any(f.step == 1 for f in frames), timeout=15.0)
            # the restarted sim took the stored episode up and sent its frame again (EQA_STEP_REDRIVE) first
            *again, f1 = frames[1:]
            assert [(f.episode_id, f.step) for f in again] == [("ep-rs", 0)] * len(again)
            assert f1.episode_id == "ep-rs" and f1.step == 1
            assert (f1.pose.x, f1.pose.y) == (goal.x, goal.y) and f1.scene == SCENE


def test_a_restarted_sim_sends_stored_steps_again_but_not_ended_episodes(hub_settings, settings) -> None:
    """EQA_STEP_RESEND_S: a sim restarted while a goal was lost takes the stored episode up and sends its frame
    again (at most EQA_STEP_RESENDS_MAX times); an episode the stopper ended meanwhile is dropped."""
    from eqa.codec import unpackb
    from eqa.store import episode_end_key, episode_state_key, open_store

    # the timer alone (the re-sends of a taken-up episode on EQA_STEP_REDRIVE are tests/fleet/test_redrive.py's)
    fast = settings.model_copy(update={"step_resend_s": 0.4, "step_resends_max": 2, "step_redrive": False})
    frames: list[Frame] = []
    with Bus(hub_settings, "gateway", "test") as bus:
        for robot in ("r1", "r2"):
            bus.subscribe(keys.stream(robot, keys.SIM_FRAME), Frame, lambda k, m: frames.append(m))
        first = SimService(fast.model_copy(update={"step_resend_s": 0.0}))  # this one never re-sends
        first.start()
        try:
            time.sleep(0.5)
            bus.publish(keys.stream("r1", keys.EPISODE_START), _start("ep-up", "r1", SCENE))
            bus.publish(keys.stream("r2", keys.EPISODE_START), _start("ep-ended", "r2", SCENE))
            assert wait_for(lambda: len(frames) == 2, timeout=15.0)
        finally:
            first.stop()
        with open_store(fast) as store:
            store.set(episode_end_key("ep-ended"), b"{}")  # the stopper ended it while no sim ran
        frames.clear()
        second = SimService(fast)
        second.start()
        try:
            assert wait_for(lambda: len(frames) == 2, timeout=15.0)
            time.sleep(1.5)  # no third resend
            assert [(f.episode_id, f.step) for f in frames] == [("ep-up", 0), ("ep-up", 0)]
            assert second.store.get(episode_state_key("sim", "ep-ended")) is None
            stored = unpackb(second.store.get(episode_state_key("sim", "ep-up")))
            assert stored["robot"] == "r1" and stored["state"]["step"] == 0
        finally:
            second.stop()

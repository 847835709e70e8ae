"""Homes in the mapper: the home map carried over, the view memory bounded and chosen for coverage, the warm
start scored through a real scorer replica over Zenoh with its memory steps decided on by the stopper, a home
continued by a restarted mapper and by a second instance, concurrent episodes in one home merged, and an
episode without a home unchanged."""

from __future__ import annotations

import math
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from support.fleet import wait_for
from support.mapper import home_rig

from eqa import homes, keys
from eqa.budget import warm_step_limit
from eqa.messages import (
    EpisodeEnd,
    EpisodeStart,
    Frame,
    MemoryScore,
    Pose2D,
    StepScores,
    StopConfig,
)
from eqa.settings import Settings
from eqa.store import RedisStore, Store
from eqa_app.evaluation import replay
from services.mapper.episode_map import EpisodeMap
from services.mapper.home_memory import HomeMap, ViewInfo, ViewPool, coverage, select_views
from services.mapper.home_shell import HomeMemory, objects_key, view_key
from services.sim import camera
from services.sim.library import load_or_generate
from services.sim.questions import generate_questions
from services.sim.render import Renderer
from services.stopper.state import CalibrationChoice, EpisodeRecord, decide

ROBOT = "r0"
W, H = 160, 120
SCENE = "gen-00007"


@pytest.fixture(scope="module")
def house(tmp_path_factory: pytest.TempPathFactory):
    scene = load_or_generate(SCENE, Path(tmp_path_factory.mktemp("scenes")))
    question = generate_questions(scene, np.random.default_rng([7, 0, 11]))[0]
    return scene, Renderer(scene), question


def frame_at(renderer: Renderer, episode_id: str, step: int, pose: Pose2D) -> Frame:
    K = camera.intrinsics(W, H)
    T = camera.camera_pose(pose)
    r = renderer.render(T, K, W, H)
    return Frame(episode_id=episode_id, step=step, pose=pose, camera_pose=T, intrinsics=K, rgb=r.rgb, depth=r.depth,
                 instances=r.instances, labels=renderer.labels(r.instances), scene=SCENE)


def turn(pose: Pose2D, step: int) -> Pose2D:
    return Pose2D(x=pose.x, y=pose.y, yaw=pose.yaw + step * math.pi / 3)


def start_of(question, episode_id: str, home: str | None) -> EpisodeStart:
    return EpisodeStart(episode_id=episode_id, robot=ROBOT, question=question, max_steps=20, record=False, seed=3,
                        home=home)


def view(vid: str, cells: list[tuple[int, int]], t: float, nbytes: int = 100) -> ViewInfo:
    return ViewInfo(vid, t, nbytes, np.array(cells, dtype=np.int32).reshape(-1, 2))


# ---- the pure parts -----------------------------------------------------------------------------------------
def test_views_are_chosen_for_coverage_not_recency_within_count_and_bytes() -> None:
    wide = view("wide", [(i, 0) for i in range(10)], t=1.0)
    other_room = view("other", [(i, 5) for i in range(6)], t=2.0)
    # the three newest views all see the same corner of the wide one
    recent = [view(f"new{k}", [(0, 0), (1, 0), (2, 0)], t=10.0 + k) for k in range(3)]
    chosen = select_views([wide, other_room, *recent], max_views=2, max_bytes=10_000)
    assert [v.view_id for v in chosen] == ["wide", "other"]
    assert coverage(chosen) == 16 > coverage(recent[-2:])
    # a third pick adds nothing: not taken even with room left
    assert [v.view_id for v in select_views([wide, other_room, *recent], 5, 10_000)] == ["wide", "other"]
    # ties go to the newer view
    assert select_views(recent, 1, 10_000)[0].view_id == "new2"
    # the byte budget holds: the wide view does not fit, the best that does is taken
    big = view("big", [(i, 0) for i in range(10)], t=1.0, nbytes=500)
    assert [v.view_id for v in select_views([big, other_room], 2, 300)] == ["other"]
    assert select_views([wide], 0, 10_000) == []


def test_view_pool_stays_bounded_and_keeps_the_covering_set() -> None:
    pool = ViewPool(max_views=3, max_bytes=1_000)
    evicted_all: list[str] = []
    for k in range(12):  # a robot turning on the spot: views of overlapping arcs, one wider every 4th
        cells = [(k + i, 0) for i in range(2)] + ([(i, 9) for i in range(8)] if k % 4 == 0 else [])
        _kept, evicted = pool.offer(view(f"v{k}", cells, t=float(k)))
        evicted_all += evicted
        assert len(pool.views) <= 3 and sum(v.nbytes for v in pool.views) <= 1_000
    best = select_views([view(f"v{k}", [(k + i, 0) for i in range(2)] + ([(i, 9) for i in range(8)] if k % 4 == 0
                                                                            else []), float(k)) for k in range(12)],
                        3, 1_000)
    assert coverage(pool.views) >= 0.8 * coverage(best)
    assert len(set(evicted_all)) == len(evicted_all)


def test_home_map_round_trip_and_merge(house) -> None:
    _scene, renderer, q = house
    a = EpisodeMap(start_of(q, "ep-a", "h-a"))
    b = EpisodeMap(start_of(q, "ep-b", "h-a"))
    for k in range(3):
        a.integrate(frame_at(renderer, "ep-a", k, turn(q.start_pose, k)))
        b.integrate(frame_at(renderer, "ep-b", k, turn(q.start_pose, k + 3)))
    ha, hb = HomeMap.from_episode(a), HomeMap.from_episode(b)
    back = HomeMap.from_bytes(ha.to_bytes())
    assert np.array_equal(back.tsdf[back.weight > 0], ha.tsdf[ha.weight > 0])
    assert np.array_equal(back.explored, ha.explored) and np.array_equal(back.traversed, ha.traversed)
    merged = ha.merge(hb)
    assert merged.explored_cells() >= max(ha.explored_cells(), hb.explored_cells())
    assert merged.explored_cells() > ha.explored_cells()  # b looked the other way
    # a fresh episode started from the merged map sees every cell either one explored
    c = EpisodeMap(start_of(q, "ep-c", "h-a"))
    merged.apply_to(c)
    c.integrate(frame_at(renderer, "ep-c", 0, q.start_pose))
    assert c.explored_area_m2() >= max(a.explored_area_m2(), b.explored_area_m2())
    assert c.layer().max() == 0.0  # no question's values carried over


def test_memory_steps_are_decided_before_the_first_move_and_kept_in_the_trace() -> None:
    q = {"text": "Which color?", "choices": ["red", "blue", "green"], "scene": SCENE, "answer": "B"}
    cal = CalibrationChoice(q_hat=1.5, eps=0.2, asked_eps=0.2, n=50, source="test")

    def record() -> EpisodeRecord:
        start = EpisodeStart(episode_id="e", robot=ROBOT, question=q, max_steps=10, stop=StopConfig(rule="cp", eps=0.2),
                             home="h-x")
        rec = EpisodeRecord.from_start(start, ROBOT)
        rec.calibration = cal
        return rec

    vague = MemoryScore(answer_probs=[0.34, 0.33, 0.33], relevance=0.1)
    sure = MemoryScore(answer_probs=[0.02, 0.96, 0.02], relevance=0.95)
    step0 = StepScores(episode_id="e", step=0, answer_probs=[0.4, 0.3, 0.3], relevance=0.2, memory=[vague, sure])
    rec = record()
    d = decide(rec, step0)
    assert d is not None and d.stop and d.answer == "B" and d.step == 0
    assert rec.memory_steps == 2 and rec.last_step == 0
    trace = rec.trace()
    assert trace is not None and trace.memory_steps == 2 and len(trace.steps) == 3
    r = replay(trace, StopConfig(rule="cp", eps=0.2), cal)
    assert r.answer == "B" and r.steps == 1
    # memory that leaves doubt: recorded, then the episode goes on from step 0
    rec = record()
    d = decide(rec, step0.model_copy(update={"memory": [vague]}))
    assert d is not None and not d.stop and rec.memory_steps == 1 and len(rec.probs) == 2
    # memory on a later step is not memory steps (the warm start is the first step only)
    assert decide(rec, StepScores(episode_id="e", step=1, answer_probs=[0.4, 0.3, 0.3], relevance=0.2,
                                  memory=[sure])) is not None and rec.memory_steps == 1
    # an episode without memory: as before
    rec = record()
    decide(rec, step0.model_copy(update={"memory": []}))
    assert rec.memory_steps == 0 and rec.trace().memory_steps == 0


def test_a_warm_step_limit_is_the_episodes_budget_and_its_traces() -> None:
    """StepScores.step_limit at step 0 (the mapper's eqa.budget.warm_step_limit) lowers the episode's max_steps:
    the stopper answers at it with the fallback answer, and the trace says the budget it ran under."""
    q = {"text": "Which color?", "choices": ["red", "blue", "green"], "scene": SCENE, "answer": "B"}
    cal = CalibrationChoice(q_hat=1.5, eps=0.2, asked_eps=0.2, n=50, source="test")
    start = EpisodeStart(episode_id="e", robot=ROBOT, question=q, max_steps=10, stop=StopConfig(rule="cp", eps=0.2),
                         home="h-x")
    vague = [0.34, 0.33, 0.33]
    rec = EpisodeRecord.from_start(start, ROBOT)
    rec.calibration = cal
    d = decide(rec, StepScores(episode_id="e", step=0, answer_probs=vague, relevance=0.1, step_limit=4,
                               memory=[MemoryScore(answer_probs=[0.1, 0.8, 0.1], relevance=0.3)]))
    assert d is not None and not d.stop and rec.max_steps == 4
    for t in (1, 2):
        d = decide(rec, StepScores(episode_id="e", step=t, answer_probs=vague, relevance=0.1, step_limit=2))
        assert d is not None and not d.stop and rec.max_steps == 4  # only step 0 carries the limit
    d = decide(rec, StepScores(episode_id="e", step=3, answer_probs=vague, relevance=0.1))
    assert d is not None and d.stop and "step limit" in d.reason and d.answer == "B"  # the memory's answer
    trace = rec.trace()
    assert trace is not None and trace.max_steps == 4 and trace.full_length
    assert replay(trace, StopConfig(rule="cp", eps=0.2), cal).steps == 4
    # a limit above the episode's own does not raise it; a task keeps its own (its planner ends it)
    rec = EpisodeRecord.from_start(start, ROBOT)
    rec.calibration = cal
    decide(rec, StepScores(episode_id="e", step=0, answer_probs=vague, relevance=0.1, step_limit=50))
    assert rec.max_steps == 10
    rec = EpisodeRecord.from_start(start, ROBOT)
    rec.calibration, rec.task = cal, True
    decide(rec, StepScores(episode_id="e", step=0, answer_probs=vague, relevance=0.1, step_limit=3))
    assert rec.max_steps == 10


def fake_scorer(calls: list):
    from eqa.messages import ScoreResult

    def score(req):
        calls.append(req)
        return ScoreResult(request_id=req.request_id, episode_id=req.episode_id, step=req.step,
                           answer_probs=[0.25] * 4, relevance=0.3, lsv=[0.5] * len(req.prompt_points), gsv=0.5,
                           backend="test")

    return score


def test_concurrent_episodes_in_one_home_merge(house, store: Store, tmp_path: Path) -> None:
    _scene, renderer, q = house
    settings = Settings(data_dir=tmp_path / "var", home_max_views=4)
    calls: list = []
    memory = HomeMemory(settings, lambda: store, lambda: fake_scorer(calls))
    maps = {}
    for eid in ("ep-x", "ep-y"):  # both start before either ends: base version 0
        em = EpisodeMap(start_of(q, eid, "h-c"))
        memory.start(em.start, em)
        maps[eid] = em
    for k in range(3):
        for eid, offset in (("ep-x", 0), ("ep-y", 3)):
            f = frame_at(renderer, eid, k, turn(q.start_pose, k + offset))
            maps[eid].integrate(f)
            memory.offer_view(maps[eid], f)
    first = memory.commit(maps["ep-x"])
    second = memory.commit(maps["ep-y"])
    assert first is not None and second is not None and (first.version, second.version) == (1, 2)
    stored = memory.read_map("h-c")
    assert stored is not None
    x, y = HomeMap.from_episode(maps["ep-x"]), HomeMap.from_episode(maps["ep-y"])
    assert stored.explored_cells() == x.merge(y).explored_cells() > max(x.explored_cells(), y.explored_cells())
    assert len(second.views) <= 4 and {v.episode_id for v in second.views} == {"ep-x", "ep-y"}
    # only the kept views are stored; the summary says what the home holds
    stored_views = [k for k in store.keys(homes.prefix("h-c") + "view:")]
    assert sorted(stored_views) == sorted(view_key("h-c", v.view_id) for v in second.views)
    summary = homes.read_summary(store, "h-c")
    assert summary is not None and summary.episodes == 2 and summary.views == len(second.views)
    assert summary.bytes == second.map_bytes + second.view_bytes and summary.scenes == [SCENE]
    assert calls == []  # nothing scored: neither episode started warm
    assert homes.delete_home(store, "h-c", 60.0) >= 3 and memory.read_index("h-c") is None


def test_a_task_in_a_home_searches_on_the_remembered_geometry_with_its_own_frontiers(
        house, store: Store, tmp_path: Path) -> None:
    """A question in a home starts from the explored map (its view memory guides it); a task in a home whose
    earlier episodes asked no detector for its class (here: a question only) starts from the geometry only: at its
    first frame it has the frontiers a cold task has there (the explored home map would send it past places whose
    objects it never detected, to the edges of what earlier episodes saw), no memory steps and its own step
    budget."""
    from eqa.messages import Task

    _scene, renderer, q = house
    memory = HomeMemory(Settings(data_dir=tmp_path / "var"), lambda: store, lambda: fake_scorer([]))
    homes.delete_home(store, "h-t", 60.0)
    first = EpisodeMap(start_of(q, "ep-t1", "h-t"))
    memory.start(first.start, first)
    for k in range(6):  # a full turn on the spot: all around the start is explored
        f = frame_at(renderer, "ep-t1", k, turn(q.start_pose, k))
        first.integrate(f)
        memory.offer_view(first, f)
    assert memory.commit(first) is not None
    task = Task(kind="find_object", text="Find a mug", scene=SCENE, object="mug")

    def first_frame(eid: str, home: str | None, with_task: bool) -> EpisodeMap:
        start = start_of(q, eid, home)
        if with_task:
            start = start.model_copy(update={"task": task})
        em = EpisodeMap(start)
        memory.start(start, em)
        em.integrate(frame_at(renderer, eid, 0, q.start_pose))
        return em

    cold = first_frame("ep-cold-task", None, True)
    warm_task = first_frame("ep-t2", "h-t", True)
    warm_question = first_frame("ep-t3", "h-t", False)
    n_cold = len(cold.find_frontier_candidates())
    assert n_cold >= 1
    assert len(warm_task.find_frontier_candidates()) >= n_cold - 1  # cold's frontiers (give or take a merge)
    assert warm_task.explored_area_m2() == pytest.approx(cold.explored_area_m2(), rel=0.05)
    assert warm_question.explored_area_m2() > 1.5 * cold.explored_area_m2()
    ep_task, ep_question = memory.episodes["ep-t2"], memory.episodes["ep-t3"]
    assert ep_task.warm_ids == [] and ep_task.step_limit is None and ep_task.loaded_cells == 0
    assert ep_question.warm_ids and ep_question.loaded_cells > 0
    # its end writes its frames into the home without forgetting what the earlier episode explored
    before = memory.read_map("h-t")
    assert before is not None and memory.commit(warm_task) is not None
    after = memory.read_map("h-t")
    assert after is not None and after.explored_cells() >= before.explored_cells()
    assert after.explored_cells() > HomeMap.from_episode(warm_task).explored_cells()
    homes.delete_home(store, "h-t", 60.0)


def test_a_reset_after_the_episode_ended_is_not_undone_by_its_write_back(house, store: Store, tmp_path: Path) -> None:
    """The gateway resets a home once no episode of it is queued or running, but the mapper writes an ended
    episode back a moment later: that write must not bring the emptied home's memory back."""
    _scene, renderer, q = house
    memory = HomeMemory(Settings(data_dir=tmp_path / "var"), lambda: store, lambda: fake_scorer([]))
    homes.delete_home(store, "h-r", 60.0)
    em = EpisodeMap(start_of(q, "ep-r", "h-r"))
    memory.start(em.start, em)
    for k in range(3):
        f = frame_at(renderer, "ep-r", k, turn(q.start_pose, k))
        em.integrate(f)
        memory.offer_view(em, f)
    assert store.keys(homes.prefix("h-r") + "view:")  # its candidate views are stored as it runs
    homes.delete_home(store, "h-r", 60.0)  # the user's reset, after the episode's end
    assert memory.commit(em) is None
    assert store.keys(homes.prefix("h-r")) == [] and memory.read_index("h-r") is None
    # an episode started after the reset is remembered as usual
    em2 = EpisodeMap(start_of(q, "ep-r2", "h-r"))
    memory.start(em2.start, em2)
    f = frame_at(renderer, "ep-r2", 0, q.start_pose)
    em2.integrate(f)
    memory.offer_view(em2, f)
    index = memory.commit(em2)
    assert index is not None and index.version == 1 and {v.episode_id for v in index.views} == {"ep-r2"}
    homes.delete_home(store, "h-r", 60.0)


def test_a_reset_waits_for_a_write_back_in_progress_and_deletes_nothing_when_it_lasts(store: Store) -> None:
    home = "h-busy"
    store.delete(homes.reset_key(home))  # a token of an earlier run in the same store
    store.set(homes.summary_key(home), b"{}")
    assert homes.take_lock(store, home, "mapper-1", 0.0)  # a mapper writing an episode back
    t0 = time.monotonic()
    with pytest.raises(homes.HomeBusyError, match="being written"):
        homes.delete_home(store, home, 60.0, wait_s=0.3)
    assert time.monotonic() - t0 >= 0.3
    assert store.get(homes.summary_key(home)) == b"{}" and homes.reset_mark(store, home) is None  # nothing lost
    store.delete(homes.lock_key(home))
    assert homes.delete_home(store, home, 60.0) == 1 and store.keys(homes.prefix(home)) == []
    assert homes.reset_mark(store, home) is not None


def test_an_expired_home_lock_released_late_leaves_the_next_holders_lock(store: Store, monkeypatch) -> None:
    home = "h-lock"
    monkeypatch.setattr(homes, "LOCK_TTL_S", 0.3)
    with homes.locked(store, home, "mapper-1", 0.0) as first:
        assert first is not None
        time.sleep(0.4)  # held past the TTL: the lock expired
        second = homes.take_lock(store, home, "mapper-2", 0.0)
        assert second is not None and second != first
    # mapper-1's block ended: its release named its own token and left mapper-2's lock
    assert store.get(homes.lock_key(home)) == second.encode()
    assert homes.take_lock(store, home, "reset", 0.0) is None
    assert homes.release_lock(store, home, second) and store.get(homes.lock_key(home)) is None


class _SlowCommitStore(RedisStore):
    """A real Redis store whose first read of one key waits for an event: a mapper whose commit stalls (a slow
    store, a paused process) after it read the home's index, past the lock's TTL."""

    def __init__(self, url: str, slow_key: str, go: threading.Event) -> None:
        super().__init__(url)
        self.slow_key, self.go, self.stalled = slow_key, go, threading.Event()

    def get(self, key: str) -> bytes | None:
        if key == self.slow_key and not self.stalled.is_set():
            self.stalled.set()
            assert self.go.wait(20.0)
        return super().get(key)


def test_a_commit_slower_than_the_lock_ttl_merges_what_was_committed_meanwhile(
        house, redis_url: str, tmp_path: Path, monkeypatch) -> None:
    """Two mapper instances end episodes of one home; the first stalls inside its commit (after reading the
    index) longer than the lock's TTL, so the second takes the expired lock and commits. The first must not
    write over that commit: its write is refused (the index changed) and it commits again, merging both."""
    _scene, renderer, q = house
    home = "h-slow"
    monkeypatch.setattr(homes, "LOCK_TTL_S", 0.5)
    settings = Settings(data_dir=tmp_path / "var", home_max_views=4)
    go = threading.Event()
    slow = _SlowCommitStore(redis_url, objects_key(home), go)
    fast = RedisStore(redis_url)
    try:
        fast.delete_many([*fast.keys(homes.prefix(home)), homes.reset_key(home)])
        a = HomeMemory(settings.model_copy(update={"instance": "mapper-a"}), lambda: slow, lambda: fake_scorer([]))
        b = HomeMemory(settings.model_copy(update={"instance": "mapper-b"}), lambda: fast, lambda: fake_scorer([]))
        maps = {}
        for eid, mem in (("ep-a", a), ("ep-b", b)):  # both start from the empty home
            em = EpisodeMap(start_of(q, eid, home))
            mem.start(em.start, em)
            maps[eid] = em
        for k in range(3):
            for eid, mem, offset in (("ep-a", a, 0), ("ep-b", b, 3)):
                f = frame_at(renderer, eid, k, turn(q.start_pose, k + offset))
                maps[eid].integrate(f)
                mem.offer_view(maps[eid], f)
        done: dict[str, object] = {}
        t = threading.Thread(target=lambda: done.setdefault("a", a.commit(maps["ep-a"])))
        t.start()
        assert slow.stalled.wait(20.0)  # a holds the lock and has read the index (version 0)
        second = b.commit(maps["ep-b"])  # waits for a's lock to expire, then commits
        assert second is not None and second.version == 1
        go.set()
        t.join(30.0)
        first = done["a"]
        assert first is not None and first.version == 2 and first.episodes == 2  # b's commit kept, not overwritten
        assert {v.episode_id for v in first.views} == {"ep-a", "ep-b"}
        stored = a.read_map(home)
        x, y = HomeMap.from_episode(maps["ep-a"]), HomeMap.from_episode(maps["ep-b"])
        assert stored is not None and stored.explored_cells() == y.merge(x).explored_cells()
        assert fast.get(homes.lock_key(home)) is None
        assert homes.delete_home(fast, home, 60.0) >= 3
    finally:
        go.set()
        slow.close()
        fast.close()


# ---- the service over Zenoh ---------------------------------------------------------------------------------
def end(episode_id: str, steps: int) -> EpisodeEnd:
    return EpisodeEnd(episode_id=episode_id, robot=ROBOT, state="stopped", reason="test", steps=steps)


def test_home_carried_over_warm_started_through_a_scorer_replica_and_continued_elsewhere(
        hub_settings: Settings, settings: Settings, house, redis_url: str) -> None:
    _scene, renderer, q = house
    settings = settings.model_copy(update={"redis_url": redis_url, "scorer_replica": "homes", "home_max_views": 3,
                                           "home_warm_budget": 0.3})
    home = homes.home_id("tenant-a", "kitchen-house")
    with home_rig(hub_settings, settings, home) as rig:  # the oracle scorer: simulated perception model, not a VLM
        bus, out, mapper = rig.bus, rig.out, rig.mapper
        store = mapper.store
        # episode 1 in the home: four views turning on the spot, then its end writes the home
        bus.publish(keys.stream(ROBOT, keys.EPISODE_START), start_of(q, "ep-h1", home))
        for k in range(4):
            bus.publish(keys.stream(ROBOT, keys.SIM_FRAME), frame_at(renderer, "ep-h1", k, turn(q.start_pose, k)))
            m, s = out.step(k)
            assert s.memory == [] and s.warm is None  # nothing to remember yet: the first question is a cold one
        first_area = m.explored_area_m2
        bus.publish(keys.stream(ROBOT, keys.EPISODE_END), end("ep-h1", 4))
        # the commit writes the index, then the summary: wait for the last of them
        assert wait_for(lambda: homes.read_summary(store, home) is not None, timeout=20)
        index = mapper.homes.read_index(home)
        assert index is not None and index.version == 1 and 1 <= len(index.views) <= 3
        summary = homes.read_summary(store, home)
        assert summary is not None and summary.views == len(index.views) and summary.episodes == 1

        # episode 2 in the home: step 0 starts from the stored map and re-scores the memory through the replica
        bus.publish(keys.stream(ROBOT, keys.EPISODE_START), start_of(q, "ep-h2", home))
        bus.publish(keys.stream(ROBOT, keys.SIM_FRAME), frame_at(renderer, "ep-h2", 0, q.start_pose))
        m0, s0 = out.step(0)
        assert m0.explored_area_m2 == pytest.approx(first_area, rel=0.02)
        assert len(s0.memory) == len(index.views) and s0.backend == "oracle"
        assert all(len(mm.answer_probs) == len(q.choices) and 0 <= mm.relevance <= 1 for mm in s0.memory)
        assert [mm.seen_at for mm in s0.memory] == sorted(mm.seen_at for mm in s0.memory)
        # its budget: appendix B's for the floor the home map left (20 steps stand for 44.4 m2), at least 6
        explored_m2 = mapper.homes.episodes["ep-h2"].loaded_cells * m0.grid.resolution ** 2
        assert explored_m2 > 0 and s0.step_limit == warm_step_limit(20, explored_m2, 0.3) < 20
        # a warm start, with the bounds its memory steps and budget were made with (the stopper's table check)
        assert s0.warm is not None and s0.warm.version == 1
        assert (s0.warm.bounds.max_views, s0.warm.bounds.warm_budget) == (3, 0.3)
        assert out.errors.empty(), out.errors.get()

        # the cold reference: the same frame without a home sees only itself, no memory steps, no home keys
        before = sorted(store.keys(homes.PREFIX))
        bus.publish(keys.stream(ROBOT, keys.EPISODE_START), start_of(q, "ep-cold", None))
        bus.publish(keys.stream(ROBOT, keys.SIM_FRAME), frame_at(renderer, "ep-cold", 0, q.start_pose))
        c0, cs0 = out.step(0)
        ref = EpisodeMap(start_of(q, "ep-ref", None))
        ref.integrate(frame_at(renderer, "ep-ref", 0, q.start_pose))
        assert c0.explored_area_m2 == pytest.approx(ref.explored_area_m2())
        assert c0.explored_area_m2 < m0.explored_area_m2
        assert cs0.memory == [] and cs0.step_limit is None and cs0.warm is None
        bus.publish(keys.stream(ROBOT, keys.EPISODE_END), end("ep-cold", 1))
        assert mapper.drain()
        time.sleep(0.3)
        assert sorted(store.keys(homes.PREFIX)) == before

        # the mapper dies mid-episode; a new instance continues episode 2 from the store and commits it
        mapper.stop()
        other = rig.instance(settings.model_copy(update={"instance": "mapper-b"}))
        bus.publish(keys.stream(ROBOT, keys.SIM_FRAME), frame_at(renderer, "ep-h2", 1, turn(q.start_pose, 4)))
        m1, s1 = out.step(1)
        assert s1.memory == [] and s1.step_limit is None and s1.warm is None
        assert m1.explored_area_m2 >= m0.explored_area_m2
        assert other.homes.step_limit("ep-h2") == s0.step_limit  # carried with the episode's state
        # the candidate keyframe of step 0 came over with the episode's state (cells read back from the store)
        pool = other.homes.episodes["ep-h2"].pool.views
        assert {v.view_id for v in pool} == {"ep-h2-0", "ep-h2-1"} and all(len(v.cells) for v in pool)
        bus.publish(keys.stream(ROBOT, keys.EPISODE_END), end("ep-h2", 2))
        deadline = time.time() + 20
        while (mapper_index := other.homes.read_index(home)) is not None and mapper_index.version < 2 \
                and time.time() < deadline:
            time.sleep(0.05)
        index2 = other.homes.read_index(home)
        assert index2 is not None and index2.version == 2 and len(index2.views) <= 3
        assert index2.episodes == 2
        stored = other.homes.read_map(home)
        assert stored is not None and stored.explored_cells() >= HomeMap.from_bytes(
            store.get(homes.prefix(home) + "map")).explored_cells()
        assert out.errors.empty(), out.errors.get()


def test_bench_sequences_are_one_house_round_robin_over_categories(tmp_path: Path) -> None:
    from eqa_app.home_bench import sequence

    qs = sequence(11, 0, 5, tmp_path)
    assert len(qs) == 5 and len({q.scene for q in qs}) == 1 and len({q.category for q in qs}) == 5
    assert [q.id for q in sequence(11, 0, 7, tmp_path)][:5] == [q.id for q in qs]  # the same order, longer


def test_bench_changes_ask_each_question_in_the_changed_house_with_its_ground_truth(tmp_path: Path) -> None:
    from eqa_app.home_bench import changed_sequence, impacts
    from services.sim.change_impact import impact, rederive
    from services.sim.changes import changes_of

    pairs = changed_sequence(11, 2, 3, tmp_path, changes=2)
    assert [a.scene for a, _ in pairs] == ["gen-110002", "gen-110002-c2", "gen-110002-c4"]
    order = [q.id for q, _ in changed_sequence(11, 2, 10, tmp_path)]  # unchanged: the asked ones are the base ones
    ranks = [order.index(b.id) for _, b in pairs]
    assert ranks == sorted(ranks) and ranks[0] == 0  # in the benchmark's order (one without truth passed over)
    assert [a.id for a, _ in pairs][1:] == [f"{b.id}-c{k}" for (_, b), k in zip(pairs[1:], (2, 4), strict=True)]
    base = load_or_generate("gen-110002", tmp_path)
    made = changes_of(base, 4)
    for (asked, q), imp in zip(pairs, impacts(pairs, tmp_path, 2), strict=True):
        if imp["k"]:
            house = load_or_generate(asked.scene, tmp_path)
            assert asked.answer == rederive(q, house).answer  # the changed house's truth is what is scored
            truth = impact(q, [c for c in made if c.round <= imp["k"]], house)
            assert (imp["affected"], imp["answer_changed"]) == (truth.affected, truth.answer_changed)
            assert imp["answer_changed"] == (asked.answer != q.answer)


def test_bench_wrong_singletons_are_paired_on_the_same_questions() -> None:
    from eqa_app.home_bench import singletons, wrong_singleton

    assert wrong_singleton(("B",), "A") and not wrong_singleton(("A",), "A") and not wrong_singleton(("A", "B"), "B")
    rows = [{"cold_wrong_singleton": c, "warm_wrong_singleton": w, "cold_correct": not c, "warm_correct": not w}
            for c, w in [(False, True)] * 5 + [(True, True), (False, False), (True, False)]]
    res = singletons(rows)
    assert res["n"] == 8 and res["warm_wrong_singleton"] == 6 / 8 and res["cold_wrong_singleton"] == 2 / 8
    assert (res["paired"]["warm_only"], res["paired"]["cold_only"]) == (5, 1)
    assert res["paired"]["diff"] == pytest.approx(4 / 8) and 0 < res["paired"]["p_value"] < 0.25
    assert singletons([]) == {"n": 0}


def test_budget_matched_cold_is_the_cold_trace_answered_at_the_warm_limit() -> None:
    """The headline's comparison: a cold trace that would stop at step 9 under its own budget, cut at a warm limit
    of 4, answers at step 4 with the fallback answer; a limit above its own budget changes nothing; a warm trace is
    refused."""
    from eqa_app.home_bench import budget_matched, matched, paired
    from services.stopper.calibration import Trace, TraceStep

    vague, sure = TraceStep(answer_probs=[0.3, 0.3, 0.2, 0.2], relevance=0.9), TraceStep(
        answer_probs=[0.97, 0.01, 0.01, 0.01], relevance=0.9)
    cold = Trace(question_id="q", scene="s", choices=["a", "b", "c", "d"], answer="A", max_steps=20, strategy="fbe",
                 steps=[vague] * 8 + [sure] * 12)
    stop, cal = StopConfig(rule="cp", eps=0.2), CalibrationChoice(q_hat=1.8, eps=0.2, asked_eps=0.2, n=10, source="t")
    assert replay(cold, stop, cal).steps == 9
    cut = replay(budget_matched(cold, 4), stop, cal)
    assert cut.steps == 4 and cut.max_steps == 4 and len(cut.prediction_set) > 1
    assert replay(budget_matched(cold, 50), stop, cal) == replay(cold, stop, cal)
    with pytest.raises(ValueError, match="memory steps"):
        budget_matched(cold.model_copy(update={"memory_steps": 2}), 4)
    rows = [{"cold_steps": 20, "warm_steps": 4, "matched_steps": 5, "cold_correct": True, "warm_correct": True,
             "matched_correct": False, "memory_steps": 3}] * 4
    res = paired(matched(rows))
    assert res["steps_ratio"] == pytest.approx(0.8) and res["success_paired"]["warm_only"] == 4


def test_bench_task_metrics_are_paired_on_the_tasks_that_have_them() -> None:
    """``eqa bench home --tasks``: a pick-and-place metric is compared on the tasks that have it (an object search
    has no FindObj), warm against cold on the same task."""
    from eqa_app.home_bench import metric_pairs
    from eqa_app.stats import sign_test_p

    rows = [{"cold_FindObj": 1.0, "warm_FindObj": 0.0}, {"cold_FindObj": 0.0, "warm_FindObj": 1.0},
            {"cold_FindObj": 0.0, "warm_FindObj": 1.0}, {"cold_FindObj": 1.0, "warm_FindObj": 1.0}, {}]
    r = metric_pairs(rows, "FindObj")
    assert (r["n"], r["cold"], r["warm"], r["warm_only"], r["cold_only"]) == (4, 0.5, 0.75, 2, 1)
    assert r["p_value"] == sign_test_p(2, 1) and r["cold_ci"][0] < 0.5 < r["cold_ci"][1]
    assert metric_pairs([{}], "Pick") == {"n": 0}

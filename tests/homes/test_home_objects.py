"""A home's HELIOS object layer across task episodes (services/mapper/home_objects.py, home_shell.py): class-keyed
evidence carried over by the rule of HELIOS Eq. 3-5 (checked against hand-computed Dirichlet counts), the layer
through the store (embedded and Redis), concurrent commits merged, bounds and hostile parts, the floor counted
explored only for classes a detector was asked for, a restarted mapper continuing a task's home part."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from eqa import homes
from eqa.messages import DetectResult, EpisodeStart, Frame, Pose2D, Question, StopConfig, Task
from eqa.settings import Settings
from eqa.store import Store
from services.mapper.episode_map import EpisodeMap, MapperConfig
from services.mapper.home_objects import (
    MAX_VOCABULARIES,
    FloorMask,
    HomeObjects,
    commit_layer,
    vocabulary,
)
from services.mapper.home_shell import HomeMemory, objects_base_key, objects_key
from services.mapper.object_map import ObjectMap, ObjectMapConfig
from services.mapper.object_shell import task_map_config

PRIOR = 1.0


def one(gamma: list[float], uid: int = -1) -> dict[str, np.ndarray]:
    return {"uid": np.array([uid], np.int64), "means": np.array([[1.0, 2.0, 0.5]], np.float32),
            "sigma": np.array([0.05], np.float32), "opacity": np.array([0.8], np.float32),
            "gamma": np.array([gamma], np.float32)}


def commit(base: HomeObjects | None, a: dict[str, np.ndarray], classes: list[str], eid: str,
           explored: FloorMask | None = None) -> HomeObjects:
    return commit_layer(base, a["uid"], a["means"], a["sigma"], a["opacity"], a["gamma"], classes, PRIOR, eid,
                        100.0, explored)


# ---- the carry-over rule (pure) -----------------------------------------------------------------------------
def test_evidence_carries_over_by_class_name_and_other_is_evidence_only_against_classes_asked() -> None:
    """Hand-computed Dirichlet counts (Eq. 3 sums, prior 1):

    task 1 asks {mug, table}; the Gaussian ends at gamma (mug 7, table 1, other 4): evidence mug 6, table 0,
    other 3 under vocabulary {mug, table}.
    task 2 asks {mug}: mug = 1 + 6 = 7; other = 1 + 3 (other under a vocabulary holding mug) + 0 (table) = 4.
    task 2' asks {cup}: cup never asked, {mug, table} does not hold cup: cup 1, other 1 (uniform: nothing says
    the Gaussian is not a cup; the 6 mug pixels are not evidence against cup either, the detector was not asked).
    task 2'' asks {mug, cup}: mug 7, cup 1, other 1 ({mug, table} does not hold cup: its other is ambiguous).
    task 2''' asks {table}: table 1, other 1 + 3 + 6 (mug pixels were mug rather than table) = 10."""
    first = commit(None, one([7.0, 1.0, 4.0]), ["mug", "table"], "ep-1")
    assert len(first) == 1 and first.uid[0] >= 0
    np.testing.assert_allclose(first.gamma_for(["mug"], PRIOR), [[7.0, 4.0]])
    np.testing.assert_allclose(first.gamma_for(["cup"], PRIOR), [[1.0, 1.0]])
    np.testing.assert_allclose(first.gamma_for(["mug", "cup"], PRIOR), [[7.0, 1.0, 1.0]])
    np.testing.assert_allclose(first.gamma_for(["table"], PRIOR), [[1.0, 10.0]])
    np.testing.assert_allclose(first.gamma_for(["table", "mug"], PRIOR), [[1.0, 7.0, 4.0]])  # order of the task

    # task 2 asks {cup} and ends at (cup 1, other 6): +5 other under {cup}, the mug evidence untouched
    restored = first.gamma_for(["cup"], PRIOR)
    second = commit(first, one([1.0, restored[0, 1] + 5.0], int(first.uid[0])), ["cup"], "ep-2")
    assert len(second) == 1  # the same Gaussian (its home id), not a second one
    np.testing.assert_allclose(second.gamma_for(["cup"], PRIOR), [[1.0, 6.0]])
    np.testing.assert_allclose(second.gamma_for(["mug"], PRIOR), [[7.0, 4.0]])  # {cup}'s other: not against mug
    np.testing.assert_allclose(second.gamma_for(["mug", "cup"], PRIOR), [[7.0, 1.0, 1.0]])
    # task 3 asks {mug, cup}, sees the mug again: +3 mug, +1 other under {cup, mug}
    third = commit(second, one([7.0 + 3.0, 1.0, 1.0 + 1.0], int(first.uid[0])), ["mug", "cup"], "ep-3")
    np.testing.assert_allclose(third.gamma_for(["mug", "cup"], PRIOR), [[10.0, 1.0, 2.0]])
    np.testing.assert_allclose(third.gamma_for(["mug"], PRIOR), [[10.0, 5.0]])  # 1 + 3 + 1 other
    np.testing.assert_allclose(third.gamma_for(["cup"], PRIOR), [[1.0, 1.0 + 5.0 + 1.0 + 3.0]])
    assert third.vocabularies == [("mug", "table"), ("cup",), ("cup", "mug")]


def test_a_task_starts_with_the_gaussians_holding_evidence_for_one_of_its_classes() -> None:
    """A Gaussian without evidence for any class of the task would be a candidate at S = 1/2 with the flat prior
    (Eq. 4, 7): it is not restored; one with evidence for a class of the task is, with the rule's counts."""
    h = commit(None, {k: np.concatenate([v, w]) for (k, v), w in zip(
        one([7.0, 1.0, 4.0]).items(), one([1.0, 1.0, 9.0]).values(), strict=True)}, ["mug", "table"], "ep-1")
    keep, gamma = h.restorable(["mug"], PRIOR)
    np.testing.assert_array_equal(keep, [0])
    np.testing.assert_allclose(gamma, [[7.0, 4.0]])
    keep, gamma = h.restorable(["cup"], PRIOR)
    assert len(keep) == 0 and gamma.shape == (0, 2)
    keep, _ = h.restorable(["cup", "mug"], PRIOR)
    np.testing.assert_array_equal(keep, [0])


def test_concurrent_commits_keep_both_episodes_evidence_whole_in_either_order() -> None:
    """Two tasks start from one stored layer (4 mug pixels' evidence on a Gaussian): ep-a adds 3 mug and a new
    Gaussian, ep-b 1 mug and 1 other. Whichever ends first, the second adds its own evidence (end minus start)
    onto what the first stored: 4 + 3 + 1 mug and 1 other, the shared Gaussian once, ep-a's new one kept."""
    base = commit(None, one([5.0, 1.0]), ["mug"], "ep-0")
    uid = int(base.uid[0])
    a_end = {k: np.concatenate([v, w]) for (k, v), w in zip(one([8.0, 1.0], uid).items(), one([1.0, 3.0]).values(),
                                                             strict=True)}
    b_end = one([6.0, 2.0], uid)

    def after(first: tuple[dict[str, np.ndarray], str], second: tuple[dict[str, np.ndarray], str]) -> HomeObjects:
        stored = commit(base, first[0], ["mug"], first[1])
        x = second[0]
        return commit_layer(base, x["uid"], x["means"], x["sigma"], x["opacity"], x["gamma"], ["mug"], PRIOR,
                            second[1], 100.0, None, onto=stored)

    for out in (after((a_end, "ep-a"), (b_end, "ep-b")), after((b_end, "ep-b"), (a_end, "ep-a"))):
        assert len(out) == 2
        row = int(np.nonzero(out.uid == uid)[0][0])
        np.testing.assert_allclose(out.gamma_for(["mug"], PRIOR)[row], [1.0 + 4.0 + 3.0 + 1.0, 1.0 + 1.0])
        new = int(np.nonzero(out.uid != uid)[0][0])
        np.testing.assert_allclose(out.gamma_for(["mug"], PRIOR)[new], [1.0, 3.0])
    # the same as one after the other: ep-b started from what ep-a stored and added the same evidence
    seq = commit(commit(base, a_end, ["mug"], "ep-a"), one([6.0 + 3.0, 2.0], uid), ["mug"], "ep-b")
    row = int(np.nonzero(seq.uid == uid)[0][0])
    np.testing.assert_allclose(seq.gamma_for(["mug"], PRIOR)[row], [9.0, 2.0])


def test_a_gaussian_the_bounds_dropped_meanwhile_comes_back_with_the_episodes_own_evidence() -> None:
    base = commit(None, one([5.0, 1.0]), ["mug"], "ep-0")
    uid = int(base.uid[0])
    stored = base.select(np.zeros(0, dtype=np.int64))  # another episode's commit left it out (bounds)
    x = one([7.0, 1.0], uid)
    out = commit_layer(base, x["uid"], x["means"], x["sigma"], x["opacity"], x["gamma"], ["mug"], PRIOR, "ep-1",
                       100.0, None, onto=stored)
    assert list(out.uid) == [uid]
    np.testing.assert_allclose(out.gamma_for(["mug"], PRIOR), [[1.0 + 2.0, 1.0]])


def test_explored_floor_counts_only_for_classes_asked_for_all_of_them() -> None:
    m1 = FloorMask(0.1, 0.0, 0.0, np.ones((4, 4), bool))
    m2 = FloorMask(0.1, 0.2, 0.0, np.ones((4, 4), bool))
    h = commit(None, one([2.0, 1.0]), ["mug"], "ep-1", m1)
    h = commit(h, one([1.0, 1.0]), ["sofa"], "ep-2", m2)
    assert h.explored_for(["mug"]).cells() == 16
    both = h.explored_for(["mug", "sofa"])
    assert both is not None and both.cells() == 8  # the overlap: columns 2..3 of mug's grid
    assert h.explored_for(["mug", "cup"]) is None  # cup never looked for: nothing counts as explored
    union = m1.union(m2)
    assert union.mask.shape == (4, 6) and union.cells() == 24


def test_bounds_hold_and_hostile_parts_are_refused() -> None:
    rng = np.random.default_rng(0)
    n = 50
    a = {"uid": np.full(n, -1, np.int64), "means": rng.normal(size=(n, 3)).astype(np.float32),
         "sigma": np.full(n, 0.05, np.float32), "opacity": np.full(n, 0.8, np.float32),
         "gamma": (1.0 + rng.uniform(0, 5, size=(n, 2))).astype(np.float32)}
    h = None
    for k in range(MAX_VOCABULARIES + 3):
        h = commit(h, a, [f"class{k}"], f"ep-{k}", FloorMask(0.1, 0.0, 0.0, np.ones((2, 2), bool)))
    assert h is not None and len(h.vocabularies) == MAX_VOCABULARIES + 3
    b = h.bounded(10)
    assert len(b) == 10 and len(b.vocabularies) == MAX_VOCABULARIES
    assert set(b.explored) == {c for v in b.vocabularies for c in v}  # floors of dropped class sets go too
    assert all(v in b.vocabularies for v, _ in b.columns)
    back = HomeObjects.from_bytes(b.to_bytes())
    np.testing.assert_array_equal(back.uid, b.uid)
    np.testing.assert_allclose(back.evidence, b.evidence)
    # hostile: negative evidence, repeated ids, a column of no vocabulary, an unknown version
    bad = b.select(np.arange(2))
    for broken in (
        HomeObjects(bad.uid, bad.means, bad.sigma, bad.opacity, bad.seen, bad.columns, -bad.evidence - 1,
                    {}, bad.vocabularies),
        HomeObjects(np.zeros(2, np.int64), bad.means, bad.sigma, bad.opacity, bad.seen, bad.columns, bad.evidence,
                    {}, bad.vocabularies),
        HomeObjects(bad.uid, bad.means, bad.sigma, bad.opacity, bad.seen, [(("zz",), "other")] * len(bad.columns),
                    bad.evidence, {}, bad.vocabularies),
    ):
        with pytest.raises(ValueError):
            HomeObjects.from_bytes(broken.to_bytes())
    with pytest.raises(ValueError):
        HomeObjects.from_bytes(b"\x93\x01\x02\x03")
    with pytest.raises(ValueError):
        vocabulary(["other"])


# ---- through the mapper's home memory and the store ---------------------------------------------------------
SCENE = "gen-00007"
W, H = 160, 120


@pytest.fixture(scope="module")
def house(tmp_path_factory: pytest.TempPathFactory):
    from services.sim.library import load_or_generate
    from services.sim.render import Renderer

    scene = load_or_generate(SCENE, Path(tmp_path_factory.mktemp("scenes")))
    return scene, Renderer(scene)


def frame_at(renderer, episode_id: str, step: int, pose: Pose2D) -> Frame:
    from services.sim import camera

    K = camera.intrinsics(W, H)
    T = camera.camera_pose(pose)
    r = renderer.render(T, K, W, H)
    return Frame(episode_id=episode_id, step=step, pose=pose, camera_pose=T, intrinsics=K, rgb=r.rgb, depth=r.depth,
                 instances=r.instances, labels=renderer.labels(r.instances), scene=SCENE)


def seen_object(scene, renderer) -> tuple[str, Pose2D]:
    """A category of a small object the start pose's full turn shows (the ground-truth detector sees it)."""
    from services.sim.questions import generate_questions

    pose = generate_questions(scene, np.random.default_rng([7, 0, 11]))[0].start_pose
    counts: dict[str, int] = {}
    for k in range(6):
        f = frame_at(renderer, "probe", k, Pose2D(x=pose.x, y=pose.y, yaw=pose.yaw + k * math.pi / 3))
        for lb in f.labels:
            px = int((f.instances == lb.id).sum())
            if px >= 30 and lb.category not in ("wall", "floor", "ceiling", "door", "window"):
                counts[lb.category] = counts.get(lb.category, 0) + px
    assert counts, "the probe pose sees no object"
    return max(counts, key=lambda c: counts[c]), pose


class GroundTruthDetector:
    """A detector reading the frame's simulator labels (what the camera shows, nothing else): every visible
    instance of an asked class, with its mask. The bench uses the seeded simulated detector; this one makes the
    counts of a test exact."""

    def __init__(self) -> None:
        self.calls: list = []

    def __call__(self, req):
        from eqa.messages import Detection

        self.calls.append(req)
        dets = []
        for lb in req.labels:
            if lb.category in req.classes:
                mask = np.asarray(req.instances) == lb.id
                if mask.sum() >= 4:
                    ys, xs = np.nonzero(mask)
                    y0, y1, x0, x1 = int(ys.min()), int(ys.max()) + 1, int(xs.min()), int(xs.max()) + 1
                    dets.append(Detection(cls=lb.category, score=0.9, box=(x0, y0, x1, y1),
                                          mask=mask[y0:y1, x0:x1]))
        return DetectResult(request_id=req.request_id, episode_id=req.episode_id, step=req.step, detections=dets,
                            backend="ground-truth", model="labels", replica="test")


def task_start(eid: str, obj: str, home: str | None, pose: Pose2D) -> EpisodeStart:
    task = Task(kind="find_object", text=f"Find a {obj}", scene=SCENE, object=obj, start_pose=pose)
    q = Question(text=task.text, scene=SCENE, start_pose=pose, max_steps=20)
    return EpisodeStart(episode_id=eid, robot="r0", question=q, stop=StopConfig(rule="max_steps"), max_steps=20,
                        seed=3, record=False, task=task, home=home)


def run_task(memory: HomeMemory, start: EpisodeStart, renderer, turns: int, detect) -> tuple[EpisodeMap, ObjectMap]:
    em = EpisodeMap(start, task_map_config(MapperConfig()))
    om = ObjectMap.for_task(start.task, ObjectMapConfig())
    memory.start(start, em, om)
    p = start.task.start_pose
    for k in range(turns):
        f = frame_at(renderer, start.episode_id, k, Pose2D(x=p.x, y=p.y, yaw=p.yaw + k * math.pi / 3))
        em.integrate(f)
        memory.offer_view(em, f)
        if k == 0:
            memory.warm_objects(em, om, f, lambda: detect)
        om.integrate(f, detect(om.detect_request(f)))
    return em, om


def best_psi(om: ObjectMap, cls: str) -> float:
    return max((o.scores[cls][2] for o in om.summaries()), default=-1.0)


def test_a_second_task_starts_with_the_target_the_first_one_saw(house, store: Store, tmp_path: Path) -> None:
    """The first task in a home sees its target while turning on the spot; a second task asking for the same
    class starts (before any frame) with that instance's Psi above tau_g, and with the floor the first explored
    counted explored; a cold task, or one in a home whose first task asked another class, starts with nothing."""
    scene, renderer = house
    obj, pose = seen_object(scene, renderer)
    settings = Settings(data_dir=tmp_path / "var")
    tau_g = settings.helios_tau_g
    detect = GroundTruthDetector()
    memory = HomeMemory(settings, lambda: store, lambda: None)
    homes.delete_home(store, "h-o", 60.0)
    em1, om1 = run_task(memory, task_start("ep-o1", obj, "h-o", pose), renderer, 6, detect)
    assert best_psi(om1, obj) > tau_g  # the first task did see it
    index = memory.commit(em1, om1)
    assert index is not None and index.gaussians > 0 and index.objects_bytes > 0
    summary = homes.read_summary(store, "h-o")
    assert summary is not None and summary.gaussians == index.gaussians
    assert summary.bytes == index.map_bytes + index.objects_bytes + index.view_bytes
    assert store.get(objects_base_key("h-o", "ep-o1")) is None
    stored = memory.read_objects("h-o")
    assert stored is not None and stored.asked(obj) and not stored.asked("zz-never")

    second = task_start("ep-o2", obj, "h-o", pose)
    em2 = EpisodeMap(second, task_map_config(MapperConfig()))
    om2 = ObjectMap.for_task(second.task, ObjectMapConfig())
    memory.start(second, em2, om2)
    assert best_psi(om2, obj) > tau_g  # before its first frame
    assert memory.episodes["ep-o2"].loaded_cells > 0 and memory.episodes["ep-o2"].redetect_ids == []
    assert store.get(objects_base_key("h-o", "ep-o2")) is not None
    cold = task_start("ep-o3", obj, None, pose)
    om3 = ObjectMap.for_task(cold.task, ObjectMapConfig())
    memory.start(cold, EpisodeMap(cold, task_map_config(MapperConfig())), om3)
    assert om3.summaries() == []
    # a task for a class never asked: no Gaussian comes back (none holds evidence for it: with the flat prior each
    # would be a candidate at S = 1/2), nothing counts as explored, the remembered views are re-detected for it
    other = task_start("ep-o4", "zz-never", "h-o", pose)
    em4 = EpisodeMap(other, task_map_config(MapperConfig()))
    om4 = ObjectMap.for_task(other.task, ObjectMapConfig())
    memory.start(other, em4, om4)
    ep4 = memory.episodes["ep-o4"]
    assert ep4.loaded_cells == 0 and len(ep4.redetect_ids) > 0 and ep4.redetect_without == []
    assert om4.summaries() == [] and len(stored) > 0
    n_calls = len(detect.calls)
    f0 = frame_at(renderer, "ep-o4", 0, pose)
    em4.integrate(f0)
    assert memory.warm_objects(em4, om4, f0, lambda: detect) == len(ep4.redetect_ids)
    assert len(detect.calls) == n_calls + len(ep4.redetect_ids)
    assert all(r.classes == ["zz-never"] for r in detect.calls[n_calls:])
    assert memory.warm_objects(em4, om4, f0, lambda: detect) == 0  # once
    # the home part rides in the episode state: a restarted mapper continues it and commits the same layer
    home_part = memory.dump("ep-o2")
    snapshot = om2.snapshot()
    other_instance = HomeMemory(settings, lambda: store, lambda: None)
    other_instance.restore("ep-o2", home_part)
    om2b = ObjectMap.restore(snapshot, ObjectMapConfig())
    assert other_instance.episodes["ep-o2"].objects_base
    for k in range(2):
        f = frame_at(renderer, "ep-o2", k, Pose2D(x=pose.x, y=pose.y, yaw=pose.yaw + k * math.pi / 3))
        em2.integrate(f)
        om2b.integrate(f, detect(om2b.detect_request(f)))
    after = other_instance.commit(em2, om2b)
    assert after is not None and after.version == 2
    kept = memory.read_objects("h-o")
    assert kept is not None and set(stored.uid.tolist()) <= set(kept.uid.tolist())
    row = {int(u): i for i, u in enumerate(kept.uid)}
    # the restored Gaussians' evidence for the object only grew: the base was counted once
    old = stored.gamma_for([obj], PRIOR)
    new = kept.gamma_for([obj], PRIOR)
    idx = [row[int(u)] for u in stored.uid]
    assert (new[idx, 0] >= old[:, 0] - 1e-4).all() and (new[idx, 0] <= 3 * old[:, 0] + 50).all()
    assert store.get(objects_base_key("h-o", "ep-o2")) is None
    assert homes.delete_home(store, "h-o", 60.0) >= 3
    assert store.get(objects_key("h-o")) is None and store.get(objects_base_key("h-o", "ep-o4")) is None


def test_two_tasks_at_once_in_a_home_both_add_their_evidence(house, store: Store, tmp_path: Path) -> None:
    """Two tasks start from one stored layer and both end: the home then holds, per remembered Gaussian, the
    stored evidence plus each task's own (what each would have added alone), and the Gaussians each one made."""
    scene, renderer = house
    obj, pose = seen_object(scene, renderer)
    memory = HomeMemory(Settings(data_dir=tmp_path / "var"), lambda: store, lambda: None)
    detect = GroundTruthDetector()
    homes.delete_home(store, "h-cc", 60.0)
    memory.commit(*run_task(memory, task_start("ep-c0", obj, "h-cc", pose), renderer, 3, detect))
    stored = memory.read_objects("h-cc")
    assert stored is not None and len(stored) > 0
    ends = {eid: run_task(memory, task_start(eid, obj, "h-cc", pose), renderer, turns, detect)
            for eid, turns in (("ep-ca", 6), ("ep-cb", 4))}  # both started before either ends
    alone = {}
    for eid, (_em, om) in ends.items():
        a = om.home_arrays()
        alone[eid] = commit_layer(stored, a["uid"], a["means"], a["sigma"], a["opacity"], a["gamma"],
                                  om.task_classes, om.layer.config.prior, eid, 100.0, None)
    for eid in ("ep-cb", "ep-ca"):  # the one that started second ends first
        memory.commit(*ends[eid])
    final = memory.read_objects("h-cc")
    assert final is not None
    made = sum(len(alone[e]) - len(stored) for e in alone)
    assert len(final) == len(stored) + made
    rows = {int(u): i for i, u in enumerate(final.uid)}
    idx = [rows[int(u)] for u in stored.uid]
    n = len(stored)
    want = (alone["ep-ca"].gamma_for([obj], PRIOR)[:n] + alone["ep-cb"].gamma_for([obj], PRIOR)[:n]
            - stored.gamma_for([obj], PRIOR))
    np.testing.assert_allclose(final.gamma_for([obj], PRIOR)[idx], want, rtol=1e-5, atol=1e-4)
    assert (want[:, 0] > stored.gamma_for([obj], PRIOR)[:, 0]).any()  # both saw the target again
    assert homes.delete_home(store, "h-cc", 60.0) >= 3


def test_the_home_layer_stays_within_its_count_and_bytes(house, store: Store, tmp_path: Path) -> None:
    scene, renderer = house
    obj, pose = seen_object(scene, renderer)
    detect = GroundTruthDetector()
    homes.delete_home(store, "h-b", 60.0)
    small = Settings(data_dir=tmp_path / "var", helios_max_gaussians=20)
    memory = HomeMemory(small, lambda: store, lambda: None)
    em, om = run_task(memory, task_start("ep-b1", obj, "h-b", pose), renderer, 4, detect)
    assert len(om.layer.store) > 20  # the episode's layer is larger than the home may keep
    index = memory.commit(em, om)
    assert index is not None and 0 < index.gaussians <= 20
    stored = memory.read_objects("h-b")
    assert stored is not None and len(stored) == index.gaussians
    # a byte budget the map and the layer cannot both fit: the layer is cut to fit, never the budget exceeded
    tight = Settings(data_dir=tmp_path / "var", home_max_bytes=index.map_bytes + 3000)
    memory2 = HomeMemory(tight, lambda: store, lambda: None)
    em2, om2 = run_task(memory2, task_start("ep-b2", obj, "h-b", pose), renderer, 2, detect)
    index2 = memory2.commit(em2, om2)
    assert index2 is not None
    assert index2.objects_bytes <= tight.home_max_bytes - index2.map_bytes
    assert index2.map_bytes + index2.objects_bytes + index2.view_bytes <= tight.home_max_bytes
    # a stored part that is not a layer is ignored (logged), the next task starts without it
    store.set(objects_key("h-b"), b"\x00garbage", ttl_s=60)
    em3, om3 = run_task(memory, task_start("ep-b3", obj, "h-b", pose), renderer, 1, detect)
    assert memory.episodes["ep-b3"].objects_base is False
    assert memory.commit(em3, om3) is not None and memory.read_objects("h-b") is not None
    homes.delete_home(store, "h-b", 60.0)


# ---- through the mapper service over Zenoh: a task continued by another instance ------------------------------
def fake_values(req):
    from eqa.messages import ValueResult

    return ValueResult(request_id=req.request_id, episode_id=req.episode_id, step=req.step,
                       values=[0.5] * len(req.targets), backend="test", model="test", replica="test")


def test_a_task_in_a_home_through_the_mapper_service_restarted_mid_task(
        hub_settings: Settings, settings: Settings, house, redis_url: str) -> None:
    """Real services over Zenoh and Redis: task 1 in a home sees its target and ends; task 2 for the same class
    publishes, at its first step, an instance of the target above tau_g and counts explored floor; the mapper
    dies, a second instance continues task 2 from the store and commits it (the home's layer grows, the copy of
    the layer it started from is deleted); a task for a class never asked re-detects the remembered views
    through the detector at its first frame."""
    import time

    from support.mapper import home_rig

    from eqa import keys
    from eqa.messages import EpisodeEnd
    from services.mapper.service import MapperService

    scene, renderer = house
    obj, pose = seen_object(scene, renderer)
    settings = settings.model_copy(update={"redis_url": redis_url, "scorer_replica": "homes-obj",
                                           "home_max_views": 4})
    home = homes.home_id("tenant-a", "task-house")
    detect = GroundTruthDetector()

    def turned(k: int) -> Pose2D:
        return Pose2D(x=pose.x, y=pose.y, yaw=pose.yaw + k * math.pi / 3)

    def ended(eid: str, steps: int) -> EpisodeEnd:
        return EpisodeEnd(episode_id=eid, robot="r0", state="stopped", reason="test", steps=steps)

    def wait_version(service: MapperService, version: int) -> None:
        deadline = time.time() + 30
        while time.time() < deadline:
            index = service.homes.read_index(home)
            if index is not None and index.version >= version:
                return
            time.sleep(0.05)
        raise AssertionError(f"home not at version {version}")

    with home_rig(hub_settings, settings, home, detector=detect, values=fake_values) as rig:
        bus, out, mapper = rig.bus, rig.out, rig.mapper
        store = mapper.store
        bus.publish(keys.stream("r0", keys.EPISODE_START), task_start("ep-s1", obj, home, pose))
        for k in range(6):
            bus.publish(keys.stream("r0", keys.SIM_FRAME), frame_at(renderer, "ep-s1", k, turned(k)))
            m, _ = out.step(k)
        assert max((o.scores[obj][2] for o in m.objects), default=-1.0) > settings.helios_tau_g
        bus.publish(keys.stream("r0", keys.EPISODE_END), ended("ep-s1", 6))
        wait_version(mapper, 1)
        index = mapper.homes.read_index(home)
        assert index is not None and index.gaussians > 0

        bus.publish(keys.stream("r0", keys.EPISODE_START), task_start("ep-s2", obj, home, pose))
        away = [k for k in range(6) if not any(
            lb.category == obj for lb in frame_at(renderer, "probe", k, turned(k)).labels)]
        assert away, f"every direction shows a {obj}"
        bus.publish(keys.stream("r0", keys.SIM_FRAME), frame_at(renderer, "ep-s2", 0, turned(away[0])))
        m0, _ = out.step(0)  # facing where no target is in view: the home's layer remembers it
        assert max((o.scores[obj][2] for o in m0.objects), default=-1.0) > settings.helios_tau_g
        assert mapper.homes.episodes["ep-s2"].loaded_cells > 0
        assert store.get(objects_base_key(home, "ep-s2")) is not None

        mapper.stop()  # dies mid-task; another instance takes the robot over from the store
        other = rig.instance(settings.model_copy(update={"instance": "mapper-b"}), detector=detect, values=fake_values)
        bus.publish(keys.stream("r0", keys.SIM_FRAME), frame_at(renderer, "ep-s2", 1, turned(away[-1])))
        m1, _ = out.step(1)
        assert max((o.scores[obj][2] for o in m1.objects), default=-1.0) > settings.helios_tau_g
        assert other.homes.episodes["ep-s2"].objects_base
        bus.publish(keys.stream("r0", keys.EPISODE_END), ended("ep-s2", 2))
        wait_version(other, 2)
        assert store.get(objects_base_key(home, "ep-s2")) is None
        after = other.homes.read_index(home)
        assert after is not None and after.episodes == 2 and after.gaussians >= index.gaussians

        n_calls = len(detect.calls)
        bus.publish(keys.stream("r0", keys.EPISODE_START), task_start("ep-s3", "zz-never", home, pose))
        bus.publish(keys.stream("r0", keys.SIM_FRAME), frame_at(renderer, "ep-s3", 0, pose))
        out.step(0)
        redetected = [r for r in detect.calls[n_calls:] if r.episode_id == "ep-s3"]
        assert len(redetected) == len(after.views) + 1  # the remembered views, then its own frame
        assert other.homes.episodes["ep-s3"].objects_warmed
        bus.publish(keys.stream("r0", keys.EPISODE_END), ended("ep-s3", 1))
        wait_version(other, 3)
        assert out.errors.empty(), out.errors.get()
        assert homes.delete_home(store, home, 60.0) >= 4

"""Stale evidence in a home's view memory: a frame contradicting a remembered view's geometry is a change the
robot observed, and views older than it (or than the age limit) give the stopper down-weighted evidence."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from eqa.settings import Settings
from services.mapper.episode_map import EpisodeMap
from services.mapper.home_memory import HomeIndex, ObservedChange, ViewInfo, disagreement, stale_weights
from services.mapper.home_shell import HomeMemory

W, H = 40, 30
K = np.array([[20.0, 0, W / 2], [0, 20.0, H / 2], [0, 0, 1]])
# camera at (0, 0, 1.5) looking along world +x: camera z = world x, camera x = world -y, camera y = world -z
R = np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]])


def cam(x: float = 0.0, y: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = (x, y, 1.5)
    return T


def shot(depth: np.ndarray, pose: np.ndarray | None = None) -> SimpleNamespace:
    return SimpleNamespace(depth=depth.astype(np.float32), intrinsics=K, camera_pose=cam() if pose is None else pose)


def wall(d: float = 3.0) -> np.ndarray:
    return np.full((H, W), d)


def with_box(depth: np.ndarray, d: float) -> np.ndarray:
    out = depth.copy()
    out[10:20, 14:26] = d  # a box in the middle of the image, nearer than the wall
    return out


def render(x0: float, box: bool) -> np.ndarray:
    """z-depth from a camera at x = x0 of a wall at x = 3 m and (``box``) a box face at x = 2 m, |y| <= 0.3 m,
    1.2 <= z <= 1.8 m."""
    v, u = np.mgrid[0:H, 0:W]
    dirs = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones((H, W))], axis=-1) @ R.T
    depth = (3.0 - x0) / dirs[..., 0]  # z-depth: the camera's z is world x
    if box:
        t = (2.0 - x0) / dirs[..., 0]
        y, z = t * dirs[..., 1], 1.5 + t * dirs[..., 2]
        depth = np.where((np.abs(y) <= 0.3) & (z >= 1.2) & (z <= 1.8), t, depth)
    return depth


def test_the_same_geometry_is_no_change() -> None:
    a = shot(with_box(wall(), 2.0))
    assert len(disagreement(a, a, 0.1, stride=2)) == 0
    # the same house seen from a step nearer: the box looks bigger, nothing violates free space
    far, near = shot(render(0.0, True)), shot(render(0.5, True), cam(x=0.5))
    assert len(disagreement(far, near, 0.1, stride=2)) == 0
    assert len(disagreement(far, shot(render(0.5, False), cam(x=0.5)), 0.1, stride=2)) > 0  # the box gone


def test_an_object_taken_away_is_seen_through() -> None:
    before, after = shot(with_box(wall(), 2.0)), shot(wall())
    cells = disagreement(before, after, 0.1, stride=2)
    assert len(cells) > 0 and set(np.unique(cells[:, 0]).tolist()) == {20}  # at x = 2.0 m: where the box was


def test_an_object_put_in_seen_free_space_is_a_change() -> None:
    before, after = shot(wall()), shot(with_box(wall(), 1.5))
    cells = disagreement(before, after, 0.1, stride=2)
    assert len(cells) > 0 and set(np.unique(cells[:, 0]).tolist()) == {15}  # at x = 1.5 m: the new box


def test_views_that_do_not_share_space_or_lack_depth_say_nothing() -> None:
    before = shot(with_box(wall(), 2.0))
    away = np.eye(4)
    away[:3, :3] = R @ np.array([[-1.0, 0, 0], [0, 1, 0], [0, 0, -1]])  # turned around: looks along -x
    away[:3, 3] = (0, 0, 1.5)
    assert len(disagreement(before, shot(wall(), away), 0.1, stride=2)) == 0
    assert len(disagreement(before, shot(np.zeros((H, W))), 0.1, stride=2)) == 0  # no depth: no evidence


def view(vid: str, t: float, cells: list[tuple[int, int]]) -> ViewInfo:
    return ViewInfo(vid, t, 1, np.array(cells, dtype=np.int32).reshape(-1, 2))


def change(t: float, cells: list[tuple[int, int]], views: tuple[str, ...] = ()) -> ObservedChange:
    return ObservedChange(t, np.array(cells, dtype=np.int32).reshape(-1, 2), views)


def test_stale_weights_follow_observed_changes_and_age() -> None:
    views = [view("old-there", 10, [(1, 1), (1, 2)]), view("new-there", 30, [(1, 2)]), view("old-else", 10, [(5, 5)]),
             view("named", 10, [(9, 9)])]
    seen = [change(20, [(1, 2), (3, 3)], views=("named",))]
    # older than a change on its cells or naming it: stale; newer than it, or elsewhere: fresh
    assert stale_weights(views, 40, seen, 0, 0.25) == [0.25, 1.0, 1.0, 0.25]
    assert stale_weights(views, 40, [], 0, 0.0) == [1.0] * 4  # nothing seen, no age limit: all fresh
    assert stale_weights(views, 40, [], 25, 0.0) == [0.0, 1.0, 0.0, 0.0]  # older than 25 s
    assert stale_weights(views, 40, seen, 0, 1.0) == [1.0] * 4  # weight 1: stale evidence counts in full
    with pytest.raises(ValueError):
        stale_weights(views, 40, seen, 0, 1.5)


def test_observed_changes_survive_the_index_round_trip() -> None:
    idx = HomeIndex(version=3, changes=[change(5.0, [(1, 2)], ("v1",))])
    back = HomeIndex.from_bytes(idx.to_bytes())
    assert back.changes[0].t == 5.0 and back.changes[0].views == ("v1",)
    assert back.changes[0].cells.tolist() == [[1, 2]]


# ---- in the mapper's home memory, in a simulated house that changed ------------------------------------------
def _frame(renderer, scene_id: str, episode_id: str, step: int, pose):
    from eqa.messages import Frame
    from services.sim import camera

    Kc = camera.intrinsics(160, 120)
    T = camera.camera_pose(pose)
    r = renderer.render(T, Kc, 160, 120)
    return Frame(episode_id=episode_id, step=step, pose=pose, camera_pose=T, intrinsics=Kc, rgb=r.rgb, depth=r.depth,
                 instances=r.instances, labels=renderer.labels(r.instances), scene=scene_id)


def _scorer(req):
    from eqa.messages import ScoreResult

    return ScoreResult(request_id=req.request_id, episode_id=req.episode_id, step=req.step,
                       answer_probs=[0.97, 0.01, 0.01, 0.01], relevance=0.9, lsv=[0.5] * len(req.prompt_points),
                       gsv=0.5, backend="test")


@pytest.fixture(scope="module")
def changed(tmp_path_factory: pytest.TempPathFactory):
    from services.sim.library import load_or_generate
    from services.sim.questions import generate_questions
    from services.sim.render import Renderer
    from services.sim.visibility import witness_poses

    scenes = Path(tmp_path_factory.mktemp("scenes"))
    base = load_or_generate("gen-00007", scenes)
    after = load_or_generate("gen-00007-c1", scenes)
    gone = sorted(set(base.instances) - set(after.instances)
                  | {i for i in base.instances if i in after.instances
                     and base.instances[i].position != after.instances[i].position})
    # the biggest of them: a mug at 3 m spans a few pixels of a 160x120 image, too few to tell from aliasing
    biggest = max(gone, key=lambda i: float(np.prod(base.instances[i].size)))
    pose = witness_poses(base, None, ids=[biggest])[biggest]
    question = generate_questions(base, np.random.default_rng([7, 0, 11]))[0]
    return base, after, Renderer(base), Renderer(after), pose, question


@pytest.mark.parametrize("weight", [0.0, 1.0])
def test_a_view_the_robot_sees_contradicted_gives_down_weighted_evidence(changed, tmp_path: Path, weight) -> None:
    from eqa.messages import EpisodeStart
    from eqa.store import EmbeddedStore

    base, after, r_base, r_after, pose, q = changed
    store = EmbeddedStore(tmp_path / "h.sqlite")
    settings = Settings(data_dir=tmp_path / "var", home_stale_weight=weight)
    memory = HomeMemory(settings, lambda: store, lambda: _scorer)
    clock = iter(range(100, 10_000, 10))
    memory.clock = lambda: float(next(clock))
    results = []
    for eid, scene, renderer in (("ep-1", base, r_base), ("ep-2", after, r_after)):
        start = EpisodeStart(episode_id=eid, robot="r0", question=q.model_copy(update={"scene": scene.id}),
                             max_steps=5, record=False, seed=3, home="h-s")
        em = EpisodeMap(start)
        memory.start(start, em)
        f = _frame(renderer, scene.id, eid, 0, pose)  # the same pose: the moved or removed object's old place
        em.integrate(f)
        memory.offer_view(em, f)
        results.append(memory.warm(em, f))
        memory.commit(em)
    assert results[0] == [] and len(results[1]) == 1
    # the robot saw the change against the remembered view: its evidence comes with relevance 0.9 * weight
    assert results[1][0].relevance == pytest.approx(0.9 * weight)
    index = memory.read_index("h-s")
    assert index is not None and (len(index.changes) == 1) == (weight < 1.0)
    store.close()


def test_an_unchanged_house_seen_from_elsewhere_shows_no_change(changed) -> None:
    """Shelf boards, chair legs and depth edges seen from two poses alias between the views' pixels; none of it
    may count as a change (every remembered view would turn stale)."""
    import math

    from eqa.messages import Pose2D
    from services.mapper.home_memory import Keyframe, cell_keys
    from services.sim.motion import reachable_map

    base, _, r_base, _, _, _ = changed
    reach, ox, oy = reachable_map(base, None)
    ii, jj = np.nonzero(reach)
    rng = np.random.default_rng(0)
    pairs = 0
    for _ in range(200):
        (a, b), yaw = rng.integers(len(ii), size=2), rng.uniform(-math.pi, math.pi)
        pa = Pose2D(x=ox + (jj[a] + 0.5) * 0.05, y=oy + (ii[a] + 0.5) * 0.05, yaw=yaw)
        pb = Pose2D(x=ox + (jj[b] + 0.5) * 0.05, y=oy + (ii[b] + 0.5) * 0.05, yaw=yaw + rng.uniform(-1, 1))
        if math.hypot(pa.x - pb.x, pa.y - pb.y) > 3:
            continue
        ka = Keyframe.from_frame(_frame(r_base, base.id, "a", 0, pa), "a", 0.05)
        kb = Keyframe.from_frame(_frame(r_base, base.id, "b", 0, pb), "b", 0.05)
        if cell_keys(ka.cells).isdisjoint(cell_keys(kb.cells)):
            continue
        pairs += 1
        assert len(disagreement(ka, kb, 0.05)) == 0, (pa, pb)
    assert pairs >= 10

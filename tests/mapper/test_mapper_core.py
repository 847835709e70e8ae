"""Mapper core on frames rendered by the simulator from a generated house (no bus)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from support.scenes import largest_room_spot, rendered_frame

from eqa.messages import EpisodeStart, Frame, Frontier, Pose2D, PromptPoint, Question
from services.mapper.episode_map import EpisodeMap
from services.mapper.frontiers import frontier_weight, sv_normal, weigh_frontiers
from services.mapper.semantic_map import semantic_value, temperatures, write_values
from services.mapper.tsdf import FrameError, TSDFVolume, check_frame
from services.sim.library import load_or_generate
from services.sim.render import Renderer

W, H = 160, 120


@pytest.fixture(scope="module")
def house(tmp_path_factory: pytest.TempPathFactory) -> tuple:
    scene = load_or_generate("gen-00007", Path(tmp_path_factory.mktemp("scenes")))
    room = max(scene.rooms, key=lambda r: r.area)
    return scene, Renderer(scene), room, scene.navigable_grid(0.1), largest_room_spot(scene)


def make_start(strategy: str = "semantic") -> EpisodeStart:
    q = Question(
        text="Where is the sofa?", choices=["kitchen", "bedroom", "living room", "bathroom"], scene="gen-7"
    )
    return EpisodeStart(episode_id="ep-map", robot="r0", question=q, max_steps=20, strategy=strategy)


def render_frame(renderer: Renderer, pose: Pose2D, step: int) -> Frame:
    return rendered_frame(renderer, pose, "ep-map", step, W, H)


@pytest.fixture(scope="module")
def turned(house: tuple) -> tuple[EpisodeMap, list[Frame]]:
    """A 360 deg turn in place (12 views, 30 deg apart) in the largest room."""
    _, renderer, _, _, (x, y) = house
    episode_map = EpisodeMap(make_start())
    frames = [render_frame(renderer, Pose2D(x=x, y=y, yaw=k * math.pi / 6), k) for k in range(12)]
    for f in frames:
        episode_map.integrate(f)
        episode_map.apply_scores([0.6, 0.3, 0.1][: len(episode_map.prompts)], 0.8)
        episode_map.compute_frontiers()
    return episode_map, frames


def gt_on_map_grid(
    episode_map: EpisodeMap, gt: np.ndarray, ox: float, oy: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    ny, nx = episode_map.volume.shape2d
    rows, cols = np.mgrid[0:ny, 0:nx]
    X, Y = episode_map.volume.cell_center(rows, cols)
    gc = np.floor((X - ox) / 0.1 + 1e-6).astype(int)
    gr = np.floor((Y - oy) / 0.1 + 1e-6).astype(int)
    inside = (gc >= 0) & (gc < gt.shape[1]) & (gr >= 0) & (gr < gt.shape[0])
    g = np.zeros((ny, nx), dtype=bool)
    g[inside] = gt[gr[inside], gc[inside]]
    return g, X, Y


def test_free_space_matches_floor_plan_after_turn(house: tuple, turned: tuple) -> None:
    _, _, room, (gt, ox, oy), (x, y) = house
    episode_map, _ = turned
    g, X, Y = gt_on_map_grid(episode_map, gt, ox, oy)
    x0, y0, x1, y1 = room.rect
    # within view range: the robot's own room, up to 4 m away
    view = (np.hypot(X - x, Y - y) <= 4.0) & (x0 <= X) & (x1 >= X) & (y0 <= Y) & (y1 >= Y)
    free = episode_map.maps.free & view
    truth = g & view
    iou = (free & truth).sum() / (free | truth).sum()
    assert truth.sum() > 1000
    assert iou >= 0.9, f"free-space IoU {iou:.3f}"


def test_explored_subset_of_observed_and_narrower(turned: tuple) -> None:
    episode_map, _ = turned
    m = episode_map.maps
    assert m.explored.any()
    assert not (m.explored & ~m.observed).any()
    assert m.explored.sum() < m.observed.sum()
    # the narrow view meets the floor within 2.6 m / cos(30 deg) (optical axis 30 deg down from 1.5 m,
    # +-30 deg azimuth), plus the truncation band behind the floor; the full view sees the whole room
    # (4.35 m to the walls)
    rows, cols = np.nonzero(m.explored & ~episode_map.volume.planes["traversed"])
    xs, ys = episode_map.volume.cell_center(rows, cols)
    pose = episode_map.pose
    assert np.hypot(xs - pose.x, ys - pose.y).max() < 2.6 / math.cos(math.radians(30)) + 0.5 + 0.2


def test_frontier_normals_point_into_unknown(turned: tuple) -> None:
    episode_map, _ = turned
    m = episode_map.maps
    assert len(episode_map.frontiers) >= 3
    unknown = ~m.explored & ~m.occupied

    def unknown_fraction(f: Frontier, sign: float) -> float:
        """Share of unknown cells in the 90 deg sector 0.3..1.0 m ahead (sign=1) or behind (sign=-1)."""
        base = math.atan2(sign * f.ny, sign * f.nx)
        hits = []
        for a in np.linspace(base - math.pi / 4, base + math.pi / 4, 7):
            for d in np.arange(0.3, 1.01, 0.1):
                r, c = episode_map.volume.cell_of(f.x + d * math.cos(a), f.y + d * math.sin(a))
                hits.append(bool(unknown[r, c]))
        return float(np.mean(hits))

    into_unknown = 0
    for f in episode_map.frontiers:
        r, c = episode_map.volume.cell_of(f.x, f.y)
        assert m.free[r, c] and m.explored[r, c]
        assert math.isclose(math.hypot(f.nx, f.ny), 1.0, rel_tol=1e-6)
        ahead, behind = unknown_fraction(f, 1.0), unknown_fraction(f, -1.0)
        into_unknown += ahead > behind
    assert into_unknown == len(episode_map.frontiers)


def test_prompt_points_in_free_space_inside_image(turned: tuple) -> None:
    episode_map, frames = turned
    assert 1 <= len(episode_map.prompts) <= 3
    assert [p.label for p in episode_map.prompts] == ["A", "B", "C"][: len(episode_map.prompts)]
    t = frames[-1].camera_pose[:3, 3]
    for p in episode_map.prompts:
        r, c = episode_map.volume.cell_of(p.x, p.y)
        assert episode_map.maps.free[r, c]
        assert 0 <= p.u <= W - 1 and 0 <= p.v <= H - 1
        assert 2.0 <= math.hypot(p.x - t[0], p.y - t[1]) <= 10.0
        # the pixel really looks at that floor point: back-project with the depth there
        K = frames[-1].intrinsics
        pc = frames[-1].camera_pose[:3, :3].T @ (np.array([p.x, p.y, 0.0]) - t)
        assert abs(K[0, 0] * pc[0] / pc[2] + K[0, 2] - p.u) < 1e-6
    for a in episode_map.prompts:
        for b in episode_map.prompts:
            if a is not b:
                assert math.hypot(a.x - b.x, a.y - b.y) >= 1.0


def test_eq_a6_by_hand_on_small_grid() -> None:
    # 10 x 40 cells of 0.1 m, origin (0, 0); value 2.0 in columns 20..39 (x in [2.0, 4.0)), 0 elsewhere
    layer = np.zeros((10, 40), dtype=np.float32)
    layer[:, 20:] = 2.0
    facing = Frontier(x=1.55, y=0.55, nx=1.0, ny=0.0, size=5)  # cell column 15, looks at the high region
    away = Frontier(x=1.55, y=0.55, nx=-1.0, ny=0.0, size=5)
    inside = Frontier(x=2.55, y=0.55, nx=0.0, ny=1.0, size=5)  # in the high region, normal leaves the grid
    out = weigh_frontiers(
        [facing, away, inside], layer, (0.0, 0.0), 0.1, tau_sv=1.0, tau_sv_normal=1.0, d_sv=3.0
    )
    # facing: SV_p = 0; samples at 0.1..3.0 m -> x = 1.65..4.55: columns 16..45;
    # 16..19 -> 0 (4 samples), 20..39 -> 2.0 (20 samples), 40..45 -> outside = 0 (6 samples): mean 40/30
    assert out[0].sv == 0.0
    assert out[0].sv_normal == pytest.approx(40 / 30)
    assert out[0].weight == pytest.approx(math.exp(0.0 + 40 / 30))
    # away: x = 1.45 .. -1.45 -> all 0 -> weight exp(0) = 1
    assert out[1].sv_normal == 0.0 and out[1].weight == pytest.approx(1.0)
    # inside: SV_p = 2; y = 0.65..3.55 -> rows 6..9 inside (4 samples of 2.0), 26 outside: mean 8/30
    assert out[2].sv == pytest.approx(2.0)
    assert out[2].sv_normal == pytest.approx(8 / 30)
    assert out[2].weight == pytest.approx(math.exp(2.0 + 8 / 30))
    assert out[0].weight > out[1].weight
    # temperatures scale each term separately
    assert frontier_weight(2.0, 0.5, tau_sv=0.5, tau_sv_normal=3.0) == pytest.approx(math.exp(1.0 + 1.5))
    # values past exp()'s range (the paper's tau = 5 gives SV up to e^10): weights divided by the largest,
    # same proportions, nothing overflows
    big = weigh_frontiers([facing, away, inside], layer * 500.0, (0.0, 0.0), 0.1, 1.0, 1.0)  # value 1000
    # log weights: facing 0 + 20000/30, away 0, inside 1000 + 4000/30 (past 700: rescaled by the largest)
    assert big[2].weight == 1.0
    assert big[0].weight == pytest.approx(math.exp(20000 / 30 - (1000 + 4000 / 30)))
    assert big[1].weight == pytest.approx(math.exp(-700.0)) and big[1].weight > 0.0  # clamped, not 0
    assert sv_normal(layer, (0.0, 0.0), 0.1, facing, 1.0) == pytest.approx(np.mean([0] * 4 + [2.0] * 6))
    # strategies without semantic values: every weight 1
    assert [f.weight for f in weigh_frontiers([facing, away], None, (0, 0), 0.1, 1.0, 1.0)] == [1.0, 1.0]


def test_semantic_values_raise_weights_of_frontiers_facing_them(turned: tuple) -> None:
    episode_map, _ = turned
    # write a strong value 2 m beyond one frontier, along its normal, into a fresh layer
    f = max(episode_map.frontiers, key=lambda fr: fr.size)
    before = {(g.x, g.y): g.weight for g in episode_map.frontiers}
    layer = episode_map.layer()
    layer[:] = 0.0
    write_values(
        layer, episode_map.origin, episode_map.resolution, [(f.x + 2.0 * f.nx, f.y + 2.0 * f.ny)],
        [semantic_value(1, 1, 1, 1)],
    )
    episode_map.compute_frontiers()
    after = {(g.x, g.y): g for g in episode_map.frontiers}
    assert after[(f.x, f.y)].sv_normal > 0.5
    others = [g for k, g in after.items() if math.hypot(k[0] - f.x, k[1] - f.y) > 4.0]
    assert others and all(after[(f.x, f.y)].weight > g.weight for g in others)
    assert before  # weights were computed before too


def test_semantic_value_eq3_and_max_fusion() -> None:
    assert semantic_value(0.5, 0.25, 2.0, 4.0) == pytest.approx(math.exp(1.0 + 1.0))
    assert temperatures("no_lsv", 1.5, 2.0) == (0.0, 2.0)
    assert temperatures("no_gsv", 1.5, 2.0) == (1.5, 0.0)
    assert temperatures("fbe", 1.0, 1.0) is None and temperatures("nearest", 1.0, 1.0) is None
    layer = np.zeros((50, 50), dtype=np.float32)
    write_values(layer, (0.0, 0.0), 0.1, [(2.55, 2.55)], [3.0], sigma=1.0)
    assert layer[25, 25] == pytest.approx(3.0)
    assert layer[25, 35] == pytest.approx(3.0 * math.exp(-0.5), rel=1e-5)  # 1 m away = one sigma
    write_values(layer, (0.0, 0.0), 0.1, [(2.55, 2.55)], [1.5], sigma=1.0)  # lower later value: max keeps 3
    assert layer[25, 25] == pytest.approx(3.0)
    write_values(layer, (0.0, 0.0), 0.1, [(2.55, 2.55)], [4.0], sigma=1.0)
    assert layer[25, 25] == pytest.approx(4.0)


def test_strategies_write_values_accordingly(house: tuple) -> None:
    _, renderer, _, _, (x, y) = house
    frame = render_frame(renderer, Pose2D(x=x, y=y, yaw=0.3), 0)
    peaks = {}
    for strategy in ("semantic", "no_lsv", "no_gsv", "fbe"):
        episode_map = EpisodeMap(make_start(strategy))
        episode_map.integrate(frame)
        sv = episode_map.apply_scores([1.0] + [0.0] * (len(episode_map.prompts) - 1), 0.5)
        episode_map.compute_frontiers()
        peaks[strategy] = (sv, float(episode_map.layer().max()), [f.weight for f in episode_map.frontiers])
    assert peaks["semantic"][0][0] == pytest.approx(math.exp(1.0 + 0.5))
    assert peaks["no_lsv"][0][0] == pytest.approx(math.exp(0.5))
    assert peaks["no_gsv"][0][0] == pytest.approx(math.exp(1.0))
    assert peaks["fbe"][0] == [] and peaks["fbe"][1] == 0.0
    assert all(w == 1.0 for w in peaks["fbe"][2])


@pytest.mark.parametrize(
    "breakage",
    ["size", "nan", "neg_inf", "all_inf", "non_rigid", "bad_last_row"],
)
def test_bad_frames_rejected_map_unchanged(house: tuple, breakage: str) -> None:
    _, renderer, _, _, (x, y) = house
    episode_map = EpisodeMap(make_start())
    episode_map.integrate(render_frame(renderer, Pose2D(x=x, y=y, yaw=0.0), 0))
    vol = episode_map.volume
    tsdf, weight, explored = vol.tsdf.copy(), vol.weight.copy(), vol.explored.copy()
    bad = render_frame(renderer, Pose2D(x=x, y=y, yaw=1.0), 1)
    if breakage == "size":
        bad.depth = np.ascontiguousarray(bad.depth[:, : W // 2])
    elif breakage == "nan":
        bad.depth = bad.depth.copy()
        bad.depth[5, 7] = np.nan
    elif breakage == "neg_inf":
        bad.depth = bad.depth.copy()
        bad.depth[3, 3] = -np.inf
    elif breakage == "all_inf":
        bad.depth = np.full_like(bad.depth, np.inf)
    elif breakage == "non_rigid":
        bad.camera_pose = bad.camera_pose.copy()
        bad.camera_pose[:3, :3] *= 1.3
    else:
        bad.camera_pose = bad.camera_pose.copy()
        bad.camera_pose[3, 0] = 0.5
    with pytest.raises(FrameError):
        episode_map.integrate(bad)
    assert episode_map.step == 0
    assert np.array_equal(episode_map.volume.tsdf, tsdf) and np.array_equal(episode_map.volume.weight, weight)
    assert np.array_equal(episode_map.volume.explored, explored)


def test_check_frame_accepts_inf_as_no_hit(house: tuple) -> None:
    _, renderer, _, _, (x, y) = house
    f = render_frame(renderer, Pose2D(x=x, y=y, yaw=0.0), 0)
    depth = f.depth.copy()
    depth[0, :] = np.inf  # bus convention: +inf = nothing hit
    check_frame(depth, f.intrinsics, f.camera_pose)


def test_snapshot_roundtrip_is_exact(turned: tuple) -> None:
    episode_map, _ = turned
    back = EpisodeMap.restore(episode_map.snapshot())
    assert back.step == episode_map.step and back.pose == episode_map.pose and back.start == episode_map.start
    assert np.array_equal(back.volume.tsdf, episode_map.volume.tsdf)
    assert np.array_equal(back.volume.weight, episode_map.volume.weight)
    assert np.array_equal(back.volume.explored, episode_map.volume.explored)
    assert np.array_equal(back.layer(), episode_map.layer())
    assert np.array_equal(back.maps.free, episode_map.maps.free)
    assert back.frontiers == episode_map.frontiers and back.prompts == episode_map.prompts
    assert isinstance(back.prompts[0], PromptPoint)


def test_memory_follows_area_not_steps(house: tuple) -> None:
    _, renderer, _, _, (x, y) = house
    vol = TSDFVolume()
    f = render_frame(renderer, Pose2D(x=x, y=y, yaw=0.0), 0)
    vol.integrate(f.depth, f.intrinsics, f.camera_pose)
    size = vol.nbytes()
    for _ in range(10):
        vol.integrate(f.depth, f.intrinsics, f.camera_pose)
    assert vol.nbytes() == size
    # looking the other way grows the grid, by whole chunks
    g = render_frame(renderer, Pose2D(x=x, y=y, yaw=math.pi), 1)
    vol.integrate(g.depth, g.intrinsics, g.camera_pose)
    assert vol.nbytes() >= size
    ny, nx = vol.shape2d
    assert ny % vol.config.chunk == 0 and nx % vol.config.chunk == 0

"""View orientation in the semantic value layers (Explore-EQA appendix C).

Hand-built cases on the pure writers, and real frames (open3d renderer, real TSDF) through
:class:`EpisodeMap` for the on/off switch, the bins a real view writes, the snapshot round trip and the
memory bound."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError
from support.scenes import largest_room_spot, rendered_frame

from eqa.messages import EpisodeStart, Frame, Pose2D, Question
from eqa.settings import Settings
from services.mapper.episode_map import EpisodeMap, MapperConfig
from services.mapper.semantic_map import (
    MAX_VIEW_BINS,
    combine_view_bins,
    neutral_value,
    semantic_value,
    view_bin,
    view_plane_names,
    write_values,
    write_values_binned,
)
from services.sim.library import load_or_generate
from services.sim.render import Renderer

W, H = 160, 120
ORIGIN, RES, SHAPE = (0.0, 0.0), 0.1, (100, 100)  # a 10 m x 10 m grid
TAU = 1.0


def _write(bins: int, agree: int, views: list[tuple[tuple[float, float], list[float], float]],
           points: list[tuple[float, float]]) -> np.ndarray:
    """The layer after ``views`` = [(camera xy, LSV per point, GSV)]; bins = 0: the layer without bins."""
    layer = np.zeros(SHAPE, np.float32)
    per_bin = [np.zeros(SHAPE, np.float32) for _ in range(bins)]
    neutral = np.zeros(SHAPE, np.float32)
    for cam, lsv, gsv in views:
        sv = [semantic_value(v, gsv, TAU, TAU) for v in lsv]
        if bins == 0:
            write_values(layer, ORIGIN, RES, points, sv)
        else:
            write_values_binned(per_bin, neutral, ORIGIN, RES, points, sv, neutral_value(len(points), gsv, TAU, TAU),
                                cam)
            layer = combine_view_bins(per_bin, neutral, agree)
    return layer


# cell centres; the region at (5, 5) is the one seen from a poor angle
POINTS = [(5.05, 5.05), (8.05, 2.05), (2.05, 8.05)]
CELL = (50, 50)  # its cell


def test_view_bin_is_the_bearing_sector() -> None:
    assert view_bin(np.array([1.0]), np.array([0.0]), 4)[0] == 0
    assert view_bin(np.array([0.0]), np.array([1.0]), 4)[0] == 1
    assert view_bin(np.array([-1.0]), np.array([-1e-9]), 4)[0] == 2  # just below -pi wraps to the last sectors
    assert view_bin(np.array([0.0]), np.array([-1.0]), 4)[0] == 3
    assert view_bin(np.array([1.0]), np.array([-1e-12]), 8)[0] == 7
    assert view_bin(np.array([1.0]), np.array([1.0]), 8)[0] == 1  # 45 deg starts sector 1 of 8


def test_region_seen_only_from_a_poor_angle_is_not_explained() -> None:
    """A view from the west (camera at x = 1) rates the point at (5, 5) the worst of its three (LSV 0.1 < 1/3):
    without bins that low value is final; with bins the region keeps the neutral value (higher) until a
    second direction agrees; seen again from the same direction it stays unexplained."""
    poor = ((1.0, 5.0), [0.1, 0.45, 0.45], 0.5)
    off = _write(0, 2, [poor], POINTS)
    on = _write(8, 2, [poor], POINTS)
    assert off[CELL] == pytest.approx(semantic_value(0.1, 0.5, TAU, TAU), rel=1e-6)
    assert on[CELL] == pytest.approx(neutral_value(3, 0.5, TAU, TAU), rel=1e-6)
    assert on[CELL] > off[CELL]
    # the same poor judgement from the same direction again: still one bin, still not explained
    assert _write(8, 2, [poor, poor], POINTS)[CELL] == on[CELL]
    # a second direction (from the south) agrees that it is poor: now it is explained, as without bins
    poor_south = ((5.0, 1.0), [0.1, 0.45, 0.45], 0.5)
    both = _write(8, 2, [poor, poor_south], POINTS)
    assert both[CELL] == pytest.approx(off[CELL], rel=1e-6)
    # agree = 3 needs a third direction
    assert _write(8, 3, [poor, poor_south], POINTS)[CELL] == on[CELL]


def test_good_values_and_unscored_cells_are_as_without_bins() -> None:
    good = ((1.0, 5.0), [0.8, 0.1, 0.1], 0.5)  # above neutral: kept as it is
    off, on = _write(0, 2, [good], POINTS), _write(8, 2, [good], POINTS)
    assert on[CELL] == off[CELL]
    assert on[99, 99] == off[99, 99] == 0.0  # far from every point: never scored, 0 either way
    # a good value from one side and a poor one from the other: the best is kept (max over bins)
    poor = ((9.0, 5.0), [0.05, 0.5, 0.45], 0.9)
    assert _write(8, 2, [good, poor], POINTS)[CELL] == _write(0, 2, [good, poor], POINTS)[CELL]


def test_agree_one_is_the_layer_without_bins_bit_for_bit() -> None:
    rng = np.random.default_rng(3)
    views = []
    for _ in range(12):
        lsv = rng.dirichlet(np.ones(3)).tolist()
        views.append(((float(rng.uniform(0, 10)), float(rng.uniform(0, 10))), lsv, float(rng.uniform(0, 1))))
    assert np.array_equal(_write(8, 1, views, POINTS), _write(0, 1, views, POINTS))


# ---- real frames through EpisodeMap -------------------------------------------------------------------------


@pytest.fixture(scope="module")
def house(tmp_path_factory: pytest.TempPathFactory) -> tuple:
    scene = load_or_generate("gen-00007", Path(tmp_path_factory.mktemp("scenes")))
    return Renderer(scene), largest_room_spot(scene)


def _start() -> EpisodeStart:
    q = Question(text="Where is the sofa?", choices=["kitchen", "bedroom", "living room", "bathroom"], scene="gen-7")
    return EpisodeStart(episode_id="ep-vb", robot="r0", question=q, max_steps=20, strategy="semantic")


def _frame(renderer: Renderer, pose: Pose2D, step: int) -> Frame:
    return rendered_frame(renderer, pose, "ep-vb", step, W, H)


def _turn(renderer: Renderer, xy: tuple[float, float], config: MapperConfig, n: int = 6) -> EpisodeMap:
    episode_map = EpisodeMap(_start(), config)
    for k in range(n):
        episode_map.integrate(_frame(renderer, Pose2D(x=xy[0], y=xy[1], yaw=k * math.pi / 3), k))
        episode_map.apply_scores([0.1, 0.6, 0.3][: len(episode_map.prompts)], 0.7)
        episode_map.compute_frontiers()
    return episode_map


def test_off_by_default_and_on_changes_only_the_values(house: tuple) -> None:
    assert Settings().view_bins == 0 and MapperConfig().view_bins == 0
    renderer, xy = house
    off = _turn(renderer, xy, MapperConfig())
    assert not any("/view" in k or k.endswith("/neutral") for k in off.volume.planes)
    same = _turn(renderer, xy, MapperConfig(view_bins=8, view_agree=1))
    assert np.array_equal(same.layer(), off.layer()) and same.frontiers == off.frontiers
    on = _turn(renderer, xy, MapperConfig(view_bins=8, view_agree=2))
    assert np.array_equal(on.maps.free, off.maps.free) and on.prompts == off.prompts
    assert (on.layer() >= off.layer()).all() and (on.layer() > off.layer()).any()


def test_a_real_view_writes_the_bins_it_looks_through(house: tuple) -> None:
    """One frame looking east (yaw 0; the simulated camera sees 120 deg across): its prompt points lie in
    front, so with 8 bins only the sectors within 60 deg of east (6, 7, 0, 1) hold values: exactly the
    sectors of the points' bearings."""
    renderer, xy = house
    episode_map = EpisodeMap(_start(), MapperConfig(view_bins=8, view_agree=2))
    episode_map.integrate(_frame(renderer, Pose2D(x=xy[0], y=xy[1], yaw=0.0), 0))
    assert episode_map.prompts, "the test house must show free floor ahead"
    episode_map.apply_scores([1.0 / len(episode_map.prompts)] * len(episode_map.prompts), 0.5)
    planes = episode_map.volume.planes
    written = {b for b, name in enumerate(view_plane_names("question", 8)[:-1]) if planes[name].any()}
    assert written and written <= {6, 7, 0, 1}, written
    bearings = [math.atan2(p.y - xy[1], p.x - xy[0]) for p in episode_map.prompts]
    assert written == {math.floor((a % (2 * math.pi)) / (math.pi / 4)) for a in bearings}


def test_snapshot_round_trip_carries_the_bins(house: tuple) -> None:
    renderer, xy = house
    config = MapperConfig(view_bins=4, view_agree=2)
    episode_map = _turn(renderer, xy, config, n=4)
    back = EpisodeMap.restore(episode_map.snapshot(), config)
    for name in [*view_plane_names("question", 4), "value/question"]:
        assert np.array_equal(back.volume.planes[name], episode_map.volume.planes[name]), name
    # the restored map goes on exactly as the original: the same next step gives the same layer
    f = _frame(renderer, Pose2D(x=xy[0], y=xy[1], yaw=4 * math.pi / 3), 4)
    for m in (episode_map, back):
        m.integrate(f)
        m.apply_scores([0.2, 0.2, 0.6][: len(m.prompts)], 0.4)
    assert np.array_equal(back.layer(), episode_map.layer())
    assert any(back.volume.planes[n].any() for n in view_plane_names("question", 4)[:-1])


def test_memory_is_bins_times_cells(house: tuple) -> None:
    renderer, xy = house
    off = _turn(renderer, xy, MapperConfig(), n=2)
    on = _turn(renderer, xy, MapperConfig(view_bins=8, view_agree=2), n=2)
    cells = off.layer().size
    extra = sum(a.nbytes for a in on.volume.planes.values()) - sum(a.nbytes for a in off.volume.planes.values())
    assert extra == (8 + 1) * cells * 4  # 8 direction bins + the neutral plane, float32, per value layer
    with pytest.raises(ValidationError):
        Settings(view_bins=MAX_VIEW_BINS + 1)
    with pytest.raises(ValidationError):
        Settings(view_agree=0)

"""A warm question's budget subtracts the floor the home map has observed inside the house (eqa/budget.py,
services.mapper.home_memory.observed_floor): hand-computed cases of the pure rule, and the mapper's warm start on
a map that has seen a whole house while appendix B's narrow view explored only part of it."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from eqa.budget import warm_step_limit
from eqa.messages import EpisodeStart, Question
from eqa.settings import Settings
from eqa.store import EmbeddedStore
from services.mapper.episode_map import EpisodeMap
from services.mapper.home_memory import HomeMap, back_band_cells, observed_floor
from services.mapper.home_shell import HomeMemory
from services.mapper.projection import band


def test_back_band_is_the_occupied_band_in_cells() -> None:
    """0.4 truncation units of 5 voxels: fusion marks 2 cells behind a surface occupied."""
    assert back_band_cells(0.4, 5.0) == 2
    assert back_band_cells(0.5, 5.0) == 3  # 2.5 cells reach into a third
    assert back_band_cells(0.0, 5.0) == 0


def _room() -> tuple[np.ndarray, np.ndarray]:
    """8 x 8 grid: unknown edge ring; ring 1 occupied only (a wall seen from inside and the band behind it);
    inside (rows and columns 2-5) free, but (3, 3) occupied only (furniture) and (4, 4) never seen."""
    known = np.zeros((8, 8), dtype=bool)
    known[1:7, 1:7] = True
    known[4, 4] = False
    free = np.zeros((8, 8), dtype=bool)
    free[2:6, 2:6] = True
    free[3, 3] = False
    free[4, 4] = False
    return known, free


def test_observed_floor_hand_computed() -> None:
    known, free = _room()
    # no peel: every known column, 36 - 1 unseen
    assert observed_floor(known, free, 0).sum() == 35
    # a peel of 1 removes the occupied-only ring next to the outside: the 16 inside cells but the unseen one
    inside = observed_floor(known, free, 1)
    assert inside.sum() == 15 and not inside[1].any() and inside[3, 3] and not inside[4, 4]
    # a peel of 2 reaches ring 2, which is free: free columns are never removed
    assert observed_floor(known, free, 2).sum() == 15
    # a free column next to the outside (a doorway onto it) stays
    known[1, 3] = free[1, 3] = True
    assert observed_floor(known, free, 1).sum() == 16
    # a hole inside the house is not the outside: the furniture next to the unseen cell stays while the peel
    # does not reach it from the edge (3 cells away), and goes when it does
    assert observed_floor(known, free, 2)[3, 3] and not observed_floor(known, free, 3)[3, 3]


def test_observed_floor_with_the_outside_off_the_grid() -> None:
    """Known columns on the grid's edge touch the outside beyond it."""
    known = np.ones((4, 4), dtype=bool)
    free = np.zeros((4, 4), dtype=bool)
    free[1:3, 1:3] = True
    assert observed_floor(known, free, 1).sum() == 4
    assert observed_floor(np.zeros((0, 0), dtype=bool), np.zeros((0, 0), dtype=bool), 2).shape == (0, 0)


def _seen_house(em: EpisodeMap, explored_cols: int) -> tuple[int, int]:
    """Write into ``em``'s volume a 2 m x 2 m house (20 x 20 cells) seen whole with the full camera: inside free
    from the floor clearance to the camera height, a wall ring occupied, the 2 cells behind it occupied (fusion's
    back band), the rest of the grid never seen; appendix B's explored voxels only in the first ``explored_cols``
    columns of the inside. Returns (inside cells, wall ring cells)."""
    v = em.volume
    v.ensure(0.0, 3.0, 0.0, 3.0)
    r0, c0 = (int(a) for a in v.cell_of(0.5, 0.5))
    sl = band(v, em.config.projection)
    inside = (slice(r0, r0 + 20), slice(c0, c0 + 20))
    for k in (3, 2, 1):  # back band rings (2, 3 cells out), then the wall ring (1 cell out)
        ring = (slice(r0 - k, r0 + 20 + k), slice(c0 - k, c0 + 20 + k))
        v.weight[ring[0], ring[1], sl] = 1.0
        v.tsdf[ring[0], ring[1], sl] = -0.1
    v.tsdf[inside[0], inside[1], sl] = 1.0
    v.explored[r0:r0 + 20, c0:c0 + explored_cols, sl.start] = True
    em.step = 0
    return 400, 22 * 22 - 400


def test_the_warm_budget_subtracts_the_observed_floor_not_the_explored(tmp_path: Path) -> None:
    """A house seen whole whose explored mask covers only half of it: with the observed floor the warm question
    owes nothing more than the least share (``A_e`` = the inside and its wall ring, more than the 4 m2 its budget
    stands for); with the explored floor it would still be given steps for the half it has seen."""
    store = EmbeddedStore(tmp_path / "home.sqlite")
    try:
        q = Question(text="Where is the mug?", choices=["kitchen", "bedroom"], scene="gen-00007")
        max_steps = 6  # stands for (6 / 3)^2 = 4 m2
        for area, home in (("observed", "h-o"), ("explored", "h-e")):
            settings = Settings(data_dir=tmp_path / "var", home_warm_area=area, home_warm_budget=0.15)
            memory = HomeMemory(settings, lambda: store, lambda: None)
            first = EpisodeMap(EpisodeStart(episode_id=f"ep1-{home}", robot="r0", question=q, max_steps=max_steps,
                                            home=home))
            memory.start(first.start, first)
            inside, wall = _seen_house(first, explored_cols=10)
            assert memory.commit(first) is not None
            stored = memory.read_map(home)
            assert stored is not None and stored.explored_cells() == 200
            start = EpisodeStart(episode_id=f"ep2-{home}", robot="r0", question=q, max_steps=max_steps, home=home)
            second = EpisodeMap(start)
            memory.start(start, second)
            ep = memory.episodes[start.episode_id]
            if area == "observed":
                # the inside and the wall ring; the back band (2 cells, next to the outside) is peeled
                assert ep.loaded_cells == inside + wall
                assert ep.step_limit == warm_step_limit(max_steps, (inside + wall) * 0.01, 0.15) == 1
            else:
                assert ep.loaded_cells == 200  # 2 m2 explored of the 4: 3 sqrt(2) = 4 steps
                assert ep.step_limit == warm_step_limit(max_steps, 2.0, 0.15) == 4
    finally:
        store.close()


def test_a_home_map_without_observations_covers_nothing() -> None:
    hm = HomeMap(0.1, 0.0, 0.0, np.zeros((0, 0, 37), np.float32), np.zeros((0, 0, 37), np.float32),
                 np.zeros((0, 0, 37), bool), np.zeros((0, 0), bool))
    assert hm.explored_cells() == 0

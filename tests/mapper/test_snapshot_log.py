"""Incremental map snapshots (services/mapper/snapshots.py) and state parts in the episode-service base.

Frames are rendered from a generated house; the map restored from the stored parts (full part + deltas +
header) must equal the live map bit for bit: every step, across compactions, after the grid grew, and after
a restart mid-episode (the restored map goes on, its saves continue the log).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from support.scenes import free_cell_walk, rendered_frame

from eqa.codec import unpackb
from eqa.episode_service import EpisodeService, StateParts
from eqa.messages import EpisodeStart, Frame, Question
from eqa.settings import Settings
from eqa.store import EmbeddedStore, episode_part_key, episode_state_key
from services.mapper import snapshots
from services.mapper.episode_map import EpisodeMap
from services.sim.library import load_or_generate
from services.sim.render import Renderer

W, H = 160, 120


@pytest.fixture(scope="module")
def frames(tmp_path_factory: pytest.TempPathFactory) -> list[Frame]:
    """A walk through the house's free cells that turns as it goes: the grid grows several times."""
    scene = load_or_generate("gen-00007", Path(tmp_path_factory.mktemp("scenes")))
    renderer = Renderer(scene)
    return [rendered_frame(renderer, pose, "ep-snap", step, W, H)
            for step, pose in enumerate(free_cell_walk(scene, 24, seed=5, turn_rad=1.1))]


def make_map() -> EpisodeMap:
    q = Question(text="Where is the sofa?", choices=["kitchen", "bedroom", "living room", "bathroom"], scene="gen-7")
    return EpisodeMap(EpisodeStart(episode_id="ep-snap", robot="r0", question=q, max_steps=30))


def step(episode_map: EpisodeMap, f: Frame) -> None:
    episode_map.integrate(f)
    episode_map.apply_scores([0.6, 0.3, 0.1, 0.5][: len(episode_map.prompts)], 0.7)
    episode_map.compute_frontiers()


def assert_same(a: EpisodeMap, b: EpisodeMap) -> None:
    va, vb = a.volume, b.volume
    assert (va.origin_x, va.origin_y) == (vb.origin_x, vb.origin_y)
    for name in ("tsdf", "weight", "explored"):
        x, y = getattr(va, name), getattr(vb, name)
        assert x.shape == y.shape and x.tobytes() == y.tobytes(), name
    assert sorted(va.planes) == sorted(vb.planes)
    for name in va.planes:
        assert va.planes[name].tobytes() == vb.planes[name].tobytes(), name
    assert (a.step, a.pose, a.frontiers, a.prompts) == (b.step, b.pose, b.frontiers, b.prompts)
    for name in ("occupied", "free", "free_all", "explored", "observed"):
        assert np.array_equal(getattr(a.maps, name), getattr(b.maps, name)), name


class Parts:
    """The store side of StateParts: parts written, then the header, then obsolete parts deleted."""

    def __init__(self) -> None:
        self.parts: dict[str, bytes] = {}
        self.header = b""
        self.fulls = 0
        self.shape: tuple[int, int] | None = None
        self.grew_in_delta = False

    def save(self, episode_map: EpisodeMap, compact_every: int) -> int:
        before = self.shape
        header, write, delete = snapshots.snapshot_step(episode_map, compact_every)
        self.shape = episode_map.volume.shape2d
        self.grew_in_delta |= before not in (None, self.shape) and not any(n.startswith("f") for n in write)
        self.parts.update(write)
        self.header = header
        for name in delete:
            self.parts.pop(name)
        self.fulls += sum(name.startswith("f") for name in write)
        return len(header) + sum(len(d) for d in write.values())

    def restore(self) -> EpisodeMap:
        return snapshots.restore(self.header, self.parts.__getitem__)


def test_restore_equals_live_every_step_with_compaction(frames: list[Frame]) -> None:
    episode_map, store = make_map(), Parts()
    shapes, sizes = set(), []
    for f in frames:
        step(episode_map, f)
        sizes.append(store.save(episode_map, compact_every=5))
        shapes.add(episode_map.volume.shape2d)
        assert_same(store.restore(), episode_map)
        assert len(store.parts) <= 1 + 5  # obsolete parts are deleted: one full part and its deltas
    assert len(shapes) > 1, "the walk should make the grid grow"
    assert store.grew_in_delta, "a delta should have been taken on a grown grid (replay pads)"
    assert store.fulls >= 24 // 6
    full = len(episode_map.snapshot())
    assert min(sizes) < full / 2  # a delta step writes much less than the whole map


def test_restart_mid_episode_continues_the_log(frames: list[Frame]) -> None:
    live, store = make_map(), Parts()
    for f in frames[:10]:
        step(live, f)
        store.save(live, compact_every=50)
    restarted = store.restore()  # a new mapper process takes the episode up from the store
    assert_same(restarted, live)
    for f in frames[10:]:
        step(live, f)
        step(restarted, f)
        store.save(restarted, compact_every=50)
        assert_same(store.restore(), live)
    assert_same(restarted, live)


def test_whole_map_snapshot_still_restores(frames: list[Frame]) -> None:
    episode_map = make_map()
    for f in frames[:3]:
        step(episode_map, f)
    assert_same(snapshots.restore(episode_map.snapshot(), lambda name: b""), episode_map)


def test_bad_parts_are_refused(frames: list[Frame]) -> None:
    episode_map, store = make_map(), Parts()
    for k, f in enumerate([*frames[:2], frames[1], frames[1]]):  # the same view again: a small delta
        step(episode_map, f.model_copy(update={"step": k}))
        store.save(episode_map, compact_every=50)
    delta = next(n for n in store.parts if n.startswith("d"))
    store.parts.pop(delta)
    with pytest.raises(KeyError):
        store.restore()
    with pytest.raises(ValueError):
        snapshots.restore(b"\x93\x01\x02\x03", store.parts.__getitem__)


class PartsService(EpisodeService[dict]):
    """A minimal service on the base whose state spans keys: one part per save, the previous one deleted."""

    name = "partstest"

    def start_episode(self, robot: str, start: EpisodeStart) -> dict:
        return {"n": 0}

    def dump_state(self, state: dict, **extra: object) -> object:
        state["n"] += 1
        n = state["n"]
        return StateParts({"n": n}, {f"p{n}": b"x" * n}, [f"p{n - 1}"] if n > 1 else [])

    def load_state(self, episode_id: str, data: object) -> dict:
        assert isinstance(data, dict)
        n = int(data["n"])
        if self.read_part(episode_id, f"p{n}") != b"x" * n:
            raise ValueError("part does not match")
        return {"n": n}


def test_base_writes_reads_and_drops_parts(tmp_path: Path) -> None:
    store = EmbeddedStore(tmp_path / "store.sqlite")
    settings = Settings(data_dir=tmp_path, record=False)
    svc = PartsService(settings, store=store)
    q = Question(text="q?", choices=["a", "b"], scene="gen-7")
    svc._on_start("r0", EpisodeStart(episode_id="ep-p", robot="r0", question=q, max_steps=5))
    for _ in range(3):
        svc.save("ep-p")
    body = unpackb(store.get(episode_state_key("partstest", "ep-p")))
    assert body["parts"] == ["p4"] and body["state"] == {"n": 4}
    assert store.get(episode_part_key("partstest", "ep-p", "p3")) is None  # deleted after the envelope
    # a restarted instance restores from the envelope and its part
    svc2 = PartsService(settings, store=store)
    assert svc2.episode("ep-p") == {"n": 4}
    # a missing part makes the stored state unusable: dropped with its parts
    store.delete(episode_part_key("partstest", "ep-p", "p4"))
    svc3 = PartsService(settings, store=store)
    assert svc3.episode("ep-p") is None and store.get(episode_state_key("partstest", "ep-p")) is None
    # drop deletes the parts with the envelope
    svc2.save("ep-p")
    assert store.get(episode_part_key("partstest", "ep-p", "p5")) is not None
    svc2.drop("ep-p")
    assert store.get(episode_part_key("partstest", "ep-p", "p5")) is None
    assert store.get(episode_state_key("partstest", "ep-p")) is None
    store.close()

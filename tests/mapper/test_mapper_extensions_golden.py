"""Golden outputs of the mapper with all three extensions at work, over real Zenoh and Redis: a question episode
with object evidence and the joint answer memory (EQA_OBJECT_EVIDENCE, EQA_ANSWER_MEMORY_MODE=joint) and a task
episode with the HELIOS object layer, each through two steps, a resent step (answered again from the stored
map), a mapper restart (restored from the store) and one more step. The published MapUpdate and StepScores and
the stored state's layout are compared with a digest taken from the mapper as it is; a change of any extension's
published output or stored parts changes it. Floats are rounded to 4 decimals (the digest is of the results,
not of the last bit of a BLAS sum); timings and send times are left out (they differ run to run).

The scorer replica answers in-process (the real ScorerService with the hf backend on a tiny random Qwen2-VL
built offline, and the simulated detector: simulated perception model, not a VLM/detector); the mapper's
messages travel over the bus."""

from __future__ import annotations

import hashlib
import io
import json
import queue
import time
import zipfile
from typing import Any

import numpy as np
import pytest
from pydantic import BaseModel
from support.objects import frame_of, ring_views

from eqa import keys
from eqa.bus import Bus
from eqa.codec import unpackb
from eqa.messages import EpisodeStart, ErrorReply, MapUpdate, Question, StepScores, StopConfig, Task
from eqa.settings import Settings
from eqa.store import RedisStore, episode_state_key
from services.mapper.service import MapperService
from services.sim.housegen import generate_house
from services.sim.render import Renderer
from services.vlm_scorer.backends.hf import HFBackend
from services.vlm_scorer.service import ScorerService
from services.vlm_scorer.tiny import build_tiny_qwen2vl

ROBOT = "r0"
W, H = 160, 120
EPISODES = ("ep-gq", "ep-gt")  # a question with evidence and memory, a task
LEFT_OUT = frozenset({"timing_ms", "sent_at", "request_id"})
# fields the digests were recorded without, left out while empty (StepScores.memory, step_limit, warm, presence:
# an episode in no home, no presence query)
EMPTY_LEFT_OUT = frozenset({"memory", "step_limit", "warm", "presence"})

# sha256 of the canonical outputs (canonical() below) of the run in the test
GOLDEN = {
    "ep-gq": "b644ea723407dbe6bf4b6aa547a272911c6e2b441ed44355b1094f1be37981c3",
    # the task: its maps take obstacles from 0.05 m up, its gaze points keep 0.25 m from mapped obstacles
    "ep-gt": "4db7de6d53f5ab80dc2ed3376918862ae08954eb9e2c40a65fb17666b78e6322",
    "state:ep-gq": "679919489d4164039fb66a1a5da65085183b05ce70a687f4d18b020346b71198",
    "state:ep-gt": "5bb70274fc4aa79bb949da70f4103f59ccdc83e3f9796e8bd117aa67fee64a6e",
}


def canonical(x: Any) -> Any:
    """JSON-able form of a message or stored state: floats rounded to 4 decimals, arrays as (dtype, shape,
    rounded values), stored parts decoded (:func:`decoded`), timings left out."""
    if isinstance(x, BaseModel):
        return canonical({name: getattr(x, name) for name in type(x).model_fields
                          if not (name in EMPTY_LEFT_OUT and not getattr(x, name))})
    if isinstance(x, dict):
        return {str(k): canonical(v) for k, v in sorted(x.items(), key=lambda kv: str(kv[0])) if k not in LEFT_OUT}
    if isinstance(x, list | tuple):
        return [canonical(v) for v in x]
    if isinstance(x, np.ndarray):
        vals = np.round(x.astype(np.float64), 4) + 0.0 if x.dtype.kind == "f" else x
        return [str(x.dtype), list(x.shape), vals.tolist()]
    if isinstance(x, float | np.floating):
        return round(float(x), 4) + 0.0
    if isinstance(x, np.integer | np.bool_):
        return x.item()
    if isinstance(x, bytes):
        return canonical(decoded(x))
    return x


def decoded(data: bytes) -> Any:
    """A stored part's contents: a zip (the object layer's snapshot: its entries' contents, not their file
    times), msgpack, or else the bytes' sha256."""
    if data[:2] == b"PK":
        with zipfile.ZipFile(io.BytesIO(data)) as z:
            return {name: decoded(z.read(name)) for name in z.namelist()}
    if data[:6] == b"\x93NUMPY":
        return np.load(io.BytesIO(data))
    try:
        return json.loads(data)
    except ValueError:
        pass
    try:
        return unpackb(data)
    except Exception:
        return hashlib.sha256(data).hexdigest()


def digest(x: Any) -> str:
    return hashlib.sha256(json.dumps(canonical(x), sort_keys=True).encode()).hexdigest()


def stored_layout(store: RedisStore, episode_id: str) -> dict[str, Any]:
    """The stored envelope's state: which parts ride along (and their contents but for the step timings), the
    names of the map's parts."""
    body = unpackb(store.get(episode_state_key("mapper", episode_id)))
    state = body["state"]
    if isinstance(state, dict):
        state = {k: v for k, v in state.items() if k != "made"}
    return {"state": state, "parts": body.get("parts")}


@pytest.fixture(scope="module")
def scene_views():
    scene = generate_house(5)
    renderer = Renderer(scene)
    return scene, renderer, ring_views(scene, renderer, 25, W, H)


@pytest.fixture(scope="module")
def backend(tmp_path_factory: pytest.TempPathFactory) -> HFBackend:
    return HFBackend(build_tiny_qwen2vl(tmp_path_factory.mktemp("tiny") / "qwen2vl"))


def starts(scene) -> list[EpisodeStart]:
    chair = scene.instances[25]
    room = next(r for r in scene.rooms if r.contains(chair.position[0], chair.position[1]))
    q = Question(text=f"Is there a chair in the {room.kind.replace('_', ' ')}?", choices=["Yes", "No"],
                 scene="gen-5")
    task = Task(kind="find_object", text="Find a chair", scene="gen-5", object="chair")
    return [
        EpisodeStart(episode_id="ep-gq", robot=ROBOT, question=q, max_steps=20, record=False, seed=1,
                     stop=StopConfig(rule="max_steps")),
        EpisodeStart(episode_id="ep-gt", robot=ROBOT, question=Question(text="Find a chair", scene="gen-5"),
                     max_steps=20, record=False, task=task, seed=1),
    ]


def test_mapper_outputs_with_every_extension_match_the_golden_digest(
        hub_settings: Settings, settings: Settings, scene_views, backend: HFBackend, redis_url: str) -> None:
    scene, renderer, views = scene_views
    settings = settings.model_copy(update={
        "redis_url": redis_url, "object_evidence": True, "answer_memory_mode": "joint", "answer_memory_views": 2,
        "detector_oracle_background_fp": 0.0})
    store = RedisStore(redis_url)  # the session's redis: nothing left of these episodes by an earlier test
    store.delete_many([k for k in store.keys("eqa:") if any(eid in k for eid in EPISODES)])
    pool = ScorerService(settings, backend=backend)  # answers in-process: the mapper's calls, no queryable

    def mapper() -> MapperService:
        m = MapperService(settings, scorer=pool.handle, detector=pool.handle_detect, values=pool.handle_values)
        m.start()
        time.sleep(0.5)
        return m

    got: dict[str, list[Any]] = {eid: [] for eid in EPISODES}
    inbox: queue.Queue[MapUpdate | StepScores] = queue.Queue()
    errors: queue.Queue[ErrorReply] = queue.Queue()
    with Bus(hub_settings, "gateway") as bus:
        bus.subscribe(keys.stream(ROBOT, keys.MAPPER_MAP), MapUpdate, lambda k, m: inbox.put(m))
        bus.subscribe(keys.stream(ROBOT, keys.MAPPER_SCORES), StepScores, lambda k, m: inbox.put(m))
        bus.subscribe(keys.stream(ROBOT, keys.MAPPER_ERROR), ErrorReply, lambda k, m: errors.put(m))

        def step(episode_id: str, n: int) -> None:
            bus.publish(keys.stream(ROBOT, keys.SIM_FRAME), frame_of(views[n], renderer, episode_id, n))
            out = sorted((inbox.get(timeout=60) for _ in range(2)), key=lambda m: m.kind)  # the map and scores
            assert all(m.episode_id == episode_id and m.step == n for m in out), out
            got[episode_id] += out

        m = mapper()
        try:
            for start in starts(scene):
                bus.publish(keys.stream(ROBOT, keys.EPISODE_START), start)
            for n in (0, 1):
                step("ep-gq", n)
                step("ep-gt", n)
            step("ep-gq", 1)  # sent again: answered from the stored map
            step("ep-gt", 1)
            m.stop()
            m = mapper()  # a restart: the episodes come back from the store
            step("ep-gq", 2)
            step("ep-gt", 2)
            assert errors.empty(), errors.get()
        finally:
            m.stop()
    assert [s.answer_views for s in got["ep-gq"] if isinstance(s, StepScores)][:2] == [[0], [0, 1]]
    assert all(s.object_evidence is not None for s in got["ep-gq"] if isinstance(s, StepScores))
    maps = [u for u in got["ep-gt"] if isinstance(u, MapUpdate)]
    assert maps[-1].objects and "helios:chair" in maps[-1].values
    # the order of the stored parts (the bytes of the envelope): the map, then the extensions in their order
    order = {eid: list(unpackb(store.get(episode_state_key("mapper", eid)))["state"]) for eid in EPISODES}
    assert order == {"ep-gq": ["map", "question_objects", "answer_views", "made"], "ep-gt": ["map", "objects", "made"]}
    digests = {eid: digest(msgs) for eid, msgs in got.items()}
    digests |= {f"state:{eid}": digest(stored_layout(store, eid)) for eid in got}
    assert digests == GOLDEN

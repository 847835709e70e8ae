"""The mapper's HELIOS object layer over real Zenoh: a task episode's frames are detected through the scorer
pool (an in-process scorer replica, simulated detector), fused, and summarised in MapUpdate.objects; per-target
value layers; the layer survives a mapper restart (snapshot in the store); question episodes carry no objects."""

from __future__ import annotations

import queue
import time

import pytest
from support.objects import frame_of, ring_views

from eqa import keys
from eqa.bus import Bus
from eqa.messages import EpisodeStart, ErrorReply, MapUpdate, Question, Task
from eqa.settings import Settings
from services.mapper.service import MapperService
from services.sim.housegen import generate_house
from services.sim.render import Renderer
from services.vlm_scorer.service import ScorerService

ROBOT = "r0"
W, H = 160, 120


@pytest.fixture(scope="module")
def chair_views():
    scene = generate_house(5)
    renderer = Renderer(scene)
    return scene, renderer, ring_views(scene, renderer, 25, W, H)


def task_start(episode_id: str) -> EpisodeStart:
    task = Task(kind="find_object", text="Find a chair", scene="gen-5", object="chair")
    q = Question(text="Find a chair", scene="gen-5")
    return EpisodeStart(episode_id=episode_id, robot=ROBOT, question=q, max_steps=20, record=False, task=task,
                        seed=1)


def test_task_episode_objects_survive_a_mapper_restart(hub_settings: Settings, settings: Settings, chair_views,
                                                        redis_url: str) -> None:
    scene, renderer, views = chair_views
    settings = settings.model_copy(update={"redis_url": redis_url, "scorer_replica": "objs",
                                           "detector_oracle_background_fp": 0.0})
    maps: queue.Queue[MapUpdate] = queue.Queue()
    errors: queue.Queue[ErrorReply] = queue.Queue()
    with Bus(hub_settings, "gateway") as bus:
        bus.subscribe(keys.stream(ROBOT, keys.MAPPER_MAP), MapUpdate, lambda k, m: maps.put(m))
        bus.subscribe(keys.stream(ROBOT, keys.MAPPER_ERROR), ErrorReply, lambda k, m: errors.put(m))
        scorer = ScorerService(settings)
        scorer.start()
        mapper = MapperService(settings)
        mapper.start()
        try:
            time.sleep(0.5)
            bus.publish(keys.stream(ROBOT, keys.EPISODE_START), task_start("ep-objs"))
            for step in (0, 1):
                bus.publish(keys.stream(ROBOT, keys.SIM_FRAME), frame_of(views[step], renderer, "ep-objs", step))
                m = maps.get(timeout=60)
                assert m.step == step
            assert errors.empty(), errors.get()
            chairs = [o for o in m.objects if o.cls == "chair"]
            assert chairs, m.objects
            pos = scene.instances[25].position
            chair = min(chairs, key=lambda o: abs(o.centre[0] - pos[0]) + abs(o.centre[1] - pos[1]))
            assert abs(chair.centre[0] - pos[0]) < 0.5 and abs(chair.centre[1] - pos[1]) < 0.5
            assert set(chair.scores) == {"chair"} and chair.n_gaussians > 0
            assert chair.gaze and chair.ig > 0  # a candidate: gaze points scored with Psi' and IG
            assert "helios:chair" in m.values and float(m.values["helios:chair"].max()) > 0
            # restart: a new mapper process state from the store only
            mapper.stop()
            mapper = MapperService(settings)
            mapper.start()
            time.sleep(0.5)
            bus.publish(keys.stream(ROBOT, keys.SIM_FRAME), frame_of(views[2], renderer, "ep-objs", 2))
            m2 = maps.get(timeout=60)
            assert m2.step == 2 and errors.empty()
            after = {o.instance_id: o for o in m2.objects}
            assert chair.instance_id in after  # the same instance, carried over the restart
            assert after[chair.instance_id].n_gaussians >= chair.n_gaussians * 0.8
            assert after[chair.instance_id].psi > chair.psi  # a third consistent view raised it

            # a question episode has no object layer and no detection requests
            q = Question(text="Is the TV on?", choices=["yes", "no"], scene="gen-5")
            bus.publish(keys.stream(ROBOT, keys.EPISODE_START),
                        EpisodeStart(episode_id="ep-q", robot=ROBOT, question=q, max_steps=5, record=False))
            bus.publish(keys.stream(ROBOT, keys.SIM_FRAME), frame_of(views[0], renderer, "ep-q", 0))
            mq = maps.get(timeout=60)
            assert mq.episode_id == "ep-q" and mq.objects == [] and set(mq.values) == {"question"}
        finally:
            mapper.stop()
            scorer.stop()

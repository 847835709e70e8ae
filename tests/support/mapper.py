"""What the mapper service tests feed the mapper and how they read what it publishes: frames of one robot
in gen-00007 at 160x120, the episode start, and a collector of its outputs."""

from __future__ import annotations

import math
import queue
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any

from eqa import keys
from eqa.bus import Bus
from eqa.messages import EpisodeStart, ErrorReply, Frame, MapUpdate, Pose2D, Question, StepScores
from eqa.settings import Settings
from services.sim.render import Renderer
from support.fleet import wait_for
from support.scenes import rendered_frame

if TYPE_CHECKING:
    from services.mapper.service import MapperService

W, H = 160, 120
ROBOT = "r0"


def frame(renderer: Renderer, episode_id: str, step: int, x: float = 8.75, y: float = 4.35) -> Frame:
    return rendered_frame(renderer, Pose2D(x=x, y=y, yaw=step * math.pi / 4), episode_id, step, W, H, instances=True)


def start_msg(episode_id: str) -> EpisodeStart:
    q = Question(text="Is the TV on?", choices=["yes", "no"], scene="gen-00007", answer="A", evidence_ids=[3])
    return EpisodeStart(episode_id=episode_id, robot=ROBOT, question=q, max_steps=20, record=False)


class Collector:
    """Subscribes to the mapper's outputs of one robot."""

    def __init__(self, bus: Bus) -> None:
        self.maps: queue.Queue[MapUpdate] = queue.Queue()
        self.scores: queue.Queue[StepScores] = queue.Queue()
        self.errors: queue.Queue[ErrorReply] = queue.Queue()
        bus.subscribe(keys.stream(ROBOT, keys.MAPPER_MAP), MapUpdate, lambda k, m: self.maps.put(m))
        bus.subscribe(keys.stream(ROBOT, keys.MAPPER_SCORES), StepScores, lambda k, m: self.scores.put(m))
        bus.subscribe(keys.stream(ROBOT, keys.MAPPER_ERROR), ErrorReply, lambda k, m: self.errors.put(m))

    def step(self, step: int) -> tuple[MapUpdate, StepScores]:
        """The map update and scores of ``step`` (the next ones to arrive)."""
        m, s = self.maps.get(timeout=60), self.scores.get(timeout=60)
        assert m.step == step and s.step == step, (m.step, s.step)
        return m, s


class HomeRig:
    """A scorer replica (the oracle backend: simulated perception model, not a VLM) and mapper instances over one
    bus, a home emptied first (:func:`home_rig`)."""

    def __init__(self, bus: Bus, out: Collector, mapper: MapperService) -> None:
        self.bus, self.out, self.mapper = bus, out, mapper
        self.started: list[MapperService] = [mapper]

    def instance(self, settings: Settings, **kwargs: Any) -> MapperService:
        """Another mapper instance (stopped with the rig)."""
        from services.mapper.service import MapperService

        other = MapperService(settings, **kwargs)
        other.start()
        self.started.append(other)
        self.settle()
        return other

    def settle(self, timeout: float = 30.0) -> None:
        """Wait until this bus sees exactly the running mapper instances (and a scorer replica) alive and each
        instance counts the same live set. Until then a frame may reach an instance that still counts a stopped
        one as the robot's owner and drops it; with no planner in the rig to send the step again, it stays lost."""
        running = [m for m in self.started if not m.stopped]
        want = {m.bus.instance for m in running}

        def settled() -> bool:
            seen = {inst for _svc, inst in self.bus.alive(keys.alive_service("mapper"), timeout=0.5)}
            return (seen == want and bool(self.bus.alive(keys.alive_service("vlm_scorer"), timeout=0.5))
                    and all(m.shard is None or m.shard.membership.live == want for m in running))

        if not wait_for(settled, timeout, every=0.1):
            raise AssertionError(f"mapper instances {sorted(want)} and a scorer replica not all seen alive "
                                 f"within {timeout} s")


@contextmanager
def home_rig(hub_settings: Settings, settings: Settings, home: str, **kwargs: Any) -> Iterator[HomeRig]:
    """The bus (opened with ``hub_settings``), a collector, a scorer replica and a mapper (``kwargs``: its injected
    detector / values) with ``settings``; ``home`` deleted first; everything stopped at the end."""
    from eqa import homes
    from services.mapper.service import MapperService
    from services.vlm_scorer.service import ScorerService

    with Bus(hub_settings, "gateway") as bus:
        out = Collector(bus)
        scorer = ScorerService(settings)
        scorer.start()
        rig = HomeRig(bus, out, MapperService(settings, **kwargs))
        rig.mapper.start()
        try:
            homes.delete_home(rig.mapper.store, home, 60.0)
            rig.settle()
            yield rig
        finally:
            for m in reversed(rig.started):
                m.stop()
            scorer.stop()

"""A scripted stand-in for the services' side of the choreography, for gateway tests and the gateway bench
while the real services are not all running.

It is a real Zenoh peer that publishes real messages (``Frame``, ``MapUpdate``, ``StepScores``,
``Decision``, ``Goal``, ``EpisodeEnd``) for each ``EpisodeStart`` it sees, at a configurable pace, and
holds the liveliness tokens of the five services. It is not a simulator: frames are small constant images,
and the prediction set shrinks by one letter per step until one is left (or the budget runs out). Scenes
named ``missing`` make it answer like a sim that cannot load the scene (``ErrorReply`` on ``sim/error``);
scenes named ``silent`` get no answer at all (to exercise the watchdog).
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from eqa import keys
from eqa.bus import Bus
from eqa.messages import (
    Decision,
    EpisodeCancel,
    EpisodeEnd,
    EpisodeStart,
    ErrorReply,
    Frame,
    Frontier,
    Goal,
    GridSpec,
    MapUpdate,
    Pose2D,
    StepScores,
    letters,
)
from eqa.recording import EpisodeRecorder
from eqa.settings import Settings
from eqa.store import Store
from gateway.manager import STOPPER_END_PREFIX

log = logging.getLogger(__name__)

SERVICES = ("sim", "mapper", "vlm_scorer", "planner", "stopper")


@dataclass
class FleetScript:
    step_delay_s: float = 0.05
    steps: int | None = None  # steps before stopping; None = until one answer is left
    end_gate: threading.Event | None = None  # when set, EpisodeEnd waits for it
    record: bool = False  # write Rerun files like the services would (a few entities)
    image_hw: tuple[int, int] = (24, 32)
    started: list[str] = field(default_factory=list)


class ScriptedFleet:
    """Use as a context manager; ``bus`` may be the test's hub bus or a fresh one."""

    def __init__(
        self,
        settings: Settings,
        script: FleetScript | None = None,
        services: tuple[str, ...] = SERVICES,
        store: Store | None = None,
    ) -> None:
        self.settings = settings
        self.script = script or FleetScript()
        self.services = services
        self.store = store  # when given, each EpisodeEnd is stored before it is published, as the stopper does
        self.bus = Bus(settings, "fleet", f"fleet-{settings.instance}"[:64])
        self._cancelled: set[str] = set()
        self._threads: list[threading.Thread] = []
        self._stop = threading.Event()
        self._tokens: list[Any | None] = []

    def __enter__(self) -> ScriptedFleet:
        self.bus.open()
        self.bus.subscribe(keys.any_robot(keys.EPISODE_START), EpisodeStart, self._on_start)
        self.bus.subscribe(keys.any_robot(keys.EPISODE_CANCEL), EpisodeCancel, self._on_cancel)
        lv = self.bus.session.liveliness()
        for svc in self.services:
            self._tokens.append(lv.declare_token(keys.alive(svc, "scripted")))
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        if self.script.end_gate is not None:
            self.script.end_gate.set()
        for t in self._threads:
            t.join(timeout=5)
        for tok in self._tokens:
            if tok is not None:
                tok.undeclare()
        self.bus.close()

    def drop_service(self, service: str) -> None:
        """Withdraw one service's liveliness token (as if it died)."""
        idx = self.services.index(service)
        token, self._tokens[idx] = self._tokens[idx], None
        if token is not None:
            token.undeclare()

    def _on_cancel(self, _key: str, msg: EpisodeCancel) -> None:
        self._cancelled.add(msg.episode_id)

    def _on_start(self, key: str, msg: EpisodeStart) -> None:
        self.script.started.append(msg.episode_id)
        t = threading.Thread(target=self._play, args=(keys.robot_of(key), msg), daemon=True)
        self._threads.append(t)
        t.start()

    def _alive(self, episode_id: str) -> bool:
        return not self._stop.is_set() and episode_id not in self._cancelled

    def _play(self, robot: str, start: EpisodeStart) -> None:
        try:
            self._run(robot, start)
        except Exception:
            log.exception("scripted episode %s failed", start.episode_id)

    def _run(self, robot: str, start: EpisodeStart) -> None:
        eid, q = start.episode_id, start.question
        pub = self.bus.publish
        if q.scene == "silent":
            return
        if q.scene == "missing":
            pub(
                keys.stream(robot, keys.SIM_ERROR),
                ErrorReply(source="sim", episode_id=eid, step=0, reason=f"unknown scene {q.scene!r}"),
            )
            return
        labels = letters(len(q.choices)) if q.choices else ["A", "B"]
        pset = list(labels)
        h, w = self.script.image_hw
        rec = {
            s: EpisodeRecorder(self.settings, eid, s, enabled=self.script.record and start.record)
            for s in ("sim", "stopper")
        }
        pose = start.question.start_pose or Pose2D(x=1.0, y=1.0, yaw=0.0)
        step = 0
        reason = "step limit reached"
        try:
            for step in range(start.max_steps):
                self._stop.wait(self.script.step_delay_s)
                if not self._alive(eid):
                    return
                rgb = np.full((h, w, 3), (step * 13) % 255, np.uint8)
                depth = np.full((h, w), 2.0, np.float32)
                pub(
                    keys.stream(robot, keys.SIM_FRAME),
                    Frame(
                        episode_id=eid,
                        step=step,
                        pose=pose,
                        camera_pose=np.eye(4),
                        intrinsics=np.eye(3),
                        rgb=rgb,
                        depth=depth,
                        scene=q.scene,
                    ),
                )
                self._log(rec, step, rgb, depth, pset)
                grid = GridSpec(origin_x=0, origin_y=0, resolution=0.5, rows=4, cols=4)
                pub(
                    keys.stream(robot, keys.MAPPER_MAP),
                    MapUpdate(
                        episode_id=eid,
                        step=step,
                        grid=grid,
                        occupied=np.zeros((4, 4), bool),
                        free=np.ones((4, 4), bool),
                        explored=np.ones((4, 4), bool),
                        pose=pose,
                        explored_area_m2=float(step + 1),
                        frontiers=[Frontier(x=2.0, y=1.0, nx=1.0, ny=0.0, size=3, weight=0.7)],
                    ),
                )
                probs = [1.0 / len(labels)] * len(labels)
                pub(
                    keys.stream(robot, keys.MAPPER_SCORES),
                    StepScores(episode_id=eid, step=step, answer_probs=probs, relevance=0.5, backend="scripted"),
                )
                if len(pset) > 1 and step > 0:
                    pset = pset[:-1]
                last = step == start.max_steps - 1
                done = len(pset) == 1 if self.script.steps is None else step + 1 >= self.script.steps
                stop = done or last
                if done:
                    reason = "one answer left" if len(pset) == 1 else "scripted stop"
                pub(
                    keys.stream(robot, keys.STOPPER_DECISION),
                    Decision(
                        episode_id=eid,
                        step=step,
                        rule=start.stop.rule,
                        stop=stop,
                        reason=reason if stop else "continue",
                        prediction_set=pset,
                        step_set=pset,
                        scores={k: 0.5 for k in pset},
                        answer=pset[0] if stop else None,
                    ),
                )
                if stop:
                    break
                pose = Pose2D(x=pose.x + 0.5, y=pose.y, yaw=pose.yaw)
                pub(keys.stream(robot, keys.PLANNER_GOAL), Goal(episode_id=eid, step=step, pose=pose))
            if self.script.end_gate is not None:
                while not self.script.end_gate.wait(0.05):
                    if not self._alive(eid):
                        return
            if not self._alive(eid):
                return
            end = EpisodeEnd(
                episode_id=eid,
                robot=robot,
                state="stopped",
                reason=reason,
                answer=pset[0],
                prediction_set=pset,
                steps=step + 1,
                max_steps=start.max_steps,
            )
            if self.store is not None:
                self.store.set(STOPPER_END_PREFIX + eid, end.model_dump_json().encode())
            pub(keys.stream(robot, keys.EPISODE_END), end)
        finally:
            for r in rec.values():
                r.close()

    @staticmethod
    def _log(rec: dict[str, EpisodeRecorder], step: int, rgb: np.ndarray, depth: np.ndarray, pset: list[str]) -> None:
        if not rec["sim"].enabled:
            return
        import rerun as rr

        from eqa.recording import ENTITIES

        for r in rec.values():
            r.set_step(step)
        rec["sim"].log(ENTITIES["rgb"], rr.Image(rgb))
        rec["sim"].log(ENTITIES["depth"], rr.DepthImage(depth, meter=1.0))
        rec["stopper"].log(ENTITIES["prediction_set"], rr.TextLog(",".join(pset)))

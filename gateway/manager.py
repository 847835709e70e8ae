"""Episode bookkeeping of the gateway: submit, queue per robot, start, follow, end, cancel, watchdog, and
reconciliation after a restart. Everything is persisted in the :class:`eqa.store.Store` (Redis in
production), so a restarted gateway loses no episode and no stored event.

Store layout (all keys under ``gw:``):

* ``gw:ep:{episode_id}``  JSON ``{"status": EpisodeStatus, "start": EpisodeStart}`` - the episode record.
* ``gw:ev:{episode_id}``  stream of compact JSON events (:mod:`gateway.events`); the entry ids are the SSE
  event ids, so a client resuming with ``Last-Event-ID`` gets every stored event exactly once.
* ``gw:robot:{robot}``    id of the episode running on the robot (absent = robot free).
* ``gw:queue:{robot}``    JSON list of queued episode ids (``EQA_BUSY_POLICY=queue``).

Restart semantics (the choice documented for issue #8). Bus messages published while no gateway runs are
not seen by any gateway, so they are not in the event stream. On start the gateway reconciles: every
episode stored as ``running`` gets a ``gateway_restart`` event (naming the time of the last event it saw,
so a client knows where the stream may have a hole), and its watchdog clock restarts from the restart time.
If the services are still working on it, its later events are picked up live and the episode ends
normally on the stopper's ``EpisodeEnd``. If the episode ended while the gateway was down, the stopper's
copy of the ``EpisodeEnd`` in the store (``eqa:stopper:end:{episode_id}``, written before it publishes)
ends it with the stopper's answer and reason, at reconciliation or at the latest when the watchdog would
fire; the recovered ``episode_end`` event is marked ``recovered``. Only when no end is stored either does the
watchdog fail the episode after ``EQA_EPISODE_TIMEOUT_S``, with a reason saying that nothing arrived, which
services are not alive, and that the gateway restarted meanwhile. Queued episodes start as soon as their
robot is free. Every event stream ends with exactly one ``episode_end`` event (from the stopper or made by
the gateway).
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

from eqa import keys
from eqa.bus import Bus
from eqa.messages import (
    Decision,
    EpisodeCancel,
    EpisodeEnd,
    EpisodeStart,
    EpisodeStatus,
    ErrorReply,
    Frame,
    Message,
    Question,
    new_id,
)
from eqa.recording import recording_dir
from eqa.settings import Settings
from eqa.store import Store, episode_end_key
from gateway.events import gateway_event, summarize
from gateway.schemas import QuestionRequest, Submitted

log = logging.getLogger(__name__)

REQUIRED_SERVICES = ("sim", "mapper", "vlm_scorer", "planner", "stopper")
TERMINAL = frozenset({"stopped", "failed", "cancelled"})
DEFAULT_MAX_STEPS = 30  # 3*sqrt(100 m^2): a mid-sized home, when the floor area is unknown


class GatewayError(Exception):
    """Base of the errors the routes turn into HTTP answers."""

    status_code = 400

    def __init__(self, message: str, field: str | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.field = field


class NotFoundError(GatewayError):
    status_code = 404


class BusyError(GatewayError):
    status_code = 409


class ConflictError(GatewayError):
    status_code = 409


class InvalidError(GatewayError):
    status_code = 422


def ep_key(episode_id: str) -> str:
    return f"gw:ep:{episode_id}"


def ev_key(episode_id: str) -> str:
    return f"gw:ev:{episode_id}"


def robot_key(robot: str) -> str:
    return f"gw:robot:{robot}"


def queue_key(robot: str) -> str:
    return f"gw:queue:{robot}"


@dataclass
class Record:
    status: EpisodeStatus
    start: EpisodeStart
    last_activity: float = field(default_factory=time.time)  # watchdog clock (not persisted)
    last_error: str | None = None  # the last ErrorReply of the episode, for the watchdog's reason (not persisted)

    def dump(self) -> dict[str, Any]:
        return {"status": self.status.model_dump(mode="json"), "start": self.start.model_dump(mode="json")}

    @classmethod
    def load(cls, raw: dict[str, Any]) -> Record:
        status = EpisodeStatus.model_validate(raw["status"])
        return cls(status=status, start=EpisodeStart.model_validate(raw["start"]), last_activity=status.updated_at)


# Floor area (m2) of a scene: ``(scene id, scenes dir, hm3d dir or None)``; raises when the scene cannot be
# loaded. The gateway imports no service: the process entry (``python -m gateway``, ``eqa gateway``) passes the
# simulator's scene library (``services.sim.library.floor_area``); without one, budgets are the default.
SceneArea = Callable[[str, Path, Path | None], float]


@lru_cache(maxsize=256)
def _scene_area(scene_area: SceneArea, scene: str, scenes_path: Path, hm3d_dir: Path | None) -> float:
    return float(scene_area(scene, scenes_path, hm3d_dir))


def step_budget(settings: Settings, req: QuestionRequest, scene_area: SceneArea | None = None) -> int:
    """``max_steps`` of an episode: the request's budget, else ``int(3*sqrt(floor area))`` (Explore-EQA
    section VI: T = 3 * sqrt(scene area)), else :data:`DEFAULT_MAX_STEPS`."""
    if req.max_steps is not None:
        return req.max_steps
    if req.scene is None or scene_area is None:
        return DEFAULT_MAX_STEPS
    try:
        area = _scene_area(scene_area, req.scene, settings.scenes_path, settings.hm3d_dir)
    except Exception as exc:
        raise InvalidError(f"scene {req.scene!r} cannot be loaded: {exc}", field="scene") from exc
    if area is None or not math.isfinite(area) or area <= 0:
        return DEFAULT_MAX_STEPS
    return max(1, int(3 * math.sqrt(area)))


class EpisodeManager:
    """All episode state transitions. Thread-safe (one lock); store and bus calls are blocking, so async
    callers run these methods in a worker thread."""

    def __init__(self, settings: Settings, store: Store, bus: Bus, notify: Callable[[], None] | None = None,
                 scene_area: SceneArea | None = None) -> None:
        self.settings = settings
        self.scene_area = scene_area
        self.store = store
        self.bus = bus
        self.notify = notify or (lambda: None)
        self._lock = threading.RLock()
        self._active: dict[str, Record] = {}
        # Copies of the active episodes' last saved status, read without the lock (fast status route).
        self._snapshots: dict[str, EpisodeStatus] = {}
        self._alive: dict[str, set[str]] = {}
        self.started_at = time.time()

    # ---- startup ----------------------------------------------------------------------------------------
    def start(self) -> None:
        """Watch liveliness, hold the gateway's token, reconcile stored episodes (call once the robot streams
        are subscribed)."""
        self.bus.watch_alive(keys.ALIVE_ANY, self._on_alive)
        self.bus.declare_alive()
        self.reconcile()

    def _on_alive(self, service: str, instance: str, alive: bool) -> None:
        with self._lock:
            group = self._alive.setdefault(service, set())
            (group.add if alive else group.discard)(instance)

    def alive_services(self) -> dict[str, list[str]]:
        with self._lock:
            return {s: sorted(i) for s, i in sorted(self._alive.items()) if i}

    def missing_services(self) -> list[str]:
        alive = self.alive_services()
        return [s for s in REQUIRED_SERVICES if not alive.get(s)]

    def reconcile(self) -> None:
        now = time.time()
        with self._lock:
            for k in self.store.keys("gw:ep:"):
                raw = self.store.get_json(k)
                if raw is None:
                    continue
                try:
                    rec = Record.load(raw)
                except Exception:
                    log.exception("unreadable episode record %s; skipped", k)
                    continue
                st = rec.status
                if st.state in TERMINAL:
                    continue
                self._active[st.episode_id] = rec
                self._snapshots[st.episode_id] = st.model_copy(deep=True)
                if st.state == "running":
                    rec.last_activity = now
                    if self.store.get(robot_key(st.robot)) is None:
                        self.store.set(robot_key(st.robot), st.episode_id.encode())
                    self._append(
                        st.episode_id,
                        gateway_event(
                            "gateway_restart",
                            st.episode_id,
                            last_seen=st.updated_at,
                            step=st.step,
                            note="the gateway restarted; bus messages published after last_seen while it "
                            "was down were not seen",
                        ),
                    )
                    if self._recover_end(rec):
                        continue
                    log.info("reconciled running episode %s on %s (step %d)", st.episode_id, st.robot, st.step)
            for robot in self.settings.robots:
                holder = self._running_on(robot)
                if holder is not None and (
                    holder not in self._active or self._active[holder].status.state != "running"
                ):
                    log.warning("robot %s was held by %s, which is not running; freed", robot, holder)
                    self.store.delete(robot_key(robot))
                    holder = None
                if holder is None:
                    self._start_next(robot)

    # ---- persistence helpers ----------------------------------------------------------------------------
    def _save(self, rec: Record) -> None:
        self.store.set_json(ep_key(rec.status.episode_id), rec.dump())
        self._snapshots[rec.status.episode_id] = rec.status.model_copy(deep=True)

    def _append(self, episode_id: str, event: dict[str, Any]) -> str:
        entry = self.store.append(ev_key(episode_id), json.dumps(event, separators=(",", ":")).encode())
        self.notify()
        return entry

    def _queue(self, robot: str) -> list[str]:
        return list(self.store.get_json(queue_key(robot)) or [])

    def _set_queue(self, robot: str, ids: list[str]) -> None:
        self.store.set_json(queue_key(robot), ids)

    def _running_on(self, robot: str) -> str | None:
        raw = self.store.get(robot_key(robot))
        return raw.decode() if raw else None

    def load(self, episode_id: str) -> Record | None:
        raw = self.store.get_json(ep_key(episode_id))
        return None if raw is None else Record.load(raw)

    # ---- queries ----------------------------------------------------------------------------------------
    def peek(self, episode_id: str) -> EpisodeStatus | None:
        """The saved status of a queued or running episode from memory (no store access), else None."""
        return self._snapshots.get(episode_id)

    def get(self, episode_id: str) -> EpisodeStatus:
        keys.check_id(episode_id, "episode id")
        rec = self.load(episode_id)
        if rec is None:
            raise NotFoundError(f"no episode {episode_id!r}")
        return rec.status

    def list(self, limit: int = 50, state: str | None = None) -> list[EpisodeStatus]:
        out = []
        for k in self.store.keys("gw:ep:"):
            raw = self.store.get_json(k)
            if raw is None:
                continue
            st = EpisodeStatus.model_validate(raw["status"])
            if state is None or st.state == state:
                out.append(st)
        out.sort(key=lambda s: s.created_at, reverse=True)
        return out[:limit]

    def events(self, episode_id: str, after: str = "0-0", count: int = 500) -> list[tuple[str, bytes]]:
        return self.store.read(ev_key(episode_id), after=after, count=count)

    def robots(self) -> dict[str, str | None]:
        return {r: self._running_on(r) for r in self.settings.robots}

    # ---- submit / start ---------------------------------------------------------------------------------
    def submit(self, req: QuestionRequest) -> Submitted:
        if req.robot is not None and req.robot not in self.settings.robots:
            raise InvalidError(f"unknown robot {req.robot!r}; known: {', '.join(self.settings.robots)}", field="robot")
        budget = step_budget(self.settings, req, self.scene_area)
        episode_id = new_id("ep")
        question = Question(
            text=req.question,
            choices=req.choices or [],
            scene=req.scene or "",
            start_pose=req.start_pose,
            max_steps=budget,
            answer=req.answer,
            **({"id": req.question_id} if req.question_id else {}),
        )
        with self._lock:
            candidates = [req.robot] if req.robot else list(self.settings.robots)
            free = [r for r in candidates if self._running_on(r) is None and not self._queue(r)]
            if free:
                robot, position = free[0], 0
            elif self.settings.busy_policy == "refuse":
                busy = ", ".join(f"{r} (running {self._running_on(r)})" for r in candidates)
                raise BusyError(f"robot busy: {busy}; EQA_BUSY_POLICY=refuse, submit again later")
            else:
                robot = min(candidates, key=lambda r: len(self._queue(r)))
                position = len(self._queue(robot)) + 1
            start = EpisodeStart(
                episode_id=episode_id,
                robot=robot,
                question=question,
                strategy=req.strategy,
                stop=req.stop_config(),
                max_steps=budget,
                seed=req.seed,
                record=req.record,
            )
            status = EpisodeStatus(
                episode_id=episode_id,
                robot=robot,
                state="queued",
                question=question,
                strategy=req.strategy,
                stop=start.stop,
                max_steps=budget,
            )
            rec = Record(status=status, start=start)
            self._active[episode_id] = rec
            self._save(rec)
            if position == 0:
                self._start(rec)
            else:
                self._set_queue(robot, [*self._queue(robot), episode_id])
                self._append(episode_id, gateway_event("queued", episode_id, robot=robot, position=position))
        return Submitted(
            episode_id=episode_id,
            robot=robot,
            state=rec.status.state,
            max_steps=budget,
            queue_position=position,
            links={
                "status": f"/v1/episodes/{episode_id}",
                "events": f"/v1/episodes/{episode_id}/events",
                "recording": f"/v1/episodes/{episode_id}/recording",
            },
        )

    def _start(self, rec: Record) -> None:
        now = time.time()
        st = rec.status
        st.state = "running"
        st.updated_at = now
        rec.last_activity = now
        rec.start = rec.start.model_copy(update={"sent_at": now})
        self._save(rec)
        self.store.set(robot_key(st.robot), st.episode_id.encode())
        self._append(st.episode_id, summarize(rec.start))
        try:
            self.bus.publish(keys.stream(st.robot, keys.EPISODE_START), rec.start)
        except Exception as exc:
            log.exception("could not publish EpisodeStart of %s", st.episode_id)
            self._finish(rec, "failed", f"could not publish EpisodeStart on the bus: {type(exc).__name__}: {exc}")
            return
        log.info("episode %s started on %s (max_steps %d)", st.episode_id, st.robot, st.max_steps)

    def _start_next(self, robot: str) -> None:
        queue = self._queue(robot)
        while queue:
            nxt = queue.pop(0)
            self._set_queue(robot, queue)
            rec = self._active.get(nxt)
            if rec is not None and rec.status.state == "queued":
                self._start(rec)
                return

    # ---- end / cancel -----------------------------------------------------------------------------------
    def _finish(self, rec: Record, state: str, reason: str, end: EpisodeEnd | None = None) -> None:
        st = rec.status
        now = time.time()
        st.state = state  # type: ignore[assignment]
        st.updated_at = now
        st.stop_reason = reason
        if end is not None:
            st.answer = end.answer
            st.answer_text = end.answer_text
            st.prediction_set = list(end.prediction_set)
            st.steps = end.steps
            st.normalized_steps = end.steps / max(st.max_steps, 1)
            st.correct = end.correct
        else:
            st.normalized_steps = st.steps / max(st.max_steps, 1)
        choices = st.question.choices
        if st.answer and st.answer_text is None and choices and "A" <= st.answer <= "Z":
            idx = ord(st.answer) - ord("A")
            st.answer_text = choices[idx] if idx < len(choices) else None
        if st.correct is None and st.answer and st.question.answer:
            st.correct = st.answer == st.question.answer
        rdir = recording_dir(self.settings, st.episode_id)
        if rdir.is_dir() and any(rdir.glob("*.rrd")):
            st.recording = f"/v1/episodes/{st.episode_id}/recording"
        self._save(rec)
        self._active.pop(st.episode_id, None)
        self._snapshots.pop(st.episode_id, None)  # the store holds the final record
        if self._running_on(st.robot) == st.episode_id:
            self.store.delete(robot_key(st.robot))
        if end is None:
            self._append(
                st.episode_id,
                gateway_event(
                    "episode_end",
                    st.episode_id,
                    robot=st.robot,
                    state=state,
                    reason=reason,
                    answer=st.answer,
                    prediction_set=st.prediction_set,
                    steps=st.steps,
                    max_steps=st.max_steps,
                    normalized_steps=round(st.normalized_steps, 4),
                    correct=st.correct,
                    source="gateway",
                ),
            )
        log.info("episode %s %s: %s", st.episode_id, state, reason)
        if self._running_on(st.robot) is None:  # a cancelled queued episode leaves its robot busy
            self._start_next(st.robot)

    def _abort(self, rec: Record, state: str, reason: str) -> None:
        """End an episode from the gateway side: tell the services to drop it, then record the end."""
        if rec.status.state == "running":
            try:
                self.bus.publish(
                    keys.stream(rec.status.robot, keys.EPISODE_CANCEL),
                    EpisodeCancel(episode_id=rec.status.episode_id, reason=reason),
                )
            except Exception:
                log.exception("could not publish EpisodeCancel for %s", rec.status.episode_id)
        self._finish(rec, state, reason)

    def cancel(self, episode_id: str, reason: str = "cancelled by user") -> EpisodeStatus:
        keys.check_id(episode_id, "episode id")
        with self._lock:
            rec = self._active.get(episode_id)
            if rec is None:
                stored = self.load(episode_id)
                if stored is None:
                    raise NotFoundError(f"no episode {episode_id!r}")
                raise ConflictError(f"episode {episode_id} already ended ({stored.status.state})")
            if rec.status.state == "queued":
                self._set_queue(rec.status.robot, [e for e in self._queue(rec.status.robot) if e != episode_id])
            self._abort(rec, "cancelled", reason)
            return rec.status

    # ---- bus messages -----------------------------------------------------------------------------------
    def handle(self, robot: str, msg: Message) -> None:
        """One message of a robot stream: store its summary, update the episode, end it on EpisodeEnd."""
        if isinstance(msg, EpisodeStart | EpisodeCancel):
            return  # the gateway records the ones it publishes itself
        episode_id = getattr(msg, "episode_id", None)
        if not isinstance(episode_id, str):
            return
        with self._lock:
            rec = self._active.get(episode_id)
            if rec is None or rec.status.state != "running":
                log.debug("message %s for episode %s that is not running here; ignored", msg.kind, episode_id)
                return
            st = rec.status
            if st.robot != robot:
                log.warning(
                    "episode %s runs on %s but a %s came from %s; ignored",
                    episode_id,
                    st.robot,
                    msg.kind,
                    robot,
                )
                return
            now = time.time()
            rec.last_activity = now
            st.updated_at = now
            if isinstance(msg, EpisodeEnd):
                state = msg.state if msg.state in TERMINAL else "stopped"
                # The final status is stored before the end event: a client that reads the event and then
                # asks for the status gets the final one.
                self._finish(rec, state, msg.reason, end=msg)
                self._append(episode_id, summarize(msg))
                return
            self._append(episode_id, summarize(msg))
            if isinstance(msg, ErrorReply):
                rec.last_error = f"{msg.source} at step {msg.step}: {msg.reason}"
                if msg.source.startswith("sim") and st.steps == 0:
                    self._abort(rec, "failed", f"sim refused the episode: {msg.reason}")
                    return
            step = getattr(msg, "step", None)
            if isinstance(step, int):
                st.step = max(st.step, step)
            if isinstance(msg, Frame):
                st.steps = max(st.steps, msg.step + 1)
            elif isinstance(msg, Decision):
                st.prediction_set = list(msg.prediction_set)
                st.answer = msg.answer or st.answer
            st.normalized_steps = st.steps / max(st.max_steps, 1)
            self._save(rec)

    def _recover_end(self, rec: Record) -> bool:
        """End ``rec`` from the stopper's stored ``EpisodeEnd`` if there is one (an end not seen on the bus)."""
        raw = self.store.get(episode_end_key(rec.status.episode_id))
        if raw is None:
            return False
        try:
            end = EpisodeEnd.model_validate_json(raw)
        except ValueError as exc:
            log.warning("stored end of %s is unreadable: %s", rec.status.episode_id, exc)
            return False
        event = summarize(end)
        event["recovered"] = "from the stopper's stored end: not seen on the bus by this gateway"
        self._finish(rec, end.state if end.state in TERMINAL else "stopped", end.reason, end=end)
        self._append(rec.status.episode_id, event)  # after the final status, as in handle()
        return True

    # ---- watchdog ---------------------------------------------------------------------------------------
    def check_timeouts(self, now: float | None = None) -> list[str]:
        """Fail running episodes with no message for ``episode_timeout_s``; return their ids."""
        now = time.time() if now is None else now
        timeout = self.settings.episode_timeout_s
        failed = []
        with self._lock:
            for rec in list(self._active.values()):
                st = rec.status
                if st.state != "running" or now - max(rec.last_activity, self.started_at) <= timeout:
                    continue
                if self._recover_end(rec):
                    continue
                missing = self.missing_services()
                restarted = st.updated_at < self.started_at
                reason = (
                    f"no message for {timeout:g} s (last step {st.step}); services not alive: "
                    f"{', '.join(missing) if missing else 'none, all alive'}"
                )
                if rec.last_error:
                    reason += f"; last error: {rec.last_error}"
                if restarted:
                    reason += "; the gateway restarted meanwhile, so the end may have been published while it was down"
                self._abort(rec, "failed", reason)
                failed.append(st.episode_id)
        return failed

"""The one pattern of every service that keeps per-episode state (sim, mapper, planner, stopper).

A subclass of :class:`EpisodeService` is its pure core plus a few hooks; the base does what each shell used to
write its own way:

* **EpisodeStart / EpisodeCancel / EpisodeEnd** are subscribed here. :meth:`EpisodeService.start_episode` builds
  the state of a new episode (a repeated start of a known episode is ignored);
  :meth:`EpisodeService.finish_episode` sees the state of an episode that ends, then the base drops it (memory,
  store, recorder, held messages).
* **Messages that overtake their EpisodeStart** (Zenoh delivers different keys on different threads, so step 0
  of one stream can arrive before the start on another) are held, bounded (episodes, messages per episode,
  bytes), for :attr:`hold_ttl_s`, and handled in step order right after the start. Expired or refused ones go
  to :meth:`EpisodeService.unknown_episode`; those of an episode that already ended are dropped.
* **The resent step** (the sim sends a step again when the instances downstream changed, and when no goal came
  back within ``EQA_STEP_RESEND_S``): a message of
  the step this service last answered (:meth:`answered_step`) is answered by publishing the step's outputs
  again (recorded by :meth:`publish_step`, kept in the store when :attr:`persist_answers`), or, when they are
  not at hand, by :meth:`answer_again`; an older step is a stale re-delivery and is ignored.
* **Per-episode state in the store** under :func:`eqa.store.episode_state_key` (``eqa:{service}:episode:{id}``),
  one msgpack envelope of :mod:`eqa.codec` holding the robot, the recording flag, the subclass's
  :meth:`dump_state` and the last step's answers. :meth:`save` writes it (call it before publishing what
  depends on it); a message of an episode not in memory restores it (:meth:`load_state`): a restarted service
  continues where the last one stopped.
* **State in several keys** (optional): :meth:`dump_state` may return :class:`StateParts`: parts written under
  :func:`eqa.store.episode_part_key` before the envelope, which lists the live ones, and parts no longer
  referenced deleted after it (a crash in between leaves the previous envelope valid, or a stray part that
  expires). :meth:`read_part` reads one in :meth:`load_state`; :meth:`drop` deletes them with the envelope.
  A service whose :meth:`dump_state` returns plain data stores exactly what it did before.
* **Recorder bookkeeping**: one :class:`eqa.recording.EpisodeRecorder` per episode in :attr:`recorders`, named
  after the service (``{service}-resume{k}`` after a restart: a file sink cannot be appended to).
* **Ownership** (sharding): :meth:`owns` is asked before any message is handled. With ``EQA_SHARD``
  (the default) the robots are shared among the live instances of the service by :class:`eqa.sharding.Shard`
  (rendezvous hashing over liveliness; one instance alone owns every robot). Before a step's handler runs the
  step is claimed in the store, so no step is computed by two instances while their views of the live set
  differ for a moment; a claim whose holder died is taken over, so none is skipped; an instance finishes the
  steps it claimed even after its robot moved; when the previous step was computed elsewhere the episode is
  reloaded from the store first. Robots that move away are forgotten in memory (their state stays stored);
  robots that move here are restored from the store with their next message.
* **Errors**: a handler that raises answers the episode at once with an ``ErrorReply`` on :attr:`error_stream`
  when the service has one (and is logged either way); the service goes on.

The constructor is ``(settings, bus=None, store=None)`` for every service.

**The sim** is on this base too, with what differs about it kept in its own shell (services/sim/service.py):
it *produces* the steps, so it has no step input to hold or answer again. Its one input, the planner's
``Goal``, is subscribed with a plain :meth:`eqa.service.Service.on` (a goal never comes before the frame it
answers; the sim claims the step it will *render*, ``goal.step + 1``, and ignores a goal of any other step
than the current one), it sends a frame again itself when no goal comes back (``EQA_STEP_RESEND_S``), and it
owns the robot's pose: a new EpisodeStart of a robot ends the robot's previous episode in the sim
(:meth:`drop`), and a restarted sim takes the stored episodes up at start (it scans
``episode_state_key("sim", "")``) instead of waiting for a message. Start/cancel/end, the stored state
(key and codec), recorders and error answers are this base's. Two small hooks exist for it:
:meth:`started` (publish step 0 once the state is registered and stored) and :attr:`answer_invalid_start`
(an EpisodeStart that does not validate is answered with an ErrorReply when its episode id can be read).
"""

from __future__ import annotations

import logging
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar, Generic, TypeVar

import numpy as np

from eqa import keys, metrics
from eqa.bus import Bus
from eqa.codec import CodecError, packb, unpackb
from eqa.messages import STREAM_TYPES, EpisodeCancel, EpisodeEnd, EpisodeStart, ErrorReply, Message, decode, encode
from eqa.recording import EpisodeRecorder
from eqa.service import Service
from eqa.settings import SettingsGroup
from eqa.sharding import Shard
from eqa.store import EPISODE_STATE_TTL_S, Store, episode_end_key, episode_part_key, episode_state_key

log = logging.getLogger(__name__)

S = TypeVar("S")
Pair = tuple[str, str]
ENVELOPE_VERSION = 1
LOST_GRACE_S = 60.0  # an instance still decodes a robot's step inputs this long after the robot moved away


def message_bytes(msg: Message) -> int:
    """Bytes of the arrays a message holds (what holding it costs)."""
    return sum(v.nbytes for v in msg.__dict__.values() if isinstance(v, np.ndarray))


@dataclass
class EpisodeMeta:
    """What the base keeps per episode beside the subclass's state."""

    robot: str
    record: bool
    answer_step: int = -1
    answers: dict[Pair, Message] = field(default_factory=dict)  # the outputs published for answer_step
    parts: set[str] = field(default_factory=set)  # live parts of a state kept in several keys (StateParts)


MAX_PART_NAME = 64


@dataclass
class StateParts:
    """A :meth:`EpisodeService.dump_state` result spread over several store keys: ``state`` goes into the
    envelope as a plain result would; ``write`` (part name -> bytes) is stored under
    :func:`eqa.store.episode_part_key` before the envelope; ``delete`` names parts no longer needed, removed
    after it. Names are short ``[A-Za-z0-9._-]`` strings."""

    state: Any
    write: dict[str, bytes] = field(default_factory=dict)
    delete: list[str] = field(default_factory=list)


def _check_part(name: Any) -> str:
    if not (isinstance(name, str) and 0 < len(name) <= MAX_PART_NAME
            and all(ch.isascii() and (ch.isalnum() or ch in "._-") for ch in name)):
        raise ValueError(f"bad state part name {name!r}")
    return name


@dataclass
class _Held:
    at: float
    robot: str
    msg: Any
    nbytes: int
    route: _Route


@dataclass
class _Route:
    pair: Pair
    handler: Callable[[str, Any, Any], None]
    resend: bool
    hold: bool


class EpisodeService(Service, Generic[S]):
    """Base of the services with per-episode state. Subclasses set ``name``, implement the hooks and declare
    their step inputs with :meth:`on_step` in :meth:`setup_episodes`."""

    hold_ttl_s: ClassVar[float] = 30.0
    hold_max_episodes: ClassVar[int] = 64
    hold_max_per_episode: ClassVar[int] = 64
    hold_max_bytes: ClassVar[int] = 64 * 1024 * 1024
    persist_answers: ClassVar[bool] = True
    state_ttl_s: ClassVar[float] = EPISODE_STATE_TTL_S
    error_stream: ClassVar[Pair | None] = None
    answer_invalid_start: ClassVar[bool] = False

    def __init__(self, settings: SettingsGroup, bus: Bus | None = None, store: Store | None = None) -> None:
        super().__init__(settings, bus, store)
        self.episodes: dict[str, S] = {}
        self.meta: dict[str, EpisodeMeta] = {}
        self.recorders: dict[str, EpisodeRecorder] = {}
        self._held: dict[str, list[_Held]] = {}
        self._routes: dict[Pair, _Route] = {}
        self.shard: Shard | None = None
        self._lost_at: dict[str, float] = {}  # robots that moved away recently (replaced whole, read on Zenoh threads)
        # episodes seen ending (bounded): a step message of an ended episode that comes late, or an instance that
        # gains the robot afterwards, must not start or restore it again (it would claim a step and linger)
        self._ended: OrderedDict[str, None] = OrderedDict()

    # ---- hooks ------------------------------------------------------------------------------------------
    def owns(self, robot: str) -> bool:
        """Whether this instance handles ``robot``: its share of the robots under :class:`eqa.sharding.Shard`
        (every robot when sharding is off or before :meth:`setup`)."""
        return self.shard is None or self.shard.owns(robot)

    def setup_episodes(self) -> None:
        """Declare the step inputs (:meth:`on_step`) and anything else to set up once the bus is open."""

    def start_episode(self, robot: str, start: EpisodeStart) -> S | None:
        """The state of a new episode, or None when it cannot start (the subclass has answered it)."""
        raise NotImplementedError

    def started(self, robot: str, episode_id: str, state: S) -> None:
        """Right after a new episode's state is registered and stored, before its held messages are handled
        (the sim publishes step 0 here). Raising answers the episode with an error and drops it."""

    def finish_episode(self, robot: str, msg: EpisodeCancel | EpisodeEnd, state: S) -> None:
        """The episode ends (cancel, or an end published by anyone); the base drops its state afterwards."""

    def dump_state(self, state: S, **extra: Any) -> Any:
        """The state as data :func:`eqa.codec.packb` takes (dicts, lists, numbers, strings, bytes, arrays)."""
        raise NotImplementedError

    def load_state(self, episode_id: str, data: Any) -> S:
        """The state from :meth:`dump_state`'s data (a restarted service). Raise ``ValueError`` when unusable."""
        raise NotImplementedError

    def answered_step(self, episode_id: str, state: S) -> int:
        """The last step this service answered (-1: none)."""
        return self.meta[episode_id].answer_step

    def answer_again(self, robot: str, state: S, msg: Any) -> None:
        """Answer a resent step whose outputs are not at hand (e.g. after a restart without
        :attr:`persist_answers`)."""
        log.info("%s: episode %s step %d sent again; nothing to re-publish", self.name, msg.episode_id, msg.step)

    def unknown_episode(self, robot: str, msg: Any, why: str) -> None:
        """A message of an episode with no EpisodeStart and no stored state, not held (any longer)."""
        log.warning("%s: %s of episode %s (step %s) dropped: %s", self.name, msg.kind, msg.episode_id,
                    getattr(msg, "step", None), why)

    # ---- wiring -----------------------------------------------------------------------------------------
    def setup(self) -> None:
        # Membership first: the first messages are already judged against the instances present.
        self.shard = Shard(self.bus, lambda: self.store, self.name, self.bus.instance,
                           on_moved=lambda gained, lost: self.submit(self._robots_moved, gained, lost),
                           enabled=self.settings.shard).start()
        self.on(keys.EPISODE_START, self._on_start,
                on_invalid=self._on_invalid_start if self.answer_invalid_start else None)
        self.on(keys.EPISODE_CANCEL, self._on_finish)
        self.on(keys.EPISODE_END, self._on_finish)
        self.setup_episodes()
        self.every(min(1.0, self.hold_ttl_s / 4), self._expire_held)

    def teardown(self) -> None:
        for recorder in self.recorders.values():
            recorder.close()
        self.recorders.clear()

    def on_step(self, pair: Pair, handler: Callable[[str, S, Any], None], resend: bool = True,
                hold: bool = True) -> None:
        """Run ``handler(robot, state, msg)`` for every message of stream ``pair`` (any robot) of an episode
        this service holds. ``resend``: a message of an already answered step is answered by the base (see the
        module docstring) instead of reaching the handler. ``hold``: a message of an unknown episode waits for
        its start; otherwise it is dropped quietly."""
        route = _Route(pair, handler, resend, hold)
        self._routes[pair] = route
        self.on(pair, lambda robot, msg: self._dispatch(robot, msg, route), prefilter=True)

    def receive(self, pair: Pair, robot: str, msg: Any) -> None:
        """Handle ``msg`` as if it came on stream ``pair`` of ``robot`` (call it on the worker: tests use
        ``svc.submit(svc.receive, pair, robot, msg)``)."""
        if pair == keys.EPISODE_START:
            self._on_start(robot, msg)
        elif pair in (keys.EPISODE_CANCEL, keys.EPISODE_END):
            self._on_finish(robot, msg)
        else:
            self._dispatch(robot, msg, self._routes[pair])

    # ---- state ------------------------------------------------------------------------------------------
    def episode(self, episode_id: str) -> S | None:
        """The episode's state: in memory, else restored from the store, else None."""
        state = self.episodes.get(episode_id)
        return state if state is not None else self._restore(episode_id)

    def save(self, episode_id: str, **extra: Any) -> None:
        """Write the episode's state (and its last answers) to the store; ``extra`` goes to :meth:`dump_state`."""
        meta = self.meta[episode_id]
        state = self.dump_state(self.episodes[episode_id], **extra)
        parts = state if isinstance(state, StateParts) else None
        body: dict[str, Any] = {
            "version": ENVELOPE_VERSION,
            "robot": meta.robot,
            "record": meta.record,
            "state": parts.state if parts is not None else state,
        }
        if self.persist_answers and meta.answers:
            body["answers"] = {"step": meta.answer_step,
                               "messages": [[*pair, encode(m)] for pair, m in meta.answers.items()]}
        if parts is None:
            self.store.set(episode_state_key(self.name, episode_id), packb(body), ttl_s=self.state_ttl_s)
            return
        # the parts before the envelope that names them, the parts it no longer names after it: one store call
        # (one round trip on Redis, in this order)
        items = [(episode_part_key(self.name, episode_id, _check_part(name)), data)
                 for name, data in parts.write.items()]
        live = (meta.parts | set(parts.write)) - set(parts.delete)
        body["parts"] = sorted(live)
        items.append((episode_state_key(self.name, episode_id), packb(body)))
        gone = [episode_part_key(self.name, episode_id, _check_part(n)) for n in parts.delete
                if n not in parts.write]
        self.store.set_many(items, ttl_s=self.state_ttl_s, then_delete=gone)
        meta.parts = live

    def read_part(self, episode_id: str, name: str) -> bytes:
        """A part of the episode's stored state (:class:`StateParts`), for :meth:`load_state`; ``ValueError``
        when it is missing (the stored state is then unusable)."""
        data = self.store.get(episode_part_key(self.name, episode_id, _check_part(name)))
        if data is None:
            raise ValueError(f"part {name!r} of the stored state of episode {episode_id} is missing")
        return data

    def _delete_parts(self, episode_id: str, parts: set[str] | list[str]) -> None:
        keys_ = [episode_part_key(self.name, episode_id, n) for n in parts]
        if keys_:
            self.store.delete_many(keys_)

    def drop(self, episode_id: str, upto_step: int = 0) -> None:
        """Forget an episode: memory, stored state, recorder, held messages, step claims (those of steps up to
        the last one answered here, or ``upto_step`` when larger: an episode restored from the store knows its
        last answered step only where answers are persisted, and the claims of the steps computed before a
        restart or by another instance would otherwise be left to expire)."""
        # noted as ended at once: this instance's own EpisodeEnd comes back over the bus only later, and a step
        # input sent again meanwhile (a re-driven frame's scores) must not start the episode anew from a
        # remembered EpisodeStart and compute its last step a second time (its claims are deleted below)
        self._note_ended(episode_id)
        self.episodes.pop(episode_id, None)
        meta = self.meta.pop(episode_id, None)
        self._forget_claims(episode_id, max(meta.answer_step + 1, upto_step) if meta is not None else upto_step)
        self._held.pop(episode_id, None)
        self.store.delete(episode_state_key(self.name, episode_id))
        if meta is not None and meta.parts:
            self._delete_parts(episode_id, meta.parts)
        recorder = self.recorders.pop(episode_id, None)
        if recorder is not None:
            recorder.close()

    def _forget_claims(self, episode_id: str, upto_step: int) -> None:
        """Delete the step claims of an ended episode (they would expire; not wait for it)."""
        if self.shard is not None and self.shard.claims is not None:
            self.shard.claims.forget(episode_id, upto_step)

    def robot_of(self, episode_id: str) -> str:
        return self.meta[episode_id].robot

    def publish_step(self, episode_id: str, pair: Pair, msg: Message, step: int, save: bool = False,
                     **extra: Any) -> None:
        """Publish an output of ``step`` and keep it as the step's answer (a resent step gets it again);
        ``save``: store the state first (whatever a consumer has seen survives a crash of this process)."""
        meta = self.meta[episode_id]
        if step != meta.answer_step:
            meta.answer_step, meta.answers = step, {}
        meta.answers[pair] = msg
        if save:
            self.save(episode_id, **extra)
        self.publish(meta.robot, pair, msg)

    def error(self, robot: str, episode_id: str | None, step: int | None, reason: str) -> None:
        """Answer an episode with an ``ErrorReply`` on :attr:`error_stream` (logged when there is none)."""
        log.warning("%s: episode %s step %s: %s", self.name, episode_id, step, reason)
        if self.error_stream is not None:
            self.publish(robot, self.error_stream,
                         ErrorReply(source=self.name, episode_id=episode_id, step=step, reason=reason[:1000]))

    # ---- internals --------------------------------------------------------------------------------------
    def _register(self, episode_id: str, state: S, meta: EpisodeMeta, recorder_name: str) -> None:
        self.episodes[episode_id] = state
        self.meta[episode_id] = meta
        old = self.recorders.pop(episode_id, None)
        if old is not None:
            old.close()
        self.recorders[episode_id] = EpisodeRecorder(self.settings, episode_id, recorder_name, enabled=meta.record)

    def _restore(self, episode_id: str) -> S | None:
        raw = self.store.get(episode_state_key(self.name, episode_id))
        if raw is None:
            return None
        parts: set[str] = set()
        try:
            body = unpackb(raw)
            if not isinstance(body, dict) or body.get("version") != ENVELOPE_VERSION:
                raise ValueError(f"not a {self.name} state of version {ENVELOPE_VERSION}")
            listed = body.get("parts", [])
            if not isinstance(listed, list) or len(listed) > 10_000:
                raise ValueError("bad list of state parts")
            parts = {_check_part(n) for n in listed}
            meta = EpisodeMeta(robot=str(body["robot"]), record=bool(body["record"]), parts=parts)
            answers = body.get("answers")
            if answers:
                meta.answer_step = int(answers["step"])
                for service, stream, payload in answers["messages"]:
                    pair = (str(service), str(stream))
                    meta.answers[pair] = decode(payload, STREAM_TYPES[pair])
            state = self.load_state(episode_id, body["state"])
        except (CodecError, KeyError, TypeError, ValueError) as exc:
            log.error("%s: stored state of episode %s unusable (%s); dropped", self.name, episode_id, exc)
            self.store.delete(episode_state_key(self.name, episode_id))
            self._delete_parts(episode_id, parts)
            return None
        self.episodes[episode_id] = state  # answered_step may need it
        self.meta[episode_id] = meta
        resumed = self.answered_step(episode_id, state) + 1
        self._register(episode_id, state, meta, f"{self.name}-resume{resumed}")
        log.info("%s: episode %s restored from the store (next step %d)", self.name, episode_id, resumed)
        metrics.inc(metrics.EPISODES_RESTORED, self.name)
        return state

    ENDED_MAX: ClassVar[int] = 4096

    def _note_ended(self, episode_id: str) -> None:
        self._ended[episode_id] = None
        self._ended.move_to_end(episode_id)
        while len(self._ended) > self.ENDED_MAX:
            self._ended.popitem(last=False)

    def _on_start(self, robot: str, start: EpisodeStart) -> None:
        eid = start.episode_id
        if eid in self._ended:
            log.info("%s: episode %s has ended; its EpisodeStart ignored", self.name, eid)
            return
        if not self.owns(robot):
            if self.shard is not None:  # the robot may move here before this episode's state is stored
                self.shard.remember_start(eid, start)
            return
        if self.episode(eid) is not None:
            log.info("%s: episode %s already started; repeated EpisodeStart ignored", self.name, eid)
            return
        try:
            state = self.start_episode(robot, start)
        except Exception as exc:
            log.exception("%s: episode %s could not start", self.name, eid)
            self.error(robot, eid, 0, f"episode could not start: {type(exc).__name__}: {exc}")
            return
        if state is None:
            self._held.pop(eid, None)
            return
        self._register(eid, state, EpisodeMeta(robot=robot, record=bool(start.record)), self.name)
        try:
            self.save(eid)
            self.started(robot, eid, state)
        except Exception as exc:
            log.exception("%s: episode %s could not start", self.name, eid)
            self.drop(eid)
            self.error(robot, eid, 0, f"episode could not start: {type(exc).__name__}: {exc}")
            return
        held = sorted(self._held.pop(eid, []), key=lambda h: getattr(h.msg, "step", 0))
        for h in held:
            log.info("%s: episode %s: %s of step %s that came before the start handled", self.name, eid,
                     h.msg.kind, getattr(h.msg, "step", None))
            self._dispatch(h.robot, h.msg, h.route)

    def _on_invalid_start(self, robot: str, payload: bytes, reason: str) -> None:
        """An EpisodeStart that does not validate (a pose out of range, a bad scene id): answer its episode at
        once when its id can be read, so the gateway fails it and frees the robot (no wait for the watchdog)."""
        try:
            raw = unpackb(payload, max_decoded=0)  # an EpisodeStart carries no arrays
            episode_id = keys.check_id(raw.get("episode_id"), "episode id")
        except Exception:
            return
        self.error(robot, episode_id, 0, f"episode start refused: {reason}")

    def _on_finish(self, robot: str, msg: EpisodeCancel | EpisodeEnd) -> None:
        self._note_ended(msg.episode_id)
        upto = getattr(msg, "steps", 0) + 1  # an EpisodeEnd counts its steps
        if not self.owns(robot):
            # A copy left from when the robot was ours; its owner drops the rest. The claims go here too: this
            # instance may have claimed a step after the robot moved away, and the owner may stop before it
            # sees the end; every instance deletes them after its own last claim, so none is left behind.
            meta = self.meta.get(msg.episode_id)
            self._forget(msg.episode_id)
            self._forget_claims(msg.episode_id, max(upto, meta.answer_step + 1 if meta is not None else 0))
            return
        state = self.episode(msg.episode_id)
        try:
            if state is not None:
                self.finish_episode(robot, msg, state)
        finally:
            self.drop(msg.episode_id, upto_step=upto)

    def _dispatch(self, robot: str, msg: Any, route: _Route) -> None:
        eid = msg.episode_id
        if eid is None:
            return
        if eid in self._ended:
            return  # a late message of an ended episode (its state and claims are gone; do not bring them back)
        step = getattr(msg, "step", None)
        mine = self.owns(robot)
        if not mine and not self._claimed_here(eid, step):
            return
        state = self.episode(eid)
        if state is None and mine and self.shard is not None:
            start = self.shard.start_of(eid)  # its start came while another instance owned the robot
            if isinstance(start, EpisodeStart) and self._ended_elsewhere(robot, eid):
                return  # ended by the instance that owned it before: nothing to start
            if isinstance(start, EpisodeStart):
                self._on_start(robot, start)
                state = self.episode(eid)
        if state is None:
            if route.hold:
                self._hold(robot, msg, route)
            return
        if self.shard is not None and step is not None:
            claim = self.shard.claim(eid, step)
            if not claim.won:
                log.info("%s: episode %s step %d is %s's; not computed here", self.name, eid, step, claim.holder)
                return
            if claim.unanchored and self._ended_elsewhere(robot, eid):
                # Another instance ended the episode (its end stored, then its claims deleted) while this one,
                # owning the robot in its own view of the membership, still held the state in memory and had
                # not yet seen the end: the claim could be won again, and the step would be computed twice.
                log.info("%s: episode %s ended elsewhere before its step %d came here; not computed", self.name,
                         eid, step)
                self._forget_claims(eid, step)
                return
            if claim.stale:  # the previous step was computed by another instance: take its stored state
                self._forget(eid)
                state = self.episode(eid)
                if state is None:
                    return
        if route.resend and step is not None:
            answered = self.answered_step(eid, state)
            if step < answered:
                log.info("%s: episode %s: %s of step %d already answered (last %d); ignored", self.name, eid,
                         msg.kind, step, answered)
                return
            if step == answered:
                self._answer_again(robot, eid, state, msg)
                return
        try:
            with metrics.timer(metrics.STEP_SECONDS, self.name, msg.kind):
                route.handler(robot, state, msg)
        except Exception as exc:
            log.exception("%s: episode %s: %s handler failed", self.name, eid, msg.kind)
            self.error(robot, eid, step, f"{self.name} failed on {msg.kind}: {type(exc).__name__}: {exc}")

    def _claimed_here(self, episode_id: str, step: int | None) -> bool:
        """Whether this instance claimed ``step`` (it finishes it even when the robot has moved meanwhile)."""
        if self.shard is None or self.shard.claims is None or step is None:
            return False
        return self.shard.claims.holder(episode_id, step) == self.bus.instance

    def _ended_elsewhere(self, robot: str, episode_id: str) -> bool:
        """Whether the episode's end is stored (another instance ended it); if so it is noted as ended and
        dropped from memory here, and :meth:`ended_before` runs."""
        if self.store.get(episode_end_key(episode_id)) is None:
            return False
        self._note_ended(episode_id)
        self._forget(episode_id)
        self.ended_before(robot, episode_id)
        return True

    def _forget(self, episode_id: str) -> None:
        """Drop an episode from memory only (its stored state is the next owner's)."""
        self.episodes.pop(episode_id, None)
        self.meta.pop(episode_id, None)
        self._held.pop(episode_id, None)
        recorder = self.recorders.pop(episode_id, None)
        if recorder is not None:
            recorder.close()

    def wants(self, robot: str) -> bool:
        """Decode the step inputs of robots this instance owns, or owned within ``LOST_GRACE_S`` (it finishes the
        steps it claimed); the rest are dropped undecoded."""
        if self.owns(robot):
            return True
        lost = self._lost_at.get(robot)
        return lost is not None and time.monotonic() - lost < LOST_GRACE_S

    def _robots_moved(self, gained: set[str], lost: set[str]) -> None:
        now = time.monotonic()
        self._lost_at = {**{r: t for r, t in self._lost_at.items() if now - t < LOST_GRACE_S},
                         **dict.fromkeys(lost, now)}
        for eid, meta in list(self.meta.items()):
            if meta.robot in lost:
                log.info("%s: robot %s moved to another instance; episode %s left to it", self.name, meta.robot,
                         eid)
                self._forget(eid)

    def ended_before(self, robot: str, episode_id: str) -> None:
        """A step message came for an episode whose end is stored but whose state is gone here. The instance
        that ended it stored the end before publishing it and may have died in between, so the service that
        ends episodes publishes the stored end again (the stopper); the others do nothing."""

    def _answer_again(self, robot: str, episode_id: str, state: S, msg: Any) -> None:
        meta = self.meta[episode_id]
        metrics.inc(metrics.RESENDS, self.name, "answer_again")
        if meta.answer_step == msg.step and meta.answers:
            log.info("%s: episode %s step %d sent again; its %s re-published", self.name, episode_id, msg.step,
                     ", ".join(m.kind for m in meta.answers.values()))
            for pair, out in meta.answers.items():
                self.publish(meta.robot, pair, out)
            return
        self.answer_again(robot, state, msg)

    def _hold(self, robot: str, msg: Any, route: _Route) -> None:
        eid = msg.episode_id
        if self._ended_elsewhere(robot, eid):
            log.info("%s: %s of ended episode %s ignored", self.name, msg.kind, eid)
            return
        items = self._held.get(eid)
        nbytes = message_bytes(msg)
        total = sum(h.nbytes for hs in self._held.values() for h in hs)
        if items is None and len(self._held) >= self.hold_max_episodes:
            why = f"no EpisodeStart seen and {self.hold_max_episodes} episodes already wait for theirs"
        elif items is not None and len(items) >= self.hold_max_per_episode:
            why = f"no EpisodeStart seen and {self.hold_max_per_episode} of its messages already wait"
        elif total + nbytes > self.hold_max_bytes:
            why = f"no EpisodeStart seen and the held messages would exceed {self.hold_max_bytes} bytes"
        else:
            self._held.setdefault(eid, []).append(_Held(time.monotonic(), robot, msg, nbytes, route))
            log.info("%s: %s of episode %s step %s held until its EpisodeStart", self.name, msg.kind, eid,
                     getattr(msg, "step", None))
            return
        metrics.inc(metrics.BUS_DROPPED, self.name, "unknown_episode")
        self.unknown_episode(robot, msg, why)

    def _expire_held(self) -> None:
        now = time.monotonic()
        for eid in [e for e, hs in self._held.items() if now - hs[0].at > self.hold_ttl_s]:
            for h in self._held.pop(eid):
                metrics.inc(metrics.BUS_DROPPED, self.name, "unknown_episode")
                self.unknown_episode(h.robot, h.msg, f"no EpisodeStart within {self.hold_ttl_s:.0f} s and no "
                                                      "stored state")


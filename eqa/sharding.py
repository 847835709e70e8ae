"""Robots shared among the live instances of a stateful service (sim, mapper, planner, stopper).

* :func:`owner` is rendezvous (highest-random-weight) hashing (Thaler & Ravishankar 1998): each
  ``(instance, robot)`` pair gets a pseudo-random weight from a fixed hash (BLAKE2b, not Python's salted
  ``hash``), and a robot belongs to the live instance of highest weight. Every instance computes the same
  answer from the same set of live instances, with no coordination; when an instance appears or vanishes only
  the robots it gains or held move (about ``1/n`` of them), the rest stay where they are.
* :class:`Membership` keeps the set of live instances of one service from Zenoh liveliness tokens
  (``eqa/v1/alive/{service}/{instance}/{session}``, which Zenoh withdraws when a process dies or its link is
  cut) and
  answers ``owns(robot)``; a callback reports the robots that moved.
* :class:`StepClaims` makes "exactly one instance computes each step" hold also while views of the live set
  differ for a moment (an instance joined and not everybody has seen it yet): before computing step ``k`` of an
  episode an instance claims it in the store (``set_if_absent``); a claim whose holder is no longer alive is
  superseded by a next attempt, so a step whose owner died half-way is computed once more by the new owner and
  never lost. :meth:`StepClaims.claim` also says whether the previous step was computed elsewhere: then the
  in-memory state is stale and the service reloads it from the store (the restart path).
"""

from __future__ import annotations

import hashlib
import logging
import threading
from collections.abc import Callable, Iterable
from dataclasses import dataclass

from eqa import keys, metrics
from eqa.store import Store

log = logging.getLogger(__name__)

CLAIM_PREFIX = "eqa:claim:"
CLAIM_TTL_S = 900.0  # a step claim matters while its episode runs: resends, the next step's staleness check
MAX_ATTEMPTS = 64
FORGET_ATTEMPTS = 4  # claims deleted per step when an episode ends (later takeovers, rarer still, expire)


def weight(instance: str, robot: str) -> int:
    """The rendezvous weight of one (instance, robot) pair: 64 bits of BLAKE2b, the same in every process."""
    digest = hashlib.blake2b(f"{instance}\x00{robot}".encode(), digest_size=8).digest()
    return int.from_bytes(digest, "big")


def owner(robot: str, instances: Iterable[str]) -> str | None:
    """The instance that handles ``robot`` among ``instances`` (None when there is none). Pure."""
    best: tuple[int, str] | None = None
    for inst in instances:
        cand = (weight(inst, robot), inst)
        if best is None or cand > best:
            best = cand
    return None if best is None else best[1]


def assignment(robots: Iterable[str], instances: Iterable[str]) -> dict[str, str | None]:
    """``robot -> instance`` for every robot. Pure."""
    live = sorted(set(instances))
    return {r: owner(r, live) for r in robots}


def moved(robots: Iterable[str], me: str, before: Iterable[str], after: Iterable[str]) -> tuple[set[str], set[str]]:
    """``(gained, lost)``: robots ``me`` handles after but not before, and before but not after. Pure."""
    b, a = sorted(set(before)), sorted(set(after))
    gained, lost = set(), set()
    for r in robots:
        was, now = owner(r, b) == me, owner(r, a) == me
        if now and not was:
            gained.add(r)
        elif was and not now:
            lost.add(r)
    return gained, lost


class Membership:
    """The live instances of one service, from liveliness, always including this one.

    ``on_change(before, after)`` runs on a Zenoh thread after each change; services hand it to their worker.
    """

    def __init__(
        self,
        bus: object,
        service: str,
        instance: str,
        on_change: Callable[[frozenset[str], frozenset[str]], None] | None = None,
    ) -> None:
        self.bus = bus
        self.service = keys.check_id(service, "service")
        self.me = keys.check_id(instance, "instance")
        self._live: frozenset[str] = frozenset({self.me})
        self._lock = threading.Lock()
        self._on_change = on_change

    def start(self, sync_timeout: float = 1.0) -> Membership:
        """Watch the tokens; also ask for the present ones at once, so that the first ``owns`` answers of a
        starting instance already count the instances that were there before it."""
        self.bus.watch_alive(keys.alive_service(self.service), self._on_alive)  # type: ignore[attr-defined]
        if sync_timeout > 0:
            for service, instance in self.bus.alive(keys.alive_service(self.service), timeout=sync_timeout):  # type: ignore[attr-defined]
                self._on_alive(service, instance, True)
        return self

    def _on_alive(self, service: str, instance: str, up: bool) -> None:
        if service != self.service or instance == self.me:
            return
        with self._lock:
            before = self._live
            after = before | {instance} if up else before - {instance}
            if after == before:
                return
            self._live = after
        log.info("%s instances: %s (%s %s)", self.service, ", ".join(sorted(after)), instance,
                 "joined" if up else "left")
        if self._on_change is not None:
            self._on_change(before, after)

    @property
    def live(self) -> frozenset[str]:
        with self._lock:
            return self._live

    def is_alive(self, instance: str) -> bool:
        return instance in self.live

    def owner(self, robot: str) -> str | None:
        return owner(robot, self.live)

    def owns(self, robot: str) -> bool:
        return self.owner(robot) == self.me


@dataclass(frozen=True)
class Claim:
    won: bool
    holder: str | None  # who computes the step (this instance when won)
    stale: bool  # the previous step was computed by another instance: reload the episode from the store
    # won with no claim of the previous step in the store (step 0, expired claims, or the claims of an episode
    # that ended meanwhile, which whoever ended it deleted after storing its end): the service checks the end
    unanchored: bool = False


class StepClaims:
    """Exactly-once computation of each step of an episode among the instances of one service."""

    def __init__(self, store: Store, service: str, me: str, is_alive: Callable[[str], bool],
                 ttl_s: float = CLAIM_TTL_S) -> None:
        self.store = store
        self.service = keys.check_id(service, "service")
        self.me = me
        self.is_alive = is_alive
        self.ttl_s = ttl_s

    def _key(self, episode_id: str, step: int) -> str:
        return f"{CLAIM_PREFIX}{self.service}:{episode_id}:{step}"

    def holder(self, episode_id: str, step: int) -> str | None:
        """The instance that last claimed ``step`` (None when nobody did, or the claim expired)."""
        raw = self.store.get(self._key(episode_id, step) + ":holder")
        return raw.decode() if raw is not None else None

    def claim(self, episode_id: str, step: int) -> Claim:
        """Attempts ``0, 1, ...`` of a step are claimed in turn; the latest one present decides: held by this
        instance (a resent step, or a restarted process of the same instance name whose predecessor claimed
        it) it is won again, held by a live instance it is lost, held by a dead one the next attempt is
        claimed. An earlier attempt never decides while a later one exists: an instance restarted under its
        name must not take back a step another instance took over while it was down."""
        base = self._key(episode_id, step)
        attempt = 0
        while attempt < MAX_ATTEMPTS:
            key = f"{base}:{attempt}"
            if self.store.set_if_absent(key, self.me.encode(), ttl_s=self.ttl_s):
                self.store.set(base + ":holder", self.me.encode(), ttl_s=self.ttl_s)
                metrics.inc(metrics.STEP_CLAIMS, self.service, "won")
                prev = self.holder(episode_id, step - 1) if step > 0 else None
                return Claim(True, self.me, prev is not None and prev != self.me, unanchored=prev is None)
            raw = self.store.get(key)
            if raw is None:  # expired between the two calls: try the same attempt again
                continue
            if self.store.get(f"{base}:{attempt + 1}") is not None:  # superseded by a takeover
                attempt += 1
                continue
            holder = raw.decode()
            if holder == self.me:  # the same step again (resent): the service answers it from its state
                metrics.inc(metrics.STEP_CLAIMS, self.service, "again")
                return Claim(True, self.me, False)
            if self.is_alive(holder):
                metrics.inc(metrics.STEP_CLAIMS, self.service, "lost")
                return Claim(False, holder, False)
            metrics.inc(metrics.STEP_TAKEOVERS, self.service)
            log.info("step %d of %s: %s claimed it and is gone; claiming it again", step, episode_id, holder)
            attempt += 1
        raise RuntimeError(f"step {step} of {episode_id}: {MAX_ATTEMPTS} claims by dead instances")

    def forget(self, episode_id: str, upto_step: int) -> None:
        """Delete the claims of an ended episode (they expire anyway)."""
        names = []
        for step in range(upto_step + 1):
            base = self._key(episode_id, step)
            names += [base + ":holder"] + [f"{base}:{a}" for a in range(FORGET_ATTEMPTS)]
        self.store.delete_many(names)


class Shard:
    """Everything a sharded instance of a stateful service needs, in one object (the episode-service base holds
    one): :meth:`owns`, :meth:`claim`, the robots that moved when the live set changed (``on_moved(gained,
    lost)``, called on a Zenoh thread: hand it to the worker), and the EpisodeStarts of robots owned by another
    instance (bounded), so that an instance that gains a robot mid-episode can still start an episode whose
    start it saw but did not own, before the episode's state was ever stored."""

    MAX_STARTS = 512
    MAX_ROBOTS = 100_000

    def __init__(self, bus: object, store: Callable[[], Store], service: str, instance: str,
                 on_moved: Callable[[set[str], set[str]], None] | None = None, enabled: bool = True) -> None:
        self.enabled = enabled
        self._store = store
        self._on_moved = on_moved
        self._robots: set[str] = set()
        self._starts: dict[str, object] = {}
        self._lock = threading.Lock()
        self.membership = Membership(bus, service, instance, on_change=self._changed)
        self.claims: StepClaims | None = None
        self.service, self.me = service, instance

    def start(self) -> Shard:
        if self.enabled:
            self.membership.start()
            self.claims = StepClaims(self._store(), self.service, self.me, self.membership.is_alive)
        return self

    def owns(self, robot: str) -> bool:
        if not self.enabled:
            return True
        with self._lock:
            if len(self._robots) < self.MAX_ROBOTS:
                self._robots.add(robot)
        return self.membership.owns(robot)

    def claim(self, episode_id: str, step: int) -> Claim:
        if self.claims is None:
            return Claim(True, self.me, False)
        return self.claims.claim(episode_id, step)

    def remember_start(self, episode_id: str, start: object) -> None:
        with self._lock:
            self._starts[episode_id] = start
            while len(self._starts) > self.MAX_STARTS:
                self._starts.pop(next(iter(self._starts)))

    def start_of(self, episode_id: str) -> object | None:
        with self._lock:
            return self._starts.get(episode_id)

    def latest_start(self, robot: str) -> object | None:
        """The last remembered EpisodeStart of ``robot`` (any object with a ``robot`` attribute)."""
        with self._lock:
            for start in reversed(list(self._starts.values())):
                if getattr(start, "robot", None) == robot:
                    return start
        return None

    def _changed(self, before: frozenset[str], after: frozenset[str]) -> None:
        with self._lock:
            robots = set(self._robots)
        gained, lost = moved(robots, self.me, before, after)
        if (gained or lost) and self._on_moved is not None:
            log.info("%s %s: robots gained %s, lost %s", self.service, self.me, sorted(gained), sorted(lost))
            self._on_moved(gained, lost)


def reassigned(robots: Iterable[str], before: Iterable[str], after: Iterable[str]) -> set[str]:
    """Robots whose owner differs between the live sets ``before`` and ``after`` (an instance that left held
    them, or one that joined takes them; with no instance at all the owner is None). Pure."""
    b, a = sorted(set(before)), sorted(set(after))
    return {r for r in robots if owner(r, b) != owner(r, a)}


REDRIVE_AFTER_S = (0.3, 2.0)


class Redrive:
    """When to send a robot's current step again because the instances of a service downstream changed.

    A step in flight when its consumer's instance dies is lost with it, and one sent while a newcomer takes a
    robot over may reach neither the old owner (it no longer takes the robot) nor the new one (not subscribed
    yet): without help it waits for the step-resend timer. The producer (the sim) feeds :meth:`changed` with
    the liveliness of the services downstream; each robot whose owner in one of them changed is due
    ``after_s`` later (the first lets the new owner's subscriptions and view of the live set settle, the next
    covers an instance that saw the change late), and :meth:`due` hands out the robots to send again with the
    step they were at. Re-sent steps are answered by the consumers without computing anything twice (the
    step claims and their stored answers). Not thread-safe: call it from the producer's worker."""

    def __init__(self, services: Iterable[str], after_s: tuple[float, ...] = REDRIVE_AFTER_S) -> None:
        self.after_s = tuple(sorted(after_s))
        self._live: dict[str, frozenset[str]] = {keys.check_id(s, "service"): frozenset() for s in services}
        self._due: dict[str, tuple[object, list[float]]] = {}

    def live(self, service: str) -> frozenset[str]:
        return self._live.get(service, frozenset())

    def changed(self, service: str, instance: str, up: bool, robots: dict[str, object], now: float) -> set[str]:
        """An instance of ``service`` appeared (``up``) or vanished; ``robots`` maps each robot the producer
        drives to its current step (any value compared by equality). An ``up`` for an instance already live is
        a process restarted under its name: the robots it owns are scheduled. Returns the robots scheduled."""
        before = self._live.get(service)
        if before is None:
            return set()
        after = before | {instance} if up else before - {instance}
        if after != before:
            self._live[service] = after
            moved_ = reassigned(robots, before, after)
        elif up:  # a new process under a live name: what was in flight to its predecessor is lost with it
            moved_ = {r for r, o in assignment(robots, after).items() if o == instance}
        else:
            return set()
        self.schedule({r: robots[r] for r in moved_}, now)
        return moved_

    def schedule(self, robots: dict[str, object], now: float) -> None:
        """Send the current step of each robot again ``after_s`` from ``now`` (a robot already scheduled is
        scheduled anew)."""
        for robot, step in robots.items():
            self._due[robot] = (step, [now + d for d in self.after_s])

    def due(self, now: float) -> dict[str, object]:
        """Robots whose next re-send time has come, with the step they were at when scheduled."""
        out: dict[str, object] = {}
        for robot, (step, times) in list(self._due.items()):
            if times and times[0] <= now:
                out[robot] = step
                while times and times[0] <= now:
                    times.pop(0)
            if not times:
                del self._due[robot]
        return out

    def pending(self) -> int:
        return len(self._due)

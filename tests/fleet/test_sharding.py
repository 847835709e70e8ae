"""Robots shared among instances (eqa.sharding): the rendezvous rule, the liveliness-driven membership over real
Zenoh sessions (one instance a separate process killed with SIGKILL), and exactly-once step claims on both
stores."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections import Counter
from pathlib import Path

import pytest

from eqa import keys, sharding
from eqa.bus import Bus
from eqa.settings import Settings
from eqa.sharding import Membership, StepClaims

REPO = Path(__file__).resolve().parents[2]
ROBOTS = [f"robot{i}" for i in range(600)]


def test_rendezvous_owner_is_deterministic_and_balanced():
    inst = ["mapper-a", "mapper-b", "mapper-c"]
    a1 = sharding.assignment(ROBOTS, inst)
    a2 = sharding.assignment(ROBOTS, list(reversed(inst)))
    assert a1 == a2
    counts = Counter(a1.values())
    assert set(counts) == set(inst)
    assert all(150 <= c <= 250 for c in counts.values()), counts  # 200 each on average
    assert sharding.owner("robot0", []) is None
    assert sharding.owner("robot0", ["only"]) == "only"


def test_a_join_moves_robots_only_to_the_newcomer_and_a_leave_only_from_the_leaver():
    before = ["p-a", "p-b", "p-c"]
    after = [*before, "p-d"]
    a, b = sharding.assignment(ROBOTS, before), sharding.assignment(ROBOTS, after)
    changed = [r for r in ROBOTS if a[r] != b[r]]
    assert all(b[r] == "p-d" for r in changed)
    assert 90 <= len(changed) <= 210  # about a quarter of 600
    gained, lost = sharding.moved(ROBOTS, "p-d", before, after)
    assert gained == set(changed) and not lost
    gained, lost = sharding.moved(ROBOTS, "p-a", before, after)
    assert not gained and lost == {r for r in changed if a[r] == "p-a"}
    c = sharding.assignment(ROBOTS, ["p-a", "p-c"])  # p-b vanished
    assert all(c[r] == a[r] for r in ROBOTS if a[r] != "p-b")


_HOLDER = """
import sys, time
from eqa.bus import Bus
from eqa.settings import Settings
s = Settings(zenoh_mode="peer", zenoh_listen=["tcp/127.0.0.1:0"], zenoh_connect=[sys.argv[1]], zenoh_multicast=False)
with Bus(s, "mapper", "mapper-proc") as b:
    b.declare_alive()
    print("up", flush=True)
    time.sleep(120)
"""


def test_membership_follows_liveliness_and_instances_agree(settings: Settings, hub_settings: Settings,
                                                          zenoh_port: int):
    changes: list[tuple[frozenset[str], frozenset[str]]] = []
    with Bus(hub_settings, "mapper", "mapper-a") as a, Bus(settings, "mapper", "mapper-b") as b:
        a.declare_alive()
        b.declare_alive()
        ma = Membership(a, "mapper", "mapper-a", on_change=lambda x, y: changes.append((x, y))).start()
        mb = Membership(b, "mapper", "mapper-b").start()
        other = Membership(b, "planner", "planner-x").start()  # another service's instances are not counted
        proc = subprocess.Popen([sys.executable, "-c", _HOLDER, f"tcp/127.0.0.1:{zenoh_port}"], cwd=REPO,
                                stdout=subprocess.PIPE, text=True, start_new_session=True)
        try:
            assert proc.stdout is not None and proc.stdout.readline().strip() == "up"
            want = {"mapper-a", "mapper-b", "mapper-proc"}
            deadline = time.monotonic() + 10
            while (ma.live != want or mb.live != want) and time.monotonic() < deadline:
                time.sleep(0.05)
            assert ma.live == mb.live == want
            assert other.live == {"planner-x"}
            owners = {r: [m.me for m in (ma, mb) if m.owns(r)] for r in ROBOTS[:60]}
            assert all(len(v) <= 1 for v in owners.values())
            assert sum(1 for r in ROBOTS[:60] if sharding.owner(r, want) == "mapper-proc") == \
                sum(1 for v in owners.values() if not v)
            os.killpg(proc.pid, signal.SIGKILL)  # no goodbye: Zenoh withdraws the token when the link drops
            proc.wait(timeout=10)
            deadline = time.monotonic() + 15
            while (ma.live != want - {"mapper-proc"} or mb.live != ma.live) and time.monotonic() < deadline:
                time.sleep(0.05)
            assert ma.live == mb.live == {"mapper-a", "mapper-b"}
            assert all(ma.owns(r) != mb.owns(r) for r in ROBOTS[:60])  # every robot has exactly one owner again
            assert changes[-1][1] == frozenset({"mapper-a", "mapper-b"})
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(timeout=10)


def test_each_step_is_claimed_once_and_a_dead_holders_claim_is_taken_over(store):
    alive = {"st-a", "st-b"}
    a = StepClaims(store, "stopper", "st-a", alive.__contains__)
    b = StepClaims(store, "stopper", "st-b", alive.__contains__)
    first = a.claim("ep-1", 0)
    assert first.won and not first.stale
    lost = b.claim("ep-1", 0)
    assert not lost.won and lost.holder == "st-a"
    assert a.claim("ep-1", 0).won  # the same step again at its holder (a resent frame): answered from state
    # st-a computes step 1 too, then dies before step 2 is done
    assert a.claim("ep-1", 1).won
    assert a.claim("ep-1", 2).won
    alive.discard("st-a")
    took = b.claim("ep-1", 2)
    assert took.won and took.holder == "st-b"
    assert took.stale  # step 1 was computed by st-a: st-b reloads the episode from the store
    assert b.holder("ep-1", 2) == "st-b"
    assert not b.claim("ep-1", 3).stale
    b.forget("ep-1", 3)
    assert b.holder("ep-1", 2) is None


def test_an_instance_restarted_under_its_name_does_not_take_back_a_step_taken_over(store):
    alive = {"pl-a", "pl-b"}
    a = StepClaims(store, "planner", "pl-a", alive.__contains__)
    b = StepClaims(store, "planner", "pl-b", alive.__contains__)
    assert a.claim("ep-2", 4).won
    alive.discard("pl-a")  # killed after its claim; pl-b takes the step over
    assert b.claim("ep-2", 4).won
    alive.add("pl-a")  # the launcher restarts it under the same name; the step comes again (a resend)
    again = a.claim("ep-2", 4)
    assert not again.won and again.holder == "pl-b"
    assert b.claim("ep-2", 4).won  # at its holder: answered from its state
    alive.discard("pl-b")
    third = a.claim("ep-2", 4)  # the takeover's holder died too: the next attempt
    assert third.won and a.holder("ep-2", 4) == "pl-a"
    a.forget("ep-2", 4)
    assert store.keys(f"{sharding.CLAIM_PREFIX}planner:ep-2:") == []


def test_concurrent_claimants_get_exactly_one_winner(store):
    alive = {f"i{k}" for k in range(4)}
    winners: list[str] = []
    lock = threading.Lock()

    def run(me: str) -> None:
        c = StepClaims(store, "planner", me, alive.__contains__)
        for step in range(30):
            if c.claim("ep-race", step).won:
                with lock:
                    winners.append(f"{step}")

    threads = [threading.Thread(target=run, args=(m,)) for m in sorted(alive)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    assert sorted(winners, key=int) == [str(s) for s in range(30)]  # each step once, none skipped


@pytest.mark.parametrize("n", [1, 2, 3])
def test_every_robot_has_one_owner_for_any_number_of_instances(n: int):
    inst = [f"sim-{i}" for i in range(n)]
    views = [sharding.assignment(ROBOTS[:100], inst) for _ in inst]
    assert all(v == views[0] for v in views)
    assert set(views[0].values()) <= set(inst)


def test_shard_reports_the_robots_that_move_when_an_instance_joins(settings: Settings, hub_settings: Settings,
                                                                   store):
    moves: list[tuple[set[str], set[str]]] = []
    robots = [f"r{i}" for i in range(20)]
    with Bus(hub_settings, "stopper", "st-a") as a:
        a.declare_alive()
        sa = sharding.Shard(a, lambda: store, "stopper", "st-a", on_moved=lambda g, lo: moves.append((g, lo))).start()
        assert all(sa.owns(r) for r in robots)  # alone: every robot (and now it knows them)
        # st-b starts after st-a is up (its token routed at the link handshake, which Bus.open waits for)
        with Bus(settings, "stopper", "st-b") as b:
            sb = sharding.Shard(b, lambda: store, "stopper", "st-b").start()
            assert sb.membership.live == {"st-a", "st-b"}  # synced at start, before its own token exists
            b.declare_alive()
            deadline = time.monotonic() + 10
            while not moves and time.monotonic() < deadline:
                time.sleep(0.05)
            gained, lost = moves[-1]
            assert not gained and lost == {r for r in robots if sharding.owner(r, ["st-a", "st-b"]) == "st-b"}
            assert all(sa.owns(r) != sb.owns(r) for r in robots)
            assert sa.claim("ep", 0).won and not sb.claim("ep", 0).won
            off = sharding.Shard(b, lambda: store, "stopper", "st-c", enabled=False).start()
            assert all(off.owns(r) for r in robots) and off.claim("ep", 0).won


def test_refused_robots_are_dropped_before_decoding(settings: Settings, hub_settings: Settings):
    from eqa import keys
    from eqa.messages import Frame

    seen: list[str] = []
    invalid: list[str] = []
    done = threading.Event()
    with Bus(hub_settings, "mapper", "m-a") as a, Bus(settings, "sim", "s") as sim:
        a.subscribe(keys.any_robot(keys.SIM_FRAME), Frame, lambda k, m: seen.append(k),
                    on_invalid=lambda k, p, why: (invalid.append(k), done.set()),
                    accept=lambda key: keys.robot_of(key) == "mine")
        time.sleep(0.3)
        sim.publish_raw(keys.stream("theirs", keys.SIM_FRAME), b"\x00 not a frame")
        sim.publish_raw(keys.stream("mine", keys.SIM_FRAME), b"\x00 not a frame")
        assert done.wait(5)
        time.sleep(0.2)
    assert invalid == [keys.stream("mine", keys.SIM_FRAME)] and not seen


def test_a_session_behind_a_slow_link_sees_the_instances_already_there(settings: Settings, hub_settings: Settings,
                                                                      zenoh_port: int, store):
    """The link's handshake completes 2.5 s after ``zenoh.open`` returned (it returns after ~0.5 s without it):
    the bus waits for the link before it answers, so the first view of a starting instance already counts the
    instance that was there. Without the wait (``bus_link_wait_s=0``) the same query answers "nobody"."""
    from support.slow_link import SlowLink

    with Bus(hub_settings, "stopper", "st-a") as a, SlowLink(zenoh_port, 2.5) as link:
        a.declare_alive()
        via = settings.model_copy(update={"zenoh_connect": [link.endpoint]})
        with Bus(via.model_copy(update={"bus_link_wait_s": 0.0}), "stopper", "st-early") as early:
            assert early.alive(keys.alive_service("stopper"), timeout=1.0) == []
        with Bus(via, "stopper", "st-b") as b:
            sb = sharding.Shard(b, lambda: store, "stopper", "st-b").start()
            assert sb.membership.live == {"st-a", "st-b"}
            robots = [f"r{i}" for i in range(20)]
            mine = {r for r in robots if sharding.owner(r, ["st-a", "st-b"]) == "st-b"}
            assert {r for r in robots if sb.owns(r)} == mine

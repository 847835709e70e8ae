"""The stopper service over real Zenoh: StepScores in, Decision / EpisodeEnd out; survives a restart."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from support.fleet import wait_for

from eqa import keys
from eqa.bus import Bus
from eqa.messages import (
    Decision,
    EpisodeCancel,
    EpisodeEnd,
    EpisodeStart,
    Goal,
    Question,
    StepScores,
    StopConfig,
)
from eqa.recording import recording_dir
from eqa.settings import Settings
from eqa.store import EmbeddedStore, episode_end_key
from services.stopper import synthetic
from services.stopper.calibration import CalibrationTable, TraceStore, calibrate, save_table
from services.stopper.service import STATE_PREFIX, StopperService

REPO = Path(__file__).resolve().parents[2]
ROBOT = "r0"
LABELS = "ABCD"




class Listener:
    """The test's own Zenoh peer (the hub): publishes inputs, collects the stopper's outputs."""

    def __init__(self, bus: Bus) -> None:
        self.bus = bus
        self.decisions: list[Decision] = []
        self.ends: list[EpisodeEnd] = []
        self._lock = threading.Lock()
        bus.subscribe(keys.stream(ROBOT, keys.STOPPER_DECISION), Decision, lambda _k, m: self._add(self.decisions, m))
        bus.subscribe(keys.stream(ROBOT, keys.EPISODE_END), EpisodeEnd, lambda _k, m: self._add(self.ends, m))

    def _add(self, into: list, msg: object) -> None:
        with self._lock:
            into.append(msg)

    def send(self, pair: tuple[str, str], msg: object) -> None:
        self.bus.publish(keys.stream(ROBOT, pair), msg)  # type: ignore[arg-type]

    def decision(self, episode_id: str, step: int) -> Decision:
        seen = lambda: any(d.episode_id == episode_id and d.step == step for d in self.decisions)  # noqa: E731
        assert wait_for(seen, timeout=10.0), f"no decision for {episode_id} step {step}"
        return next(d for d in self.decisions if d.episode_id == episode_id and d.step == step)

    def end(self, episode_id: str) -> EpisodeEnd:
        ended = lambda: any(e.episode_id == episode_id for e in self.ends)  # noqa: E731
        assert wait_for(ended, timeout=10.0), f"no end for {episode_id}"
        return next(e for e in self.ends if e.episode_id == episode_id)

    def ready(self, timeout: float = 30.0) -> None:
        """Wait until the stopper answers end to end: a one-step probe episode until its EpisodeEnd arrives
        (subscriptions propagate asynchronously; a fixed sleep is not enough on a loaded machine)."""
        deadline = time.monotonic() + timeout
        n = 0
        while time.monotonic() < deadline:
            n += 1
            eid = f"probe-{n}-{time.monotonic_ns()}"
            self.send(keys.EPISODE_START, _start(eid, rule="max_steps", max_steps=1))
            self.send(keys.MAPPER_SCORES, _scores(eid, 0, [0.25] * 4, 0.5))
            if wait_for(lambda e=eid: any(x.episode_id == e for x in self.ends), timeout=1.0):
                return
        raise AssertionError("the stopper never answered a probe episode")

    def alive_instances(self) -> set[str]:
        return {inst for _svc, inst in self.bus.alive(keys.alive_service("stopper"), timeout=0.5)}


def _table(name: str = "default") -> CalibrationTable:
    traces = [synthetic.to_trace(e, f"q{i}") for i, e in enumerate(synthetic.episodes(200, seed=21))]
    return calibrate(traces, [0.1, 0.2, 0.5], name=name)


def keeping(keep: str, q_hat: float) -> tuple[list[float], float]:
    """Scores of one step whose causal set C^t (Eq. 10) is exactly ``keep`` under ``q_hat``."""
    m = q_hat - 1.0
    if keep == LABELS:
        return [0.97, 0.01, 0.01, 0.01], 0.0  # an irrelevant (Rel = 0) but confident view keeps everything
    dropped = len(LABELS) - len(keep)
    f_keep = (1.0 - 0.01 * dropped) / len(keep)
    probs = [f_keep if y in keep else 0.01 for y in LABELS]
    a, b = 1.0 - f_keep, 0.99
    rel = min(1.0, 2 * m / (a + b))
    assert rel * a <= m < rel * b
    return probs, rel


def _question(answer: str = "B") -> Question:
    return Question(
        id="q-sofa",
        text="What colour is the sofa?",
        choices=["red", "blue", "green", "grey"],
        scene="gen-00001",
        answer=answer,
        category="identification",
    )


def _start(
    eid: str,
    rule: str = "cp",
    eps: float = 0.2,
    max_steps: int = 10,
    record: bool = False,
    threshold: float | None = None,
) -> EpisodeStart:
    return EpisodeStart(
        episode_id=eid,
        robot=ROBOT,
        question=_question(),
        max_steps=max_steps,
        record=record,
        stop=StopConfig(rule=rule, eps=eps, threshold=threshold),
    )  # type: ignore[arg-type]


def _scores(eid: str, step: int, probs: list[float], rel: float) -> StepScores:
    return StepScores(episode_id=eid, step=step, answer_probs=probs, relevance=rel, backend="test")


@contextlib.contextmanager
def listened_stopper(hub_settings: Settings, svc_settings: Settings) -> Iterator[tuple[Listener, StopperService]]:
    """An in-process stopper with ``svc_settings`` and a :class:`Listener` it answers end to end."""
    with Bus(hub_settings, "gateway", "test") as bus:
        listener = Listener(bus)
        svc = StopperService(svc_settings)
        svc.start()
        try:
            assert wait_for(lambda: listener.alive_instances(), timeout=10.0)
            listener.ready()
            yield listener, svc
        finally:
            svc.stop()


@pytest.fixture
def running(hub_settings: Settings, settings: Settings) -> Iterator[tuple[Listener, StopperService, Settings]]:
    svc_settings = settings.model_copy(update={"record": True})
    store = EmbeddedStore(settings.data_dir / "store.sqlite")
    save_table(store, _table())
    store.close()
    with listened_stopper(hub_settings, svc_settings) as (listener, svc):
        yield listener, svc, svc_settings


def test_cp_episode_stops_when_one_answer_is_left(running: tuple[Listener, StopperService, Settings]) -> None:
    lis, svc, st = running
    q_hat = _table().lookup(0.2)[0].q_hat  # type: ignore[index]
    lis.send(keys.EPISODE_START, _start("ep-cp", record=True))
    plan = ["ABC", "ABCD", "BCD", "B"]
    expected_running = ["ABC", "ABC", "BC", "B"]
    for t, keep in enumerate(plan):
        lis.send(keys.MAPPER_SCORES, _scores("ep-cp", t, *keeping(keep, q_hat)))
        d = lis.decision("ep-cp", t)
        assert d.rule == "cp" and d.q_hat == q_hat
        assert d.step_set == list(keep) and d.prediction_set == list(expected_running[t])
        assert d.stop == (t == 3)
        assert set(d.scores) == set(LABELS)
        if t == 1:  # a repeated step is not decided twice: its decision is published again, unchanged
            lis.send(keys.MAPPER_SCORES, _scores("ep-cp", 1, [0.01, 0.01, 0.01, 0.97], 1.0))
            assert wait_for(lambda: sum(d.episode_id == "ep-cp" and d.step == 1 for d in lis.decisions) == 2)
    end = lis.end("ep-cp")
    assert (end.state, end.answer, end.answer_text, end.prediction_set) == ("stopped", "B", "blue", ["B"])
    assert end.steps == 4 and end.max_steps == 10 and end.correct is True
    assert "one answer left" in end.reason and "eps=0.2" in end.reason
    assert end.recording == str(recording_dir(st, "ep-cp"))
    assert (Path(end.recording) / "stopper.rrd").stat().st_size > 0
    svc.drain()
    printed = subprocess.run(
        [str(Path(sys.executable).with_name("rerun")), "rrd", "print", str(Path(end.recording) / "stopper.rrd")],
        capture_output=True,
        text=True,
        timeout=60,
        env={**os.environ, "RERUN_TELEMETRY_ENABLED": "false"},
        check=True,
    ).stdout
    for entity in (
        "/stopper/rho/A",
        "/stopper/rho/D",
        "/stopper/set_size",
        "/stopper/relevance",
        "/stopper/prediction_set",
        "/stopper/scores/B",
        "/stopper/log",
    ):
        assert f" - {entity} - " in printed, entity
    decisions = [d for d in lis.decisions if d.episode_id == "ep-cp"]
    assert [d.step for d in decisions] == [0, 1, 1, 2, 3] and decisions[1] == decisions[2]
    svc.drain()
    trace = TraceStore(svc.store).trace_for_episode("ep-cp")
    assert trace is not None and len(trace.steps) == 4 and trace.answer == "B" and trace.question_id == "q-sofa"
    assert svc.store.get(STATE_PREFIX + "ep-cp") is None
    assert EpisodeEnd.model_validate_json(svc.store.get(episode_end_key("ep-cp")) or b"") == end


def test_calibration_lookup_bad_scores_planner_done_cancel_and_baselines(
    running: tuple[Listener, StopperService, Settings],
) -> None:
    lis, svc, _ = running
    q_hat = _table().lookup(0.2)[0].q_hat  # type: ignore[index]

    # eps 0.3 is not in the table: the nearest stored eps below (0.2) is used, and the reason says so
    lis.send(keys.EPISODE_START, _start("ep-near", eps=0.3))
    lis.send(keys.MAPPER_SCORES, _scores("ep-near", 0, *keeping("ABC", q_hat)))
    d = lis.decision("ep-near", 0)
    assert d.q_hat == q_hat and "nearest stored eps=0.2" in d.reason and not d.stop

    # eps below every stored one: the episode fails and tells the user what to do
    lis.send(keys.EPISODE_START, _start("ep-none", eps=0.05))
    end = lis.end("ep-none")
    assert end.state == "failed" and "eqa calibrate" in end.reason and end.answer is None

    # NaN scores: the episode fails with the reason; the stored trace keeps only the valid steps
    lis.send(keys.EPISODE_START, _start("ep-nan"))
    lis.send(keys.MAPPER_SCORES, _scores("ep-nan", 0, *keeping("ABC", q_hat)))
    lis.decision("ep-nan", 0)
    lis.bus.publish_raw(keys.stream(ROBOT, keys.MAPPER_SCORES), b"\x93garbage")
    lis.send(keys.MAPPER_SCORES, _scores("ep-nan", 1, [0.5, float("nan"), 0.25, 0.25], 0.5))
    end = lis.end("ep-nan")
    assert end.state == "failed" and "NaN" in end.reason and end.steps == 1
    svc.drain()
    trace = TraceStore(svc.store).trace_for_episode("ep-nan")
    assert trace is not None and len(trace.steps) == 1

    # the planner has nothing left: fallback answer = argmax f at the most relevant step
    lis.send(keys.MAPPER_SCORES, _scores("ep-near", 1, [0.1, 0.1, 0.7, 0.1], 0.0))
    lis.decision("ep-near", 1)
    lis.send(keys.PLANNER_GOAL, Goal(episode_id="ep-near", step=1, done=True, reason="no frontiers left"))
    end = lis.end("ep-near")
    assert end.state == "stopped" and "no frontiers left" in end.reason and end.steps == 2
    assert end.answer == "A"  # step 0 (Rel > 0) has f = (0.33, 0.33, 0.33, 0.01): first of the tied labels
    assert end.correct is False

    # cancel
    lis.send(keys.EPISODE_START, _start("ep-cancel"))
    lis.send(keys.MAPPER_SCORES, _scores("ep-cancel", 0, *keeping("ABCD", q_hat)))
    lis.decision("ep-cancel", 0)
    lis.send(keys.EPISODE_CANCEL, EpisodeCancel(episode_id="ep-cancel", reason="user changed their mind"))
    end = lis.end("ep-cancel")
    assert end.state == "cancelled" and end.reason == "user changed their mind" and end.correct is None

    # scores that overtake their EpisodeStart (different subscriptions, different Zenoh threads) are held
    lis.send(keys.MAPPER_SCORES, _scores("ep-early", 0, *keeping("AB", q_hat)))
    time.sleep(0.3)
    assert not any(d.episode_id == "ep-early" for d in lis.decisions)
    lis.send(keys.EPISODE_START, _start("ep-early"))
    assert lis.decision("ep-early", 0).prediction_set == ["A", "B"]
    lis.send(keys.EPISODE_CANCEL, EpisodeCancel(episode_id="ep-early"))
    assert lis.end("ep-early").state == "cancelled"

    # entropy baseline stops on a confident view; relevance baseline does not on an irrelevant one
    lis.send(keys.EPISODE_START, _start("ep-ent", rule="entropy", threshold=0.2))
    lis.send(keys.EPISODE_START, _start("ep-rel", rule="relevance", max_steps=2))
    lis.send(keys.MAPPER_SCORES, _scores("ep-ent", 0, [0.01, 0.97, 0.01, 0.01], 0.05))
    lis.send(keys.MAPPER_SCORES, _scores("ep-rel", 0, [0.01, 0.97, 0.01, 0.01], 0.05))
    assert lis.decision("ep-ent", 0).stop and lis.end("ep-ent").answer == "B"
    assert not lis.decision("ep-rel", 0).stop
    lis.send(keys.MAPPER_SCORES, _scores("ep-rel", 1, [0.01, 0.01, 0.97, 0.01], 0.3))
    end = lis.end("ep-rel")
    assert end.answer == "C" and "step limit" in end.reason and end.steps == 2 and end.prediction_set == []
    svc.drain()
    assert [k for k in svc.store.keys(STATE_PREFIX) if "probe-" not in k] == []
    assert [e for e in svc.episodes if not e.startswith("probe-")] == []


def test_restart_of_the_stopper_process_keeps_the_running_intersection(
    hub_settings: Settings, settings: Settings
) -> None:
    table = _table()
    q_hat = table.lookup(0.2)[0].q_hat  # type: ignore[index]
    store = EmbeddedStore(settings.data_dir / "store.sqlite")
    save_table(store, table)
    store.close()
    env = {k: v for k, v in os.environ.items() if not k.startswith("EQA_")}
    env.update({k: v for k, v in settings.env().items() if k != "EQA_INSTANCE"})
    env["EQA_LOG_LEVEL"] = "WARNING"

    def spawn() -> subprocess.Popen[bytes]:
        return subprocess.Popen(
            [sys.executable, "-m", "services.stopper"],
            cwd=REPO,
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
        )

    procs: list[subprocess.Popen[bytes]] = []
    with Bus(hub_settings, "gateway", "test") as bus:
        lis = Listener(bus)
        try:
            procs.append(spawn())
            assert wait_for(lis.alive_instances, timeout=30), "stopper process did not come up"
            first = lis.alive_instances()
            lis.ready()
            lis.send(keys.EPISODE_START, _start("ep-restart"))
            lis.send(keys.MAPPER_SCORES, _scores("ep-restart", 0, *keeping("ABC", q_hat)))
            assert lis.decision("ep-restart", 0).prediction_set == ["A", "B", "C"]
            lis.send(keys.MAPPER_SCORES, _scores("ep-restart", 1, *keeping("AB", q_hat)))
            assert lis.decision("ep-restart", 1).prediction_set == ["A", "B"]

            procs[0].send_signal(signal.SIGKILL)  # no clean shutdown: the state must already be stored
            procs[0].wait(timeout=10)
            procs.append(spawn())
            assert wait_for(lambda: lis.alive_instances() - first, timeout=30), "restarted stopper not up"
            lis.ready()
            # C^2 = {B, C}: with the restored running set {A, B} only B is left -> stop with B
            lis.send(keys.MAPPER_SCORES, _scores("ep-restart", 2, *keeping("BC", q_hat)))
            d = lis.decision("ep-restart", 2)
            assert d.step_set == ["B", "C"] and d.prediction_set == ["B"] and d.stop
            end = lis.end("ep-restart")
            assert end.answer == "B" and end.steps == 3 and end.correct is True
        finally:
            for p in procs:
                if p.poll() is None:
                    p.send_signal(signal.SIGTERM)
                    try:
                        p.wait(timeout=15)
                    except subprocess.TimeoutExpired:
                        p.kill()
                        p.wait()
    assert procs[-1].returncode == 0, (procs[-1].stderr.read() if procs[-1].stderr else b"").decode()[-2000:]
    store = EmbeddedStore(settings.data_dir / "store.sqlite")
    try:
        trace = TraceStore(store).trace_for_episode("ep-restart")
        assert trace is not None and len(trace.steps) == 3
    finally:
        store.close()


def test_a_stored_end_is_published_again_when_a_step_comes_after_it(
    running: tuple[Listener, StopperService, Settings],
) -> None:
    """An instance killed between storing an episode's end and publishing it: its successor, asked the last step
    again, publishes the stored end (without it the episode waits for the gateway's watchdog)."""
    lis, svc, st = running
    lis.send(keys.EPISODE_START, _start("ep-stored-end", rule="max_steps", max_steps=1))
    lis.send(keys.MAPPER_SCORES, _scores("ep-stored-end", 0, [0.25] * 4, 0.5))
    first = lis.end("ep-stored-end")
    svc.stop()  # as if killed after storing the end: the successor has no state and never saw the end
    with lis._lock:
        lis.ends.clear()
    successor = StopperService(st)
    successor.start()
    try:
        assert wait_for(lambda: lis.alive_instances(), timeout=10.0)
        deadline = time.monotonic() + 30
        while not lis.ends and time.monotonic() < deadline:  # the step re-sent until the successor listens
            lis.send(keys.MAPPER_SCORES, _scores("ep-stored-end", 0, [0.25] * 4, 0.5))
            wait_for(lambda: bool(lis.ends), timeout=1.0)
        again = lis.end("ep-stored-end")
        assert again == first
    finally:
        successor.stop()


def test_a_step_of_an_episode_another_instance_ended_is_not_decided_again(
    running: tuple[Listener, StopperService, Settings],
) -> None:
    """Two instances that both count the robot as theirs for a moment (their views of the membership differ while
    one joins): the other one decides the last step, stores the end, deletes the step claims and state, and
    publishes; this one, still holding the episode in memory, then gets the same last step's scores before the
    end. The claims are gone, so the step's claim is won again: the stored end must stop it from deciding the
    step a second time (it publishes the stored end instead)."""
    lis, svc, _ = running
    eid = "ep-ended-elsewhere"
    lis.send(keys.EPISODE_START, _start(eid, rule="max_steps", max_steps=3))
    for t in range(2):
        lis.send(keys.MAPPER_SCORES, _scores(eid, t, [0.25] * 4, 0.5))
        lis.decision(eid, t)
    svc.drain()
    assert eid in svc.episodes
    # what the other instance did when it decided step 2: the end stored, then the claims and the state deleted
    end = EpisodeEnd(episode_id=eid, robot=ROBOT, state="stopped", reason="max steps (elsewhere)", answer="A",
                     steps=3, max_steps=3)
    svc.store.set(episode_end_key(eid), end.model_dump_json().encode())
    assert svc.shard is not None and svc.shard.claims is not None
    svc.shard.claims.forget(eid, 3)
    svc.store.delete(STATE_PREFIX + eid)
    lis.send(keys.MAPPER_SCORES, _scores(eid, 2, [0.25] * 4, 0.5))
    assert lis.end(eid) == end  # the stored end, published again
    svc.drain()
    assert not any(d.episode_id == eid and d.step == 2 for d in lis.decisions)
    assert eid not in svc.episodes and svc.store.get(STATE_PREFIX + eid) is None


def test_a_question_in_a_home_stops_on_the_warm_table_only_when_it_started_warm(
        hub_settings: Settings, settings: Settings) -> None:
    """EQA_HOME_CALIBRATION_NAME names the warm table; the first question in an empty home (no StepScores.warm)
    is a cold question and stops on the cold table; a question that started from the home's memory on the warm
    one, and its decisions say so."""
    from eqa.messages import MemoryBounds, MemoryScore, WarmStart

    bounds = MemoryBounds(max_views=24, warm_views=24, memory_steps=0, warm_budget=0.15, warm_area="observed",
                          stale_weight=0.0)
    warm_start = WarmStart(version=1, bounds=bounds)
    warm_traces = [synthetic.to_trace(e, f"w{i}").model_copy(update={"memory_steps": 1, "warm": warm_start})
                   for i, e in enumerate(synthetic.episodes(40, seed=5))]
    warm_table = calibrate(warm_traces, [0.2], name="home-warm")
    store = EmbeddedStore(settings.data_dir / "store.sqlite")
    save_table(store, _table())
    save_table(store, warm_table)
    store.close()
    cold_q = _table().lookup(0.2)[0].q_hat  # type: ignore[index]
    warm_q = warm_table.lookup(0.2)[0].q_hat  # type: ignore[index]
    assert cold_q != warm_q
    with listened_stopper(hub_settings, settings.model_copy(update={"home_calibration_name": "home-warm"})) as (
            lis, _svc):
        for eid, warm in (("ep-home-first", None), ("ep-home-warm", warm_start)):
            lis.send(keys.EPISODE_START, _start(eid).model_copy(update={"home": "h-0123456789abcdef"}))
            memory = [MemoryScore(answer_probs=[0.25] * 4, relevance=0.1)] if warm else []
            lis.send(keys.MAPPER_SCORES, _scores(eid, 0, [0.3, 0.3, 0.2, 0.2], 0.2).model_copy(
                update={"memory": memory, "warm": warm}))
        first, warm_d = lis.decision("ep-home-first", 0), lis.decision("ep-home-warm", 0)
        assert first.q_hat == cold_q and first.warm_calibrated is None
        assert warm_d.q_hat == warm_q and warm_d.warm_calibrated is True

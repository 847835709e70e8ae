"""Warm standbys (eqa.standby, EQA_STANDBY): with one process per service, a kill -9 of any service is answered by
promoting that service's pre-started standby (imports done, off the bus) instead of starting a new process, the
episode goes on with each step computed once, and a new standby takes the promoted one's place. Real processes,
real Zenoh, real Redis; the sim never resends on its own (``EQA_STEP_RESEND_S=0``), so the episode goes on only
through the promoted process's re-drive."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest
from support.fleet import wait_for
from test_redrive import SCENE, Run

from eqa import keys, standby
from eqa.launcher import PIPELINE, Fleet
from eqa.settings import Settings

STEPS = 10
SERVICES = ("sim", "mapper", "vlm_scorer", "planner", "stopper")


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory, redis_url: str):
    from services.sim.library import load_or_generate

    data = tmp_path_factory.mktemp("standby")
    settings = Settings(data_dir=data, redis_url=redis_url, zenoh_listen=[], zenoh_connect=[], sim_width=160,
                        sim_height=120, record=False, step_resend_s=0.0, episode_timeout_s=300.0, standby=True)
    load_or_generate(SCENE, settings.scenes_path)
    with Fleet(settings, services=PIPELINE, scorers=1, max_restarts=10) as f:
        run, ledger = Run.watching(f.hub)
        f.wait_standbys(timeout=180)
        yield f, run, ledger


def test_standbys_are_ready_and_off_the_bus(fleet) -> None:
    f, _, _ = fleet
    rows = f.status()
    spares = [r for r in rows if r["role"] == "standby"]
    assert sorted(r["service"] for r in spares) == sorted(SERVICES)  # one per service, no more
    assert all(r["ready"] and r["alive"] for r in spares), spares
    live = f.hub.alive(keys.ALIVE_ANY, timeout=2.0)
    assert sorted(service for service, _ in live) == sorted(SERVICES), live  # the active instances only
    assert all("standby" not in inst for _, inst in live), live
    for service in SERVICES:
        text = f.standbys[service].log_path.read_text(errors="replace")
        assert "waiting off the bus for a promotion" in text, text[-2000:]


@pytest.mark.parametrize("service", SERVICES)
def test_a_kill_is_answered_by_the_standby_and_every_step_is_made_once(fleet, service: str) -> None:
    f, run, ledger = fleet
    f.wait_alive(timeout=120)
    f.wait_standbys(timeout=180)
    spare_pid = f.standbys[service].proc.pid
    eid = f"standby-{service}-{os.getpid()}-{time.time_ns()}"
    run.start_mid_step(f.hub, eid, STEPS, 5, service)
    child = f.child(service)
    killed = child.proc.pid  # type: ignore[union-attr]
    f.kill(service)
    ended = run.wait(lambda: eid in run.ends, 180)
    assert ended, f"episode stuck at step {run.last.get(eid)} after the {service} kill; " \
        f"{child.log_path.read_text(errors='replace')[-2000:]}"
    end = run.ends[eid]
    assert end.state == "stopped" and end.steps == STEPS, end
    # the episode may end before the promotion (a kill in its last step): the take-over itself is bounded
    assert wait_for(lambda: child.proc is not None and child.proc.pid == spare_pid, 15.0), child.history
    assert spare_pid != killed  # the standby took the instance's place
    assert f"standby pid {spare_pid} promoted" in child.history
    assert f"promoted to instance {child.instance}" in child.log_path.read_text(errors="replace")
    assert not (problems := ledger.settled_problems({eid: STEPS})), problems
    f.wait_standbys(timeout=180)  # a new standby, a new process
    assert f.standbys[service].proc.pid not in (spare_pid, killed)


def test_a_standby_whose_launcher_closes_the_pipe_exits_without_joining(tmp_path) -> None:
    read_fd, write_fd = os.pipe()
    env = {**os.environ, "EQA_DATA_DIR": str(tmp_path), "EQA_ZENOH_CONNECT": "tcp/127.0.0.1:9"}
    proc = subprocess.Popen([sys.executable, "-m", "services.stopper", "--standby", str(write_fd)], env=env,
                            stdin=subprocess.PIPE, stderr=subprocess.PIPE, pass_fds=(write_fd,))
    os.close(write_fd)
    with os.fdopen(read_fd, "rb") as pipe:
        assert pipe.readline() == standby.READY
    assert proc.poll() is None  # waiting
    assert proc.stdin is not None
    proc.stdin.close()
    assert proc.wait(timeout=30) == 0
    err = proc.stderr.read().decode() if proc.stderr else ""
    assert "closed the pipe" in err and " up" not in err.split("closed the pipe")[-1], err


def test_a_promotion_is_bounded_and_checked() -> None:
    with pytest.raises(ValueError, match="at most"):
        standby.Promotion(env={f"EQA_X{i}": "1" for i in range(standby.MAX_VARS + 1)})
    with pytest.raises(ValueError, match="invalid"):
        standby.Promotion(env={"A=B": "1"})
    p = standby.Promotion(env={"EQA_INSTANCE": "mapper-0"}, unset=["EQA_X"])
    assert standby.Promotion.model_validate_json(p.encode()) == p


def test_waiting_for_the_fleet_right_after_a_kill_waits_for_the_replacement(fleet) -> None:
    """A dead child the supervisor is replacing is not a child that "exited before it was up": ``wait_alive``
    right after a kill returns once its standby holds the instance's token."""
    f, _, _ = fleet
    f.wait_alive(timeout=120)
    f.wait_standbys(timeout=180)
    spare_pid = f.standbys["stopper"].proc.pid
    f.kill("stopper")
    f.wait_alive(timeout=60)  # raised LaunchError while the promotion waited for the dead token to go
    assert f.child("stopper").proc.pid == spare_pid


def test_a_dead_process_is_not_up_while_the_bus_still_shows_its_token(tmp_path) -> None:
    """A killed process's liveliness token stays visible until the bus notices its session is gone: waiting for
    the fleet then must not count the dead process as up (here nothing replaces it, so the wait says so)."""
    from eqa.launcher import Child, LaunchError

    f = Fleet(Settings(data_dir=tmp_path), services=["stopper"], restart=False)
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait(timeout=30)
    child = Child("stopper", "stopper-0", {}, tmp_path / "stopper.log", proc=dead, up_at=time.monotonic())
    f.children.append(child)
    f._alive.add(("stopper", "stopper-0"))  # the token the bus has not dropped yet
    with pytest.raises(LaunchError, match="exited with code 0 before it was up"):
        f.wait_alive(timeout=2.0)
    assert f.missing() == [child]

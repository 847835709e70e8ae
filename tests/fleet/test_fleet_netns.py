"""A fleet across three hosts (Linux network namespaces made by the test, see tests/support/netns.py), with the
bus secured (mTLS, passwords, the ownership ACL): the fleet's router on h1 with the sim and the stopper, Redis
and two instances each of the mapper and the planner (sharing the robots) on h2, two scorer replicas on their
own host h3; each host's share started by `eqa up --join`. 8 robots run at once; a mapper (h2) and the stopper
(h1) are killed with SIGKILL and restarted by their host's launcher, and the scorer host is cut off (link down)
and comes back. Every episode runs to its end with all its steps, none is lost.

Skipped, with the reason, only where namespaces cannot be made (not root, no iproute2); docs/deployment.md (Scaling out)
says how to run it there."""

from __future__ import annotations

import os
import signal
import subprocess
import threading
import time
from pathlib import Path

import pytest
from support.exactly_once import StepLedger
from support.netns import PY, Hosts, why_not

from eqa import keys, security
from eqa.bus import Bus
from eqa.messages import EpisodeEnd, EpisodeStart, Question, StopConfig
from eqa.settings import Settings

REASON = why_not()
pytestmark = pytest.mark.skipif(REASON is not None, reason=f"network namespaces unavailable: {REASON}")

ROBOTS = [f"robot{i}" for i in range(8)]
MAX_STEPS = 6
SCENE = "gen-00001"


def _tail(path: Path, n: int = 25) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-n:])
    except OSError:
        return ""


def _wait(pred, timeout: float, what: str, logs: list[Path], procs: tuple = ()) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return
        if any(p.poll() is not None for p in procs):
            what += " (a host's `eqa up` exited)"
            break
        time.sleep(0.2)
    raise AssertionError(f"timed out: {what}\n" + "\n".join(f"== {p}\n{_tail(p)}" for p in logs))


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory):
    from services.sim.library import load_or_generate

    root = tmp_path_factory.mktemp("netns")
    hosts = Hosts()
    pki = root / "pki"
    router_addr = hosts.addr("h1")
    security.make_fleet_certs(pki, hosts=("localhost", "127.0.0.1", router_addr), days=1)
    users = pki / "users.txt"
    users.write_text("".join(f"{r}:pw-{r}-{os.getpid()}\n" for r in security.ROLES))
    users.chmod(0o600)
    data = root / "var"
    load_or_generate(SCENE, data / "scenes")
    logs = root / "logs"
    logs.mkdir()
    base_env = {k: v for k, v in os.environ.items() if not k.startswith("EQA_")}
    base_env.update({
        "EQA_DATA_DIR": str(data), "EQA_RECORD": "false", "EQA_SIM_WIDTH": "160", "EQA_SIM_HEIGHT": "120",
        "EQA_ZENOH_TLS_DIR": str(pki), "EQA_ZENOH_USERS_FILE": str(users), "EQA_ZENOH_ACL": "true",
        "EQA_ZENOH_LISTEN": "", "EQA_ZENOH_CONNECT": "", "EQA_REDIS_URL": f"redis://{hosts.addr('h2')}:6379/0",
        "EQA_STEP_RESEND_S": "6", "EQA_SCORER_TIMEOUT_S": "8", "EQA_LOG_LEVEL": "INFO",
        "PYTHONUNBUFFERED": "1", "RERUN_TELEMETRY_ENABLED": "false",
    })
    try:
        hosts.create()
        endpoint = f"tls/{router_addr}:7447"
        redis = ["redis-server", "--bind", hosts.addr("h2"), "--port", "6379", "--save", "", "--appendonly", "no",
                 "--protected-mode", "no", "--dir", str(root)]
        hosts.run("h2", redis, base_env, logs / "redis.log")
        router_env = {**base_env, "EQA_ZENOH_TLS_CA": str(pki / "ca.pem"),
                      "EQA_ZENOH_TLS_CERT": str(pki / "router.pem"), "EQA_ZENOH_TLS_KEY": str(pki / "router.key")}
        hosts.run("h1", [PY, "-m", "eqa_app", "router", "--listen", endpoint], router_env, logs / "router.log")
        shares = {  # host: (services, scorer replicas, instances of each stateful service)
            "h1": ("sim,stopper", 1, 1),
            "h2": ("mapper,planner", 1, 2),
            "h3": ("vlm_scorer", 2, 1),
        }
        ups = {}
        for host, (services, scorers, instances) in shares.items():
            # no warm standbys: the test finds the processes it kills by their command line, which a waiting
            # standby shares (tests/fleet/test_standby.py covers the standbys' take-over)
            env = {**base_env, "EQA_DATA_DIR": str(data), "EQA_STANDBY": "false"}
            argv = [PY, "-m", "eqa_app", "up", "--join", endpoint, "--services", services, "--scorers", str(scorers),
                    "--instances", str(instances), "--timeout", "120"]
            ups[host] = hosts.run(host, argv, env, logs / f"up-{host}.log")
        all_logs = [logs / f"up-{h}.log" for h in shares] + [logs / "router.log"]
        _wait(lambda: all("fleet up" in (logs / f"up-{h}.log").read_text(errors="replace") for h in shares),
              150, "every host's share up", all_logs, tuple(ups.values()))
        driver = Settings(
            data_dir=data, zenoh_mode="client", zenoh_listen=[], zenoh_connect=[endpoint],
            zenoh_tls_ca=pki / "ca.pem", zenoh_tls_cert=pki / "gateway.pem", zenoh_tls_key=pki / "gateway.key",
            zenoh_user="gateway", zenoh_password=f"pw-gateway-{os.getpid()}",
        )
        yield hosts, ups, driver, data, logs, all_logs
    finally:
        hosts.destroy()


def _start(robot: str, i: int) -> EpisodeStart:
    q = Question(text="Is there a bed in the bedroom?", choices=["Yes", "No"], scene=SCENE)
    return EpisodeStart(episode_id=f"ns-{i}-{os.getpid()}", robot=robot, question=q, max_steps=MAX_STEPS,
                        stop=StopConfig(rule="max_steps"), seed=i, record=False)


def test_eight_robots_across_three_hosts_survive_kills_and_a_partition(fleet):
    hosts, ups, driver, _data, _logs, all_logs = fleet
    ends: dict[str, EpisodeEnd] = {}
    ledger = StepLedger()
    lock = threading.Lock()

    def on_end(_key: str, end: EpisodeEnd) -> None:
        with lock:
            ends.setdefault(end.episode_id, end)

    with Bus(driver, "gateway", "netns-driver") as bus:
        bus.subscribe(keys.any_robot(keys.EPISODE_END), EpisodeEnd, on_end)
        ledger.subscribe(bus)
        alive = {s for s, _ in bus.alive(timeout=3.0)}
        assert {"sim", "mapper", "planner", "stopper", "vlm_scorer"} <= alive, alive
        starts = [_start(r, i) for i, r in enumerate(ROBOTS)]
        t0 = time.monotonic()
        for st in starts:
            bus.publish(keys.stream(st.robot, keys.EPISODE_START), st)
        time.sleep(2.0)
        # kill -9 on two hosts: one of the two mappers on h2 (the other takes its robots over until it is back),
        # the stopper on h1; their launchers restart them
        killed = []
        for host, module, count in (("h2", "services.mapper", 2), ("h1", "services.stopper", 1)):
            pids = hosts.children(ups[host], module)
            assert len(pids) == count, f"{len(pids)} {module} under eqa up on {host}, expected {count}"
            os.kill(pids[0], signal.SIGKILL)
            killed.append((host, module, pids[:1]))
        # the scorer host is cut off for 4 s (shorter than Zenoh's 10 s lease: the links survive)
        hosts.partition("h3")
        time.sleep(4.0)
        hosts.heal("h3")
        ids = {st.episode_id for st in starts}
        _wait(lambda: ids <= set(ends), 150, f"all 8 episodes ended (ended: {sorted(ends)})", all_logs,
              tuple(ups.values()))
        took = time.monotonic() - t0
    for host, module, pids in killed:
        again = hosts.children(ups[host], module)
        assert again and not set(again) & set(pids), f"{module} on {host} was not restarted"
    bad = {e.episode_id: (e.state, e.reason) for e in ends.values() if e.state != "stopped"}
    assert not bad, bad
    assert all(ends[i].steps == MAX_STEPS for i in ids), {i: ends[i].steps for i in ids}
    problems = ledger.problems({i: MAX_STEPS for i in ids})  # each step integrated, decided, planned once
    assert not problems, problems
    print(f"8 episodes x {MAX_STEPS} steps across 3 namespaces with 2 kills and a 4 s partition: {took:.1f} s")


def test_the_scorer_host_is_really_cut_off_while_partitioned(fleet):
    hosts, _ups, _driver, _data, _logs, _ = fleet
    probe = f"import socket; socket.create_connection(('{hosts.addr('h1')}', 7447), timeout=2).close()"
    ping = ["ip", "netns", "exec", hosts.ns("h3"), PY, "-c", probe]
    assert subprocess.run(ping, capture_output=True, timeout=10).returncode == 0
    hosts.partition("h3")
    try:
        assert subprocess.run(ping, capture_output=True, timeout=10).returncode != 0
    finally:
        hosts.heal("h3")

"""Smoke run of the compose fleet in containers (``make compose-smoke``).

Starts docker-compose.yml (with docker-compose.podman.yml) under podman: the Zenoh router, Redis, every service,
two scorer replicas and the gateway; waits until every container with a health check passes it (the compose
file's own check commands, run with ``podman healthcheck run``); asks one question over HTTP through the
gateway's published port; while the episode runs, kills one service container's process from the host (a
crash, not a ``stop``) and waits for the restart policy to bring it back; requires the episode to finish
(state ``stopped``) after that; tears the fleet down (``down -v``). Exit 0 only if all of it happened.

Needs ``scripts/containers.sh setup`` and ``build`` first (``make compose-smoke`` does both) and root (or sudo).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SUDO = [] if os.geteuid() == 0 else ["sudo"]
PROJECT = "eqa-smoke"
# The demo's scene and question (``eqa ask`` without arguments): a 100 m2 house, the box in the kitchen.
QUESTION = {
    "question": "Is the box in the kitchen closed?", "choices": ["Yes", "No"], "scene": "gen-00151",
    "strategy": "semantic", "stop_rule": "cp", "eps": 0.2, "seed": 0, "max_steps": 30,
}


class SmokeError(Exception):
    pass


def log(msg: str) -> None:
    print(f"[compose-smoke {time.strftime('%H:%M:%S')}] {msg}", flush=True)


def compose(*args: str, check: bool = True, timeout: float = 1800) -> subprocess.CompletedProcess[str]:
    cmd = ["bash", str(REPO / "scripts/containers.sh"), "compose", "-p", PROJECT, *args]
    out = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=timeout)
    if check and out.returncode != 0:
        raise SmokeError(f"{' '.join(cmd[2:])} failed ({out.returncode}):\n{out.stdout[-2000:]}\n{out.stderr[-3000:]}")
    return out


def podman(*args: str, check: bool = True, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    out = subprocess.run([*SUDO, "podman", *args], capture_output=True, text=True, timeout=timeout)
    if check and out.returncode != 0:
        raise SmokeError(f"podman {' '.join(args)} failed ({out.returncode}): {out.stderr[-1500:]}")
    return out


def containers() -> list[dict]:
    out = podman("ps", "-a", "--filter", f"label=io.podman.compose.project={PROJECT}", "--format", "json")
    return json.loads(out.stdout or "[]")


def inspect(name: str) -> dict:
    return json.loads(podman("inspect", name).stdout)[0]


def has_healthcheck(name: str) -> bool:
    return bool((inspect(name).get("Config") or {}).get("Healthcheck"))


def wait_healthy(names: list[str], deadline: float) -> dict[str, float]:
    """Run each container's own health check until it passes (podman runs checks on systemd timers; a host
    without systemd gets none, so they are run here, with the compose file's commands)."""
    t0 = time.monotonic()
    passed: dict[str, float] = {}
    last: dict[str, str] = {}
    while len(passed) < len(names):
        if time.monotonic() > deadline:
            missing = sorted(set(names) - set(passed))
            raise SmokeError(f"health checks not passing in time: {missing}; last output: "
                              f"{ {n: last.get(n, '')[-300:] for n in missing} }")
        for name in names:
            if name in passed:
                continue
            out = podman("healthcheck", "run", name, check=False, timeout=60)
            if out.returncode == 0:
                passed[name] = time.monotonic() - t0
                log(f"healthy: {name} after {passed[name]:.0f} s")
            else:
                last[name] = (out.stdout + out.stderr).strip()
        time.sleep(2)
    return passed


def main_pid(name: str) -> int:
    return int(inspect(name)["State"]["Pid"])


def http(method: str, url: str, body: dict | None = None) -> tuple[int, str]:
    """One request (standard library only, so the smoke needs no virtualenv): status and text."""
    data = json.dumps(body).encode() if body is not None else None
    req = urllib.request.Request(url, data=data, method=method, headers={"Content-Type": "application/json"})
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            return r.status, r.read().decode()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read().decode(errors="replace")
    except (urllib.error.URLError, OSError) as exc:
        return 0, str(exc)


def run(args: argparse.Namespace) -> dict:
    figures: dict = {}
    log("clean slate: down -v")
    compose("down", "-v", check=False, timeout=600)
    t0 = time.monotonic()
    compose("up", "-d", "--no-build", timeout=1800)
    figures["up_s"] = round(time.monotonic() - t0, 1)
    names = sorted(c["Names"][0] for c in containers())
    log(f"up -d in {figures['up_s']} s: {len(names)} containers: {', '.join(names)}")
    services = {n.removeprefix(f"{PROJECT}_").rsplit("_", 1)[0] for n in names}
    want = {"zenoh", "redis", "sim", "mapper", "vlm_scorer", "planner", "stopper", "gateway"}
    if not want <= services:
        raise SmokeError(f"services missing from the fleet: {sorted(want - services)}")
    scorers = [n for n in names if "_vlm_scorer_" in n]
    if len(scorers) < 2:
        raise SmokeError(f"expected 2 scorer replicas, got {scorers}")
    checked = [n for n in names if has_healthcheck(n)]
    health = wait_healthy(checked, time.monotonic() + args.health_timeout)
    figures["healthy_s"] = round(time.monotonic() - t0, 1)
    figures["health_checked"] = len(checked)
    log(f"all {len(checked)} health checks pass, {figures['healthy_s']} s after `up`")
    del health

    url = f"http://127.0.0.1:{args.port}"
    victim = f"{PROJECT}_{args.kill}_1"
    ready_deadline = time.monotonic() + args.health_timeout
    while True:  # the gateway's readiness: store, bus and every required service alive
        code, text = http("GET", f"{url}/v1/ready")
        if code == 200:
            break
        if time.monotonic() > ready_deadline:
            raise SmokeError(f"gateway /v1/ready not ready: {code} {text[:500]}")
        time.sleep(2)
    log(f"gateway ready, {time.monotonic() - t0:.0f} s after `up`")
    t_ask = time.monotonic()
    code, text = http("POST", f"{url}/v1/questions", QUESTION)
    if code >= 400 or code == 0:
        raise SmokeError(f"POST /v1/questions answered {code}: {text[:500]}")
    eid = json.loads(text)["episode_id"]
    log(f"episode {eid} submitted: {QUESTION['question']}")
    killed = None
    deadline = time.monotonic() + args.episode_timeout
    while True:
        code, text = http("GET", f"{url}/v1/episodes/{eid}")
        if code != 200:
            raise SmokeError(f"GET /v1/episodes/{eid} answered {code}: {text[:500]}")
        status = json.loads(text)
        if killed is None and status.get("step", -1) >= args.kill_after_step:
            pid = main_pid(victim)
            restarts = int(inspect(victim).get("RestartCount", 0))
            log(f"step {status['step']}: killing {victim} (host pid {pid}) with SIGKILL")
            subprocess.run([*SUDO, "kill", "-9", str(pid)], check=True)
            killed = (time.monotonic(), restarts, pid)
        if killed is not None and "restart_s" not in figures:
            st = inspect(victim)
            if int(st.get("RestartCount", 0)) > killed[1] and st["State"].get("Running"):
                figures["restart_s"] = round(time.monotonic() - killed[0], 1)
                log(f"{victim} restarted by its restart policy in {figures['restart_s']} s "
                    f"(restart count {st['RestartCount']}, new pid {st['State']['Pid']})")
        if status["state"] in ("stopped", "failed", "cancelled"):
            break
        if time.monotonic() > deadline:
            raise SmokeError(f"episode not finished in {args.episode_timeout} s: {status}")
        time.sleep(1)
    figures["episode_s"] = round(time.monotonic() - t_ask, 1)
    figures["episode"] = {k: status.get(k) for k in ("state", "steps", "answer", "answer_text", "stop_reason",
                                                      "correct")}
    log(f"episode finished: {figures['episode']} in {figures['episode_s']} s")
    if killed is None:
        raise SmokeError(f"the episode ended before step {args.kill_after_step}: nothing was killed")
    if "restart_s" not in figures:
        st = inspect(victim)
        if int(st.get("RestartCount", 0)) > killed[1] and st["State"].get("Running"):
            figures["restart_s"] = "before the episode ended"
    if "restart_s" not in figures:
        raise SmokeError(f"{victim} was not restarted: {st['State']}, restart count {st.get('RestartCount')}")
    if status["state"] != "stopped":
        raise SmokeError(f"the episode did not finish normally: {status['state']} ({status.get('stop_reason')})")
    return figures


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--port", type=int, default=18080,
                   help="the gateway's published port on 127.0.0.1 (docker-compose.podman.yml: 18080)")
    p.add_argument("--kill", default="mapper", help="service whose first container is killed mid-episode")
    p.add_argument("--kill-after-step", type=int, default=2, help="kill once the episode reached this step")
    p.add_argument("--health-timeout", type=float, default=900.0, help="seconds for all health checks to pass")
    p.add_argument("--episode-timeout", type=float, default=1200.0, help="seconds for the episode to finish")
    p.add_argument("--keep", action="store_true", help="leave the fleet running (no `down -v`) for a look")
    args = p.parse_args()
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # a killed run still tears the fleet down
    t0 = time.monotonic()
    ok = False
    try:
        figures = run(args)
        ok = True
    except SmokeError as exc:
        log(f"FAILED: {exc}")
        for c in containers():
            name = c["Names"][0]
            log(f"--- {name}: {c.get('State')} ({c.get('Status')}); last log lines:")
            print(podman("logs", "--tail", "15", name, check=False).stdout, flush=True)
    finally:
        if not args.keep:
            t_down = time.monotonic()
            compose("down", "-v", check=False, timeout=600)
            log(f"torn down in {time.monotonic() - t_down:.0f} s")
    if ok:
        figures["total_s"] = round(time.monotonic() - t0, 1)
        log(f"PASSED: {json.dumps(figures)}")
        return 0
    return 1


if __name__ == "__main__":
    sys.exit(main())

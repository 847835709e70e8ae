"""Load test of the gateway: N status requests per second for D seconds during a running episode, with a
history of stored episodes, then POSTs against a full queue.

Loopback only and bounded (rate x duration requests, at most --connections at once). Starts a private
redis-server on a free port (or uses --redis-url / --embedded), the real services (sim, mapper, vlm_scorer,
planner, stopper as processes, eqa.launcher.Fleet, 160x120 images) sharing that store, and the gateway as a
separate ``python -m gateway`` process joined to them; submits one long episode (budget --max-steps, stop
rule ``max_steps``) and, while it runs, sends open-loop GET /v1/episodes/{id} requests (the running episode
and random ones of --stored ended episodes written into the store first); prints latency percentiles, the
machine's load average, errors and how far the episode got meanwhile; then fills the robot's queue and times
POSTs that must be refused at once (429 + Retry-After); then cancels everything. Exit code 1 when any
request failed.

    python -m eqa_app.benches.gateway                  # 200 rps for 30 s
    python -m eqa_app.benches.gateway --rate 50 --duration 5

``--refusals``: the cost of refusals instead (no services, only the gateway process and its Redis): an
open-loop mix at --rate (default 500 req/s) of requests that must be refused: a valid token over its rate limit
(429), wrong tokens (401, then 429 once the address' failure bucket is empty), bodies over the cap (413,
answered from the headers, a new connection each) and submissions against a full queue (429); prints the
latency percentiles of each kind and the machine's load.

    python -m eqa_app.benches.gateway --refusals --rate 500 --duration 20
"""

from __future__ import annotations

import argparse
import asyncio
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np
from tqdm import tqdm

os.environ.setdefault("RERUN_TELEMETRY_ENABLED", "false")

from eqa.launcher import Fleet, LaunchError, free_port
from eqa.settings import Settings
from eqa_app.benches import harness

harness.use_test_support()
from support.fleet import GatewayProcess, fleet_settings, wait_for  # noqa: E402

TOKEN = "bench-token"


def start_redis(workdir: Path) -> tuple[subprocess.Popen[bytes], str]:
    exe = shutil.which("redis-server")
    if exe is None:
        raise SystemExit("redis-server not found: install it, or pass --redis-url or --embedded")
    port = free_port()
    proc = subprocess.Popen(
        [exe, "--port", str(port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no", "--dir", str(workdir)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return proc, f"redis://127.0.0.1:{port}/0"
        time.sleep(0.05)
    proc.kill()
    raise SystemExit("redis-server did not start")


async def _request(reader: asyncio.StreamReader, writer: asyncio.StreamWriter, raw: bytes) -> tuple[int, bytes]:
    """One HTTP/1.1 keep-alive GET on an open connection: (status, body). A minimal client, so that the load
    generator (not the gateway) is not what limits the rate on a small machine."""
    writer.write(raw)
    await writer.drain()
    head = await reader.readuntil(b"\r\n\r\n")
    status = int(head.split(b" ", 2)[1])
    length = 0
    for line in head.split(b"\r\n"):
        if line.lower().startswith(b"content-length:"):
            length = int(line.split(b":", 1)[1])
    body = await reader.readexactly(length) if length else b""
    return status, body


async def _paced(due: asyncio.Queue, workers: list[asyncio.Task], total: int, rate: float) -> None:
    """Put ``total`` requests on ``due`` at ``rate`` per second (open loop: the schedule does not wait for
    answers), then one stop marker per worker, and wait for the workers."""
    start = time.perf_counter()
    for i in range(total):
        t_due = start + i / rate
        delay = t_due - time.perf_counter()
        if delay > 0:
            await asyncio.sleep(delay)
        due.put_nowait((t_due, i))
    for _ in workers:
        due.put_nowait(None)
    await asyncio.gather(*workers)
    elapsed = time.perf_counter() - start
    print(f"sent {total} requests in {elapsed:.1f} s ({total / elapsed:.1f} req/s), {len(workers)} keep-alive "
          "connections")


async def load(
    port: int, paths: list[str], rate: float, duration: float, conns: int
) -> tuple[dict[str, list[float]], list[str], float]:
    """Open-loop load: request i (of path i mod len(paths)) is due at i/rate; ``conns`` keep-alive connections
    take due requests. Returns latencies per path kind (send to full response), errors and the worst lag."""
    latencies: dict[str, list[float]] = {}
    errors: list[str] = []
    total = int(rate * duration)
    raws = [
        (p, (f"GET {p} HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer {TOKEN}\r\n\r\n").encode())
        for p in paths
    ]
    due: asyncio.Queue[tuple[float, int] | None] = asyncio.Queue()
    lag = 0.0

    async def worker() -> None:
        nonlocal lag
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        try:
            while (item := await due.get()) is not None:
                t_due, i = item
                path, raw = raws[i % len(raws)]
                kind = "running episode" if path == raws[0][0] else "stored episode"
                t0 = time.perf_counter()
                lag = max(lag, t0 - t_due)
                try:
                    status, body = await asyncio.wait_for(_request(reader, writer, raw), timeout=10)
                except (OSError, asyncio.IncompleteReadError, TimeoutError, ValueError) as exc:
                    errors.append(f"{type(exc).__name__}: {exc}")
                    writer.close()
                    reader, writer = await asyncio.open_connection("127.0.0.1", port)
                    continue
                latencies.setdefault(kind, []).append(time.perf_counter() - t0)
                if status != 200:
                    errors.append(f"HTTP {status} for {path}: {body[:100]!r}")
        finally:
            writer.close()

    await _paced(due, [asyncio.create_task(worker()) for _ in range(conns)], total, rate)
    return latencies, errors, lag


async def refusal_load(port: int, mix: list[tuple[str, bytes, bool, set[int]]], rate: float, duration: float,
                       conns: int) -> tuple[dict[str, list[float]], list[str], float]:
    """Open-loop load of ``mix`` entries ``(kind, raw request, on a new connection, statuses wanted)``, request
    i being entry i mod len(mix), due at i/rate. Returns latencies per kind, errors (other statuses) and the
    worst lag behind the schedule."""
    latencies: dict[str, list[float]] = {}
    errors: list[str] = []
    due: asyncio.Queue[tuple[float, int] | None] = asyncio.Queue()
    lag = 0.0

    async def worker() -> None:
        nonlocal lag
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        try:
            while (item := await due.get()) is not None:
                t_due, i = item
                kind, raw, fresh, wanted = mix[i % len(mix)]
                t0 = time.perf_counter()
                lag = max(lag, t0 - t_due)
                try:
                    if fresh:
                        r2, w2 = await asyncio.open_connection("127.0.0.1", port)
                        try:
                            status, body = await asyncio.wait_for(_request(r2, w2, raw), timeout=10)
                        finally:
                            w2.close()
                    else:
                        status, body = await asyncio.wait_for(_request(reader, writer, raw), timeout=10)
                except (OSError, asyncio.IncompleteReadError, TimeoutError, ValueError) as exc:
                    errors.append(f"{kind}: {type(exc).__name__}: {exc}")
                    writer.close()
                    reader, writer = await asyncio.open_connection("127.0.0.1", port)
                    continue
                latencies.setdefault(f"{kind} -> {status}", []).append(time.perf_counter() - t0)
                if status not in wanted:
                    errors.append(f"{kind}: HTTP {status}: {body[:100]!r}")
        finally:
            writer.close()

    await _paced(due, [asyncio.create_task(worker()) for _ in range(conns)], int(rate * duration), rate)
    return latencies, errors, lag


def refusals(args: argparse.Namespace) -> int:
    """The ``--refusals`` bench (see the module docstring)."""
    import json

    print(f"machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f} (1 min) at the start")
    tmp = Path(tempfile.mkdtemp(prefix="bench-refusals-"))
    redis_proc, redis_url = (None, args.redis_url) if args.redis_url else start_redis(tmp)
    flood, submitter = TOKEN, TOKEN + "-submitter"
    queue_max = 5
    settings = fleet_settings(tmp / "var", redis_url, log_level="WARNING").model_copy(update={
        "api_tokens": [flood, submitter], "rate_limit_per_s": 5.0, "auth_failures_per_min": 20.0,
        "queue_max_per_robot": queue_max, "queue_max_per_token": 100, "episode_timeout_s": 3600.0,
        "zenoh_listen": [f"tcp/127.0.0.1:{free_port()}"], "zenoh_connect": [],
    })
    question = json.dumps({"question": "Is the oven on?", "scene": "gen-00001", "max_steps": 5,
                           "record": False}).encode()

    def req(method: str, path: str, token: str, body: bytes = b"", length: int | None = None) -> bytes:
        head = f"{method} {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer {token}\r\n"
        if method == "POST":
            head += f"Content-Type: application/json\r\nContent-Length: {len(body) if length is None else length}\r\n"
        return (head + "\r\n").encode() + body

    # per 10 requests: 4 over the rate limit, 3 wrong tokens, 2 bodies over the cap, 1 against a full queue
    mix = [
        *[("valid token over its rate limit", req("GET", "/v1/episodes?limit=1", flood), False, {200, 429})] * 4,
        *[("wrong token", req("GET", "/v1/episodes?limit=1", "wrong-token"), False, {401, 429})] * 3,
        *[("body over the cap", req("POST", "/v1/questions", flood, length=64 * 1024 * 1024), True, {413})] * 2,
        ("submission against a full queue", req("POST", "/v1/questions", submitter, question), False, {429}),
    ]
    try:
        with GatewayProcess(settings, log_path=tmp / "gateway.log") as gw, httpx.Client(
            base_url=gw.url, headers={"Authorization": f"Bearer {submitter}"}, timeout=30
        ) as c:
            for _ in range(queue_max + 1):  # one running (no services: it stays so) + a full queue
                r = c.post("/v1/questions", content=question, headers={"Content-Type": "application/json"})
                if r.status_code != 202:
                    print(f"error: filling the queue: {r.status_code} {r.text[:200]}", file=sys.stderr)
                    return 1
                time.sleep(1.0 / 4)  # within the rate limit
            time.sleep(1.5)  # the submitter's rate bucket refills
            load_before = os.getloadavg()[0]
            cpu0 = _cpu_s(gw.proc.pid)  # type: ignore[union-attr]
            lat, errors, lag = asyncio.run(refusal_load(gw.port, mix, args.rate, args.duration, args.connections))
            cpu_s = _cpu_s(gw.proc.pid) - cpu0  # type: ignore[union-attr]
            load_after = os.getloadavg()[0]
    finally:
        if redis_proc is not None:
            redis_proc.terminate()
            redis_proc.wait(timeout=10)
    print(f"machine load average (1 min): {load_before:.2f} before, {load_after:.2f} after ({os.cpu_count()} cores, "
          "shared with whatever else runs)")
    all_ms = np.asarray([x for v in lat.values() for x in v]) * 1000
    for kind, values in [("all", list(all_ms / 1000)), *sorted(lat.items())]:
        ms = np.asarray(values) * 1000
        print(f"{kind}: p50 {np.percentile(ms, 50):.2f}  p90 {np.percentile(ms, 90):.2f}  p99 "
              f"{np.percentile(ms, 99):.2f}  max {ms.max():.2f} ms (n={len(ms)})")
    n = sum(len(v) for v in lat.values())
    print(f"gateway process CPU time: {cpu_s:.2f} s for {n} requests = {cpu_s / max(1, n) * 1000:.2f} ms per request "
          "(user + system; what a request costs the server whatever the machine's load)")
    print(f"worst lag of a request behind its schedule: {lag * 1000:.1f} ms")
    print(f"errors: {len(errors)}" + (f" (first: {errors[0]})" if errors else ""))
    return 1 if errors else 0


def _cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process so far (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def seed_history(settings: Settings, n: int) -> list[str]:
    """``n`` ended episodes of the bench's token written into the gateway's store (its record and index
    layout, :meth:`gateway.manager.EpisodeManager.store_record`), as a long-running gateway would hold them."""
    from eqa.messages import EpisodeStart, EpisodeStatus, Question, new_id
    from eqa.store import open_store
    from gateway.auth import tenant_of
    from gateway.manager import EpisodeManager, Record

    ids = []
    with open_store(settings) as store:
        manager = EpisodeManager(settings, store, bus=None)  # type: ignore[arg-type]  # no bus needed to store
        now = time.time() - n
        for i in tqdm(range(n), desc="stored episodes", unit="ep", mininterval=2.0):
            eid = new_id("ep")
            q = Question(text=f"Where is object {i}?", choices=["bedroom", "hallway"], scene="gen-00002")
            start = EpisodeStart(episode_id=eid, robot="robot0", question=q, max_steps=30)
            status = EpisodeStatus(episode_id=eid, robot="robot0", state="stopped", question=q, strategy="semantic",
                                   stop=start.stop, max_steps=30, steps=30, answer="A", stop_reason="step limit",
                                   created_at=now + i, updated_at=now + i + 1)
            manager.store_record(Record(status=status, start=start, owner=tenant_of(TOKEN)))
            ids.append(eid)
    return ids


def post_with_full_queue(c: httpx.Client, body: dict, queue_max: int, n: int) -> tuple[list[float], list[str]]:
    """Fill the robot's queue (``queue_max`` episodes behind the running one), then time ``n`` more POSTs:
    each must be refused at once with 429 and a Retry-After."""
    queued = []
    for _ in range(queue_max):
        r = c.post("/v1/questions", json=body)
        if r.status_code != 202:
            return [], [f"filling the queue: HTTP {r.status_code} {r.text[:200]}"]
        queued.append(r.json()["episode_id"])
    times, errors = [], []
    for _ in range(n):
        t0 = time.perf_counter()
        r = c.post("/v1/questions", json=body)
        times.append(time.perf_counter() - t0)
        if r.status_code != 429 or int(r.headers.get("retry-after", "0")) < 1:
            errors.append(f"full queue: HTTP {r.status_code} {r.text[:200]}")
    for eid in queued:
        c.delete(f"/v1/episodes/{eid}")
    return times, errors


def main(argv: list[str] | None = None) -> int:
    ap = harness.parser(__doc__)
    ap.add_argument("--rate", type=float, default=200.0, help="requests per second (default 200)")
    ap.add_argument("--duration", type=float, default=30.0, help="seconds of load (default 30)")
    ap.add_argument("--connections", type=int, default=16, help="keep-alive connections = max in flight (16)")
    ap.add_argument("--scene", default="gen-00002", help="scene of the episode (default gen-00002: 300+ steps)")
    ap.add_argument("--max-steps", type=int, default=10_000, help="step budget of the episode (default 10000)")
    ap.add_argument("--scorers", type=int, default=1, help="scorer replicas of the fleet (default 1)")
    ap.add_argument("--redis-url", default=None, help="use this Redis instead of a private redis-server")
    ap.add_argument("--embedded", action="store_true", help="use the embedded SQLite store instead of Redis")
    ap.add_argument("--stored", type=int, default=10_000, help="ended episodes in the store during the load (10000)")
    ap.add_argument("--queue-max", type=int, default=20, help="EQA_QUEUE_MAX_PER_ROBOT for the full-queue POSTs (20)")
    ap.add_argument("--refusals", action="store_true",
                    help="measure refusals (429/401/413) instead: gateway and Redis only, default 500 req/s")
    args = ap.parse_args(argv)
    if args.refusals:
        if "--rate" not in (argv if argv is not None else sys.argv[1:]):
            args.rate = 500.0
        if not (0 < args.rate <= 5000 and 0 < args.duration <= 600 and 1 <= args.connections <= 256):
            print("error: need 0 < rate <= 5000, 0 < duration <= 600, 1 <= connections <= 256", file=sys.stderr)
            return 2
        return refusals(args)
    if not (0 < args.rate <= 5000 and 0 < args.duration <= 600 and 1 <= args.connections <= 256):
        print("error: need 0 < rate <= 5000, 0 < duration <= 600, 1 <= connections <= 256", file=sys.stderr)
        return 2
    if not (1 <= args.max_steps <= 10_000 and 1 <= args.scorers <= 8):
        print("error: need 1 <= max-steps <= 10000, 1 <= scorers <= 8", file=sys.stderr)
        return 2
    if not (0 <= args.stored <= 200_000 and 1 <= args.queue_max <= 1000):
        print("error: need 0 <= stored <= 200000, 1 <= queue-max <= 1000", file=sys.stderr)
        return 2
    print(f"machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f} (1 min) at the start")
    tmp = Path(tempfile.mkdtemp(prefix="bench-gateway-"))
    redis_proc = None
    redis_url = args.redis_url
    if not args.embedded and redis_url is None:
        redis_proc, redis_url = start_redis(tmp)
    base = fleet_settings(
        tmp / "var",
        None if args.embedded else redis_url,
        log_level="WARNING",
        episode_timeout_s=120.0,
    )
    try:
        with Fleet(base, scorers=args.scorers) as fleet:
            gw_settings = fleet.client_settings().model_copy(
                update={"api_tokens": [TOKEN], "rate_limit_per_s": max(1000.0, 4 * args.rate),
                        "queue_max_per_robot": args.queue_max, "queue_max_per_token": args.queue_max + 10,
                        "episode_retention_count": max(50_000, 2 * args.stored)}
            )
            stored = seed_history(gw_settings, args.stored) if args.stored else []
            with (
                GatewayProcess(gw_settings, log_path=tmp / "gateway.log") as gw,
                httpx.Client(base_url=gw.url, headers={"Authorization": f"Bearer {TOKEN}"}, timeout=30) as c,
            ):
                if not wait_for(lambda: c.get("/v1/ready").status_code == 200, 60):
                    print(f"error: gateway not ready: {c.get('/v1/ready').text}", file=sys.stderr)
                    return 1
                r = c.post(
                    "/v1/questions",
                    json={
                        "question": "Where is the black suitcase?",
                        "choices": ["bedroom", "hallway", "storage room", "living room"],
                        "scene": args.scene,
                        "max_steps": args.max_steps,
                        "stop_rule": "max_steps",
                        "record": False,
                    },
                )
                if r.status_code != 202:
                    print(f"error: submit failed: {r.status_code} {r.text[:300]}", file=sys.stderr)
                    return 1
                eid = r.json()["episode_id"]
                # the first step includes generating/loading the scene: start the load once the robot moves
                if not wait_for(lambda: c.get(f"/v1/episodes/{eid}").json()["step"] >= 1, 300):
                    print(f"error: episode did not get going: {c.get(f'/v1/episodes/{eid}').text}", file=sys.stderr)
                    return 1
                before = c.get(f"/v1/episodes/{eid}").json()
                print(
                    f"episode {eid} running on the real fleet ({args.scene}, step {before['step']}); "
                    f"{args.rate:g} req/s for {args.duration:g} s ({'embedded store' if args.embedded else 'redis'})"
                )
                rng = np.random.default_rng(0)
                # every other request: the running episode (served from memory), else a random stored one
                paths = [p for k in rng.integers(0, len(stored), 3000)
                         for p in (f"/v1/episodes/{eid}", f"/v1/episodes/{stored[int(k)]}")] if stored else []
                load_before = os.getloadavg()[0]
                lat, errors, lag = asyncio.run(
                    load(gw.port, paths or [f"/v1/episodes/{eid}"], args.rate, args.duration, args.connections)
                )
                load_after = os.getloadavg()[0]
                st = c.get(f"/v1/episodes/{eid}").json()
                t0 = time.perf_counter()
                listed = c.get("/v1/episodes", params={"limit": 10})
                list_ms = (time.perf_counter() - t0) * 1000
                if listed.status_code != 200 or len(listed.json()["episodes"]) != 10:
                    errors.append(f"list: HTTP {listed.status_code}")
                full_times, full_errors = post_with_full_queue(
                    c, {"question": "Is the oven on?", "scene": args.scene, "max_steps": 5, "record": False},
                    args.queue_max, 50,
                )
                errors += full_errors
                if st["state"] == "running":
                    c.delete(f"/v1/episodes/{eid}")
    except LaunchError as exc:
        print(f"error: the fleet did not start: {exc}", file=sys.stderr)
        return 1
    finally:
        if redis_proc is not None:
            redis_proc.terminate()
            redis_proc.wait(timeout=10)
    print(f"machine load average (1 min): {load_before:.2f} before the load, {load_after:.2f} after "
          f"({os.cpu_count()} cores; the fleet and the gateway run on them too)")
    print(f"stored episodes: {len(stored)} ended + the running one")
    for kind, values in [("all", [x for v in lat.values() for x in v]), *sorted(lat.items())]:
        if not values:
            continue
        ms = np.asarray(values) * 1000
        print(
            f"status latency ms ({kind}): p50 {np.percentile(ms, 50):.2f}  p90 {np.percentile(ms, 90):.2f}  "
            f"p99 {np.percentile(ms, 99):.2f}  max {ms.max():.2f}  (n={len(ms)})"
        )
    print(f"GET /v1/episodes?limit=10 with {len(stored)} stored: {list_ms:.1f} ms")
    if full_times:
        ms = np.asarray(full_times) * 1000
        print(f"POST with a full queue ({args.queue_max} queued): 429 + Retry-After, p50 {np.percentile(ms, 50):.2f} "
              f"p99 {np.percentile(ms, 99):.2f} max {ms.max():.2f} ms (n={len(ms)})")
    print(f"worst lag of a request behind its schedule: {lag * 1000:.1f} ms")
    print(
        f"episode during the load: steps {before['step']} -> {st['step']} "
        f"({(st['step'] - before['step']) / args.duration:.2f} steps/s), state at the end: {st['state']}"
        + ("" if st["state"] == "running" else f" ({st['stop_reason']}; the load ran partly after its end)")
    )
    print(f"errors: {len(errors)}" + (f" (first: {errors[0]})" if errors else ""))
    return 1 if errors else 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Load test of the gateway: N status requests per second for D seconds during a running episode.

Loopback only and bounded (rate x duration requests, at most --connections at once). Starts a private
redis-server on a free port (or uses --redis-url / --embedded), the real services (sim, mapper, vlm_scorer,
planner, stopper as processes, eqa.launcher.Fleet, 160x120 images) sharing that store, and the gateway as a
separate ``python -m gateway`` process joined to them; submits one long episode (budget --max-steps, stop
rule ``max_steps``) and, while it runs, sends open-loop GET /v1/episodes/{id} requests; prints latency
percentiles, errors and how far the episode got meanwhile, then cancels it. Exit code 1 when any request
failed.

    python bench/bench_gateway.py                  # 200 rps for 30 s
    python bench/bench_gateway.py --rate 50 --duration 5
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

os.environ.setdefault("RERUN_TELEMETRY_ENABLED", "false")

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # test support: tests/fleet_support.py

from fleet_support import GatewayProcess, fleet_settings, wait_for

from eqa.launcher import Fleet, LaunchError, free_port

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


async def load(port: int, path: str, rate: float, duration: float, conns: int) -> tuple[list[float], list[str], float]:
    """Open-loop load: request i is due at i/rate; ``conns`` keep-alive connections take due requests.
    Returns latencies (send to full response), errors and the worst lag behind the schedule."""
    latencies: list[float] = []
    errors: list[str] = []
    total = int(rate * duration)
    raw = (f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer {TOKEN}\r\n\r\n").encode()
    due: asyncio.Queue[float | None] = asyncio.Queue()
    lag = 0.0

    async def worker() -> None:
        nonlocal lag
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        try:
            while (t_due := await due.get()) is not None:
                t0 = time.perf_counter()
                lag = max(lag, t0 - t_due)
                try:
                    status, body = await asyncio.wait_for(_request(reader, writer, raw), timeout=10)
                except (OSError, asyncio.IncompleteReadError, TimeoutError, ValueError) as exc:
                    errors.append(f"{type(exc).__name__}: {exc}")
                    writer.close()
                    reader, writer = await asyncio.open_connection("127.0.0.1", port)
                    continue
                latencies.append(time.perf_counter() - t0)
                if status != 200:
                    errors.append(f"HTTP {status}: {body[:100]!r}")
        finally:
            writer.close()

    workers = [asyncio.create_task(worker()) for _ in range(conns)]
    start = time.perf_counter()
    for i in range(total):
        t_due = start + i / rate
        delay = t_due - time.perf_counter()
        if delay > 0:
            await asyncio.sleep(delay)
        due.put_nowait(t_due)
    for _ in workers:
        due.put_nowait(None)
    await asyncio.gather(*workers)
    elapsed = time.perf_counter() - start
    print(f"sent {total} requests in {elapsed:.1f} s ({total / elapsed:.1f} req/s), {conns} keep-alive connections")
    return latencies, errors, lag


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rate", type=float, default=200.0, help="requests per second (default 200)")
    ap.add_argument("--duration", type=float, default=30.0, help="seconds of load (default 30)")
    ap.add_argument("--connections", type=int, default=16, help="keep-alive connections = max in flight (16)")
    ap.add_argument("--scene", default="gen-00002", help="scene of the episode (default gen-00002: 300+ steps)")
    ap.add_argument("--max-steps", type=int, default=10_000, help="step budget of the episode (default 10000)")
    ap.add_argument("--scorers", type=int, default=1, help="scorer replicas of the fleet (default 1)")
    ap.add_argument("--redis-url", default=None, help="use this Redis instead of a private redis-server")
    ap.add_argument("--embedded", action="store_true", help="use the embedded SQLite store instead of Redis")
    args = ap.parse_args(argv)
    if not (0 < args.rate <= 5000 and 0 < args.duration <= 600 and 1 <= args.connections <= 256):
        print("error: need 0 < rate <= 5000, 0 < duration <= 600, 1 <= connections <= 256", file=sys.stderr)
        return 2
    if not (1 <= args.max_steps <= 10_000 and 1 <= args.scorers <= 8):
        print("error: need 1 <= max-steps <= 10000, 1 <= scorers <= 8", file=sys.stderr)
        return 2
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
                update={"api_tokens": [TOKEN], "rate_limit_per_s": max(1000.0, 4 * args.rate)}
            )
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
                lat, errors, lag = asyncio.run(
                    load(gw.port, f"/v1/episodes/{eid}", args.rate, args.duration, args.connections)
                )
                st = c.get(f"/v1/episodes/{eid}").json()
                if st["state"] == "running":
                    c.delete(f"/v1/episodes/{eid}")
    except LaunchError as exc:
        print(f"error: the fleet did not start: {exc}", file=sys.stderr)
        return 1
    finally:
        if redis_proc is not None:
            redis_proc.terminate()
            redis_proc.wait(timeout=10)
    if lat:
        ms = np.asarray(lat) * 1000
        print(
            f"latency ms: p50 {np.percentile(ms, 50):.2f}  p90 {np.percentile(ms, 90):.2f}  "
            f"p99 {np.percentile(ms, 99):.2f}  max {ms.max():.2f}  (n={len(ms)})"
        )
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

"""Load test of the gateway: N status requests per second for D seconds during a running episode.

Loopback only and bounded (rate x duration requests, at most --connections at once). Starts a private
redis-server on a free port (or uses --redis-url / --embedded), a scripted fleet that keeps one episode
running over real Zenoh (gateway.scripted_fleet: real messages, one step every --step-s seconds), and the
gateway as a separate ``python -m gateway`` process; then sends open-loop GET /v1/episodes/{id} requests
and prints latency percentiles and errors. Exit code 1 when any request failed.

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
import threading
import time
from pathlib import Path

import httpx
import numpy as np

os.environ.setdefault("RERUN_TELEMETRY_ENABLED", "false")

from eqa.settings import Settings
from gateway.harness import GatewayProcess, free_port
from gateway.scripted_fleet import FleetScript, ScriptedFleet

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
    ap.add_argument("--step-s", type=float, default=0.5, help="seconds per scripted episode step (default 0.5)")
    ap.add_argument("--redis-url", default=None, help="use this Redis instead of a private redis-server")
    ap.add_argument("--embedded", action="store_true", help="use the embedded SQLite store instead of Redis")
    args = ap.parse_args(argv)
    if not (0 < args.rate <= 5000 and 0 < args.duration <= 600 and 1 <= args.connections <= 256):
        print("error: need 0 < rate <= 5000, 0 < duration <= 600, 1 <= connections <= 256", file=sys.stderr)
        return 2
    tmp = Path(tempfile.mkdtemp(prefix="bench-gateway-"))
    redis_proc = None
    redis_url = args.redis_url
    if not args.embedded and redis_url is None:
        redis_proc, redis_url = start_redis(tmp)
    hub_port = free_port()
    base = Settings(
        data_dir=tmp / "var",
        zenoh_mode="peer",
        zenoh_multicast=False,
        record=False,
        redis_url=None if args.embedded else redis_url,
        api_tokens=[TOKEN],
        rate_limit_per_s=max(1000.0, 4 * args.rate),
        episode_timeout_s=max(60.0, 10 * args.step_s),
        log_level="WARNING",
    )
    hub = base.model_copy(update={"zenoh_listen": [f"tcp/127.0.0.1:{hub_port}"], "zenoh_connect": []})
    peer = base.model_copy(update={"zenoh_listen": ["tcp/127.0.0.1:0"], "zenoh_connect": [f"tcp/127.0.0.1:{hub_port}"]})
    gate = threading.Event()
    try:
        with (
            ScriptedFleet(hub, FleetScript(step_delay_s=args.step_s, end_gate=gate, image_hw=(120, 160))),
            GatewayProcess(peer, log_path=tmp / "gateway.log") as gw,
            httpx.Client(base_url=gw.url, headers={"Authorization": f"Bearer {TOKEN}"}, timeout=10) as c,
        ):
            deadline = time.monotonic() + 30
            while c.get("/v1/ready").status_code != 200:
                if time.monotonic() > deadline:
                    print(f"error: gateway not ready: {c.get('/v1/ready').text}", file=sys.stderr)
                    return 1
                time.sleep(0.1)
            eid = c.post(
                "/v1/questions",
                json={
                    "question": "Where is the black suitcase?",
                    "choices": [f"room {i}" for i in range(26)],
                    "scene": "bench",
                    "max_steps": 10_000,
                },
            ).json()["episode_id"]
            print(
                f"episode {eid} running; {args.rate:g} req/s for {args.duration:g} s "
                f"({'embedded store' if args.embedded else 'redis'})"
            )
            lat, errors, lag = asyncio.run(
                load(gw.port, f"/v1/episodes/{eid}", args.rate, args.duration, args.connections)
            )
            st = c.get(f"/v1/episodes/{eid}").json()
            gate.set()
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
    print(f"episode state during the load: {st['state']}, step {st['step']}")
    print(f"errors: {len(errors)}" + (f" (first: {errors[0]})" if errors else ""))
    return 1 if errors else 0


if __name__ == "__main__":
    raise SystemExit(main())

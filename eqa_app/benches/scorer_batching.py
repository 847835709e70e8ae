"""Dynamic batching in one scorer replica: what a saturated replica serves per second, batching off vs on.

Two replica processes of the tiny random Qwen2-VL (built offline; ``python -m services.vlm_scorer``, one torch
thread each) run side by side: ``off`` with ``EQA_SCORER_BATCH_MAX=1``, ``on`` with batching (``--batch-max``,
``--window-ms``). For each robot count N, N robots each send their steps one after the other (a robot waits for
its step's scores before sending the next, as a mapper does), every robot with its own question. The same
requests go to ``off`` and to ``on`` in alternating rounds (only one replica works at a time; a load drift hits
both alike).

The robots live in ``--clients`` client processes (threads in each), not in this one: a client only sends
bytes encoded before the run and keeps the reply bytes, decoding them after it, so the replica, not the
client, is the bottleneck (the client processes' CPU per step is printed to show it).

Printed per robot count and mode:

* steps/s: steps answered per second of wall time, all robots together (what one replica serves on this
  machine, shared with the clients and whatever else runs: see the load average);
* p50 / p95 latency of a step (send to reply, per request) in ms;
* replica CPU ms per step: user + system time of the replica process (``/proc``, 10 ms ticks) over all rounds
  per step served; 1000 / it is the steps per second one core of a saturated replica sustains, the figure that
  sizes a replica independent of what else shares the machine;
* client CPU ms per step, all client processes together;
* whether every request got the same values from both replicas, byte for byte, and (``--reference``) the
  same as a recorded run of an earlier tree (``bench/results/perf/scorer_values_*.json``, written by
  ``--record``).

The tiny model is not a real VLM: the figures say what merging the steps of several robots saves in a
replica's per-call work on this CPU, not what a GPU serving a real model would gain.

    python -m eqa_app.benches.scorer_batching [--robots 1 2 4 8 16] [--steps 6] [--rounds 4] [--clients 2]
        [--reference bench/results/perf/scorer_values_d726069.json]
    python -m eqa_app.benches.scorer_batching --record FILE --robots 16 --steps 8   # values of this tree, one by one
"""

from __future__ import annotations

import contextlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
os.environ.setdefault("RERUN_TELEMETRY_ENABLED", "false")

from eqa_app.benches import harness

REPO = harness.REPO
harness.use_test_support()

from eqa import keys  # noqa: E402
from eqa.bus import Bus  # noqa: E402
from eqa.launcher import free_port  # noqa: E402
from eqa.messages import ErrorReply, Question, ScoreRequest, ScoreResult, decode, encode  # noqa: E402
from eqa.scorer_client import ScorerClient  # noqa: E402
from eqa.settings import Settings  # noqa: E402
from eqa_app.benches.fleet_scale import cpu_seconds  # noqa: E402
from eqa_app.stats import percentile as pct  # noqa: E402

QUESTIONS = [
    ("Is the stove in the kitchen turned off?", ["Yes", "No"]),
    ("What color is the sofa in the living room?", ["Blue", "Red", "Green", "White"]),
    ("Where did I leave the black suitcase?", ["bedroom", "hallway", "storage room", "living room"]),
    ("How many chairs are around the dining table?", ["two", "four", "six", "eight"]),
    ("Is the lamp on the nightstand switched on?", ["Yes", "No"]),
    ("Which room has the potted plant?", ["kitchen", "bathroom", "office", "bedroom"]),
    ("Is there a towel hanging in the bathroom?", ["Yes", "No"]),
    ("What is on the kitchen counter next to the sink?", ["a kettle", "a toaster", "a plant", "nothing"]),
]
MODES = ("off", "on")


def _robot_requests(robot: int, steps: int, h: int, w: int) -> list[ScoreRequest]:
    """Robot ``robot``'s steps: its own question and episode, a frame per step (the same in every run)."""
    from support.scorer import frame_request

    text, choices = QUESTIONS[robot % len(QUESTIONS)]
    q = Question(id=f"q{robot}", text=text, choices=choices, scene="s0")
    return [frame_request(step=s, h=h, w=w, episode=f"ep{robot}", question=q,
                          seed=robot).model_copy(update={"request_id": f"r{robot}-s{s}"}) for s in range(steps)]


def _values(res: ScoreResult) -> list[Any]:
    return [list(res.answer_probs), list(res.lsv), res.gsv, res.relevance]


# ---- client processes ------------------------------------------------------------------------------------
def client_main(hub_port: int, data_dir: str, name: str) -> int:
    """A client process: reads one JSON command per line on stdin, runs it, writes one JSON line on stdout.

    ``{"prepare": {"robots": [...], "steps": n, "size": [h, w]}}`` encodes those robots' requests (answer
    ``{"ready": true}``); ``{"run": "b-on"}`` sends them to that replica, each robot a thread sending its steps
    one after the other, and answers with each request's latency, values (decoded after the run), the run's
    monotonic start and end, and the process's CPU seconds during it."""
    settings = Settings(data_dir=Path(data_dir), zenoh_listen=["tcp/127.0.0.1:0"],
                        zenoh_connect=[f"tcp/127.0.0.1:{hub_port}"], record=False, log_level="WARNING")
    payloads: list[list[tuple[str, bytes]]] = []
    with Bus(settings, "gateway", name) as bus:
        if not ScorerClient(bus, settings).wait_for_replicas(2, timeout=120):
            print(json.dumps({"error": "replicas not seen"}), flush=True)
            return 1
        print(json.dumps({"ready": True}), flush=True)
        for line in sys.stdin:
            cmd = json.loads(line)
            if "prepare" in cmd:
                p = cmd["prepare"]
                h, w = p["size"]
                payloads = [[(r.request_id, encode(r)) for r in _robot_requests(robot, p["steps"], h, w)]
                            for robot in p["robots"]]
                print(json.dumps({"ready": True}), flush=True)
            elif "run" in cmd:
                print(json.dumps(_client_run(bus, cmd["run"], payloads)), flush=True)
            else:
                return 0
    return 0


def _client_run(bus: Bus, replica: str, payloads: list[list[tuple[str, bytes]]]) -> dict[str, Any]:
    key = keys.scorer_replica(replica)
    latencies: list[float] = []
    raw: dict[str, bytes | None] = {}
    lock = threading.Lock()

    def robot(reqs: list[tuple[str, bytes]]) -> None:
        for rid, payload in reqs:
            t0 = time.perf_counter()
            got = None
            for reply in bus.session.get(key, payload=payload, timeout=120):
                if reply.ok is not None:
                    got = reply.ok.payload.to_bytes()
            dt = (time.perf_counter() - t0) * 1e3
            with lock:
                latencies.append(dt)
                raw[rid] = got

    threads = [threading.Thread(target=robot, args=(reqs,)) for reqs in payloads]
    cpu0, t0 = time.process_time(), time.monotonic()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    t1, cpu1 = time.monotonic(), time.process_time()
    values: dict[str, Any] = {}
    for rid, data in raw.items():
        msg = decode(data) if data is not None else None
        if isinstance(msg, ScoreResult):
            values[rid] = _values(msg)
        else:
            values[rid] = {"error": msg.reason if isinstance(msg, ErrorReply) else "no reply"}
    return {"latencies": latencies, "values": values, "start": t0, "end": t1, "cpu": cpu1 - cpu0}


class Clients:
    """The client processes, each holding a share of the robots."""

    def __init__(self, n: int, hub_port: int, data_dir: Path) -> None:
        self.procs = [subprocess.Popen(harness.command("scorer_batching", "--client", str(hub_port),
                                                       str(data_dir / f"c{i}"), f"c{i}"),
                                       cwd=REPO, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                                       env={**harness.environment(), "EQA_LOG_LEVEL": "WARNING"})
                      for i in range(n)]
        for p in self.procs:
            self._read(p)

    @staticmethod
    def _read(p: subprocess.Popen) -> dict[str, Any]:
        assert p.stdout is not None
        line = p.stdout.readline()
        if not line:
            raise RuntimeError("a client process ended")
        out = json.loads(line)
        if "error" in out:
            raise RuntimeError(f"client: {out['error']}")
        return out

    def _send(self, p: subprocess.Popen, cmd: dict[str, Any]) -> None:
        assert p.stdin is not None
        p.stdin.write(json.dumps(cmd) + "\n")
        p.stdin.flush()

    def prepare(self, robots: int, steps: int, size: tuple[int, int]) -> None:
        for i, p in enumerate(self.procs):
            self._send(p, {"prepare": {"robots": list(range(i, robots, len(self.procs))), "steps": steps,
                                       "size": list(size)}})
        for p in self.procs:
            self._read(p)

    def run(self, replica: str) -> list[dict[str, Any]]:
        for p in self.procs:
            self._send(p, {"run": replica})
        return [self._read(p) for p in self.procs]

    def close(self) -> None:
        for p in self.procs:
            with contextlib.suppress(OSError):  # a client that already ended
                self._send(p, {"stop": True})
        for p in self.procs:
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()


# ---- one tree's values, request by request ----------------------------------------------------------------
def record(path: Path, robots: int, steps: int, h: int, w: int) -> int:
    """Score the bench's requests one by one in this process (hf backend, tiny model, one torch thread) and
    write their values: the reference a later tree's runs are compared with (``--reference``)."""
    import torch

    from services.vlm_scorer.backends.hf import HFBackend
    from services.vlm_scorer.tiny import build_tiny_qwen2vl

    torch.set_num_threads(1)
    backend = HFBackend(build_tiny_qwen2vl(Path(tempfile.mkdtemp(prefix="bench-scorer-record-")) / "m"))
    values = {}
    for robot in range(robots):
        for req in _robot_requests(robot, steps, h, w):
            s = backend.score(req)
            values[req.request_id] = [list(s.answer_probs), list(s.lsv), s.gsv, s.relevance]
    rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True,
                         check=False).stdout.strip()
    dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=REPO, capture_output=True,
                           text=True, check=False).stdout.strip()
    path.write_text(json.dumps({"tree": rev + ("+changes" if dirty else ""), "size": f"{h}x{w}", "robots": robots,
                                "steps": steps, "values": values}, indent=0) + "\n")
    print(f"wrote the values of {len(values)} requests ({robots} robots x {steps} steps, {w}x{h}) to {path}")
    return 0


# ---- the bench --------------------------------------------------------------------------------------------
def _load() -> str:
    return " ".join(f"{x:.1f}" for x in os.getloadavg())


def main(argv: list[str] | None = None) -> int:
    ap = harness.parser(__doc__)
    ap.add_argument("--robots", type=int, nargs="+", default=[1, 2, 4, 8, 16], help="concurrent robot counts (1..64)")
    ap.add_argument("--steps", type=int, default=6, help="steps per robot per round (1..100, default 6)")
    ap.add_argument("--rounds", type=int, default=4,
                    help="alternating off/on rounds per robot count (1..20, default 4)")
    ap.add_argument("--clients", type=int, default=2, help="client processes the robots are spread over (1..8)")
    ap.add_argument("--batch-max", type=int, default=16, help="EQA_SCORER_BATCH_MAX of the 'on' replica (default 16)")
    ap.add_argument("--window-ms", type=float, default=0.0, help="EQA_SCORER_BATCH_WINDOW_MS of the 'on' replica")
    ap.add_argument("--size", default="120x160", help="image HxW (default 120x160)")
    ap.add_argument("--replica-tree", type=Path, default=REPO, help="the checkout whose replicas run (default: "
                    "this one); e.g. an export of an earlier commit, to measure it in this harness")
    ap.add_argument("--reference", type=Path, help="values recorded from an earlier tree (--record): every request "
                    "of this run that it holds must have exactly those values")
    ap.add_argument("--record", type=Path, help="write this tree's values of the requests of --robots (the largest) "
                    "x --steps, scored one by one in this process, to this file, and stop")
    if argv is None and len(sys.argv) > 1 and sys.argv[1] == "--client":
        return client_main(int(sys.argv[2]), sys.argv[3], sys.argv[4])
    args = ap.parse_args(argv)
    h, w = (int(v) for v in args.size.split("x"))
    if not (all(1 <= r <= 64 for r in args.robots) and 1 <= args.steps <= 100 and 1 <= args.rounds <= 20
            and 1 <= args.clients <= 8 and 16 <= h <= 1024 and 16 <= w <= 1024):
        print("error: robots 1..64, steps 1..100, rounds 1..20, clients 1..8, sides 16..1024", file=sys.stderr)
        return 2
    if args.record:
        return record(args.record, max(args.robots), args.steps, h, w)
    reference: dict[str, Any] = {}
    if args.reference:
        ref = json.loads(args.reference.read_text())
        if ref["size"] != f"{h}x{w}":
            print(f"error: {args.reference} holds {ref['size']} frames, this run {h}x{w}", file=sys.stderr)
            return 2
        reference = ref["values"]

    from services.vlm_scorer.tiny import build_tiny_qwen2vl

    tmp = Path(tempfile.mkdtemp(prefix="bench-scorer-batching-"))
    model_dir = build_tiny_qwen2vl(tmp / "tiny-qwen2vl")
    port = free_port()
    base = Settings(data_dir=tmp / "var", zenoh_listen=["tcp/127.0.0.1:0"],
                    zenoh_connect=[f"tcp/127.0.0.1:{port}"], record=False, scorer_backend="hf",
                    hf_model_path=model_dir, scorer_timeout_s=120)
    hub = base.model_copy(update={"zenoh_listen": [f"tcp/127.0.0.1:{port}"], "zenoh_connect": []})
    env = {**os.environ, **base.env(), "EQA_LOG_LEVEL": "WARNING", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    extra = {"off": {"EQA_SCORER_BATCH_MAX": "1"},
             "on": {"EQA_SCORER_BATCH_MAX": str(args.batch_max), "EQA_SCORER_BATCH_WINDOW_MS": str(args.window_ms)}}
    print(f"scorer batching bench: robots {args.robots}, {args.steps} steps x {args.rounds} rounds, {args.clients} "
          f"client processes, {w}x{h} frames, replicas of {args.replica_tree}; load {_load()}", flush=True)
    rows = []
    identical = True
    loads: list[float] = [os.getloadavg()[0]]
    with Bus(hub, "gateway", "bench") as bus:
        procs = {m: subprocess.Popen([sys.executable, "-m", "services.vlm_scorer"], cwd=args.replica_tree,
                                     env={**env, **extra[m], "EQA_SCORER_REPLICA": f"b-{m}", "EQA_INSTANCE": f"b-{m}"})
                 for m in MODES}
        clients: Clients | None = None
        try:
            if not ScorerClient(bus, base).wait_for_replicas(2, timeout=180):
                print("error: the two replicas did not come up", file=sys.stderr)
                return 1
            clients = Clients(args.clients, port, tmp)
            print("  replicas and clients up; warming up", flush=True)
            clients.prepare(min(2 * args.clients, 4), 2, (h, w))
            for m in MODES:
                clients.run(f"b-{m}")
            for n in args.robots:
                clients.prepare(n, args.steps, (h, w))
                rates: dict[str, list[float]] = {m: [] for m in MODES}
                cpus: dict[str, list[float]] = {m: [] for m in MODES}
                ccpus: dict[str, list[float]] = {m: [] for m in MODES}
                lats: dict[str, list[float]] = {m: [] for m in MODES}
                served = dict.fromkeys(MODES, 0)
                vals: dict[str, dict[str, Any]] = {m: {} for m in MODES}
                for rnd in range(args.rounds):
                    for m in (MODES if rnd % 2 == 0 else MODES[::-1]):
                        cpu0 = cpu_seconds(procs[m].pid)
                        outs = clients.run(f"b-{m}")
                        cpu = cpu_seconds(procs[m].pid) - cpu0
                        steps = sum(len(o["latencies"]) for o in outs)
                        wall = max(o["end"] for o in outs) - min(o["start"] for o in outs)
                        rates[m].append(steps / wall)
                        cpus[m].append(cpu)
                        ccpus[m].append(sum(o["cpu"] for o in outs))
                        served[m] += steps
                        for o in outs:
                            lats[m].extend(o["latencies"])
                            for rid, v in o["values"].items():
                                if vals[m].setdefault(rid, v) != v:
                                    vals[m][rid] = {"error": "values differ between rounds"}
                    loads.append(os.getloadavg()[0])
                errors = [rid for m in MODES for rid, v in vals[m].items() if isinstance(v, dict)]
                same = not errors and vals["off"] == vals["on"]
                checked = [rid for rid in vals["off"] if rid in reference]
                as_ref = all(vals["off"][rid] == reference[rid] for rid in checked)
                identical &= same and as_ref
                row = {"robots": n, "rate": {m: statistics.median(rates[m]) for m in MODES},
                       "lat": {m: (pct(lats[m], 50), pct(lats[m], 95)) for m in MODES},
                       "cpu": {m: sum(cpus[m]) / served[m] * 1e3 for m in MODES},
                       "ccpu": {m: sum(ccpus[m]) / served[m] * 1e3 for m in MODES},
                       "same": same, "ref": (len(checked), as_ref), "load": os.getloadavg()[0]}
                rows.append(row)
                print(f"  {n:3d} robots: off {row['rate']['off']:6.1f} steps/s {row['cpu']['off']:5.2f} CPU ms/step, "
                      f"on {row['rate']['on']:6.1f} steps/s {row['cpu']['on']:5.2f} CPU ms/step; same values "
                      f"{'yes' if same else 'NO'}" + (f", as reference {'yes' if as_ref else 'NO'} ({len(checked)})"
                                                      if reference else "") + f"; load {_load()}", flush=True)
                if errors:
                    print(f"    failed requests: {errors[:5]}", flush=True)
        finally:
            if clients is not None:
                clients.close()
            for p in procs.values():
                p.terminate()
            for p in procs.values():
                p.wait(timeout=30)
    print(f"\nscorer replica, tiny random Qwen2-VL (not a VLM), {w}x{h} frames, 1 torch thread, batch max "
          f"{args.batch_max}, window {args.window_ms:g} ms; {args.steps} steps per robot x {args.rounds} rounds "
          f"(alternating), robots in {args.clients} client processes; {os.cpu_count()} CPUs, 1-min load "
          f"{min(loads):.1f}-{max(loads):.1f} during the run")
    print(f"{'robots':>6} {'steps/s off':>11} {'on':>6} {'on/off':>6} {'p50/p95 ms off':>15} {'on':>11} "
          f"{'replica CPU ms/step off':>23} {'on':>5} {'off/on':>6} {'client CPU ms/step off/on':>26}  same values"
          + ("  as reference" if reference else ""))
    for r in rows:
        rate, lat, cpu, ccpu = r["rate"], r["lat"], r["cpu"], r["ccpu"]
        print(f"{r['robots']:6d} {rate['off']:11.1f} {rate['on']:6.1f} {rate['on'] / rate['off']:6.2f} "
              f"{lat['off'][0]:7.0f}/{lat['off'][1]:<7.0f} {lat['on'][0]:5.0f}/{lat['on'][1]:<5.0f} "
              f"{cpu['off']:23.2f} {cpu['on']:5.2f} {cpu['off'] / cpu['on']:6.2f} "
              f"{ccpu['off']:18.2f}/{ccpu['on']:<7.2f}  {'yes' if r['same'] else 'NO':>11}"
              + (f"  {'yes' if r['ref'][1] else 'NO'} ({r['ref'][0]} requests)" if reference else ""))
    print("steps/s: all robots' steps per second of wall time (the replica and the clients share this machine's "
          "cores), median over rounds; replica CPU ms/step: user+system time of the replica process over all "
          "rounds per step served (1000 / it = steps per second one core of a saturated replica sustains); client "
          "CPU: all client processes together; same values: every request's values byte for byte equal between "
          "off and on")
    return 0 if identical else 1


if __name__ == "__main__":
    raise SystemExit(main())

"""One step of the whole pipeline: steps per second through the real fleet, and where the time of a step goes.

Three parts, all on this machine, in one command:

1. **Fleet throughput.** The real services (sim, mapper, scorer replica with the oracle backend, stopper,
   planner) as separate processes over Zenoh (:class:`eqa_app.benchmark_runner.Runner`), ``--questions`` generated
   questions on one house, each capped at ``--steps`` steps, with 1 and 2 robots, at each ``--sizes``
   (default 640x480 and 320x240), Rerun recording off. Steps/s = StepScores received / wall time from the
   first EpisodeStart to the last EpisodeEnd.
2. **Where a step goes in the fleet** (1 robot, 640x480, with Rerun recording ON, "figures included"): the
   hub timestamps every message of the robot on arrival (frames are not decoded; their order gives the
   step), so per step: sim (Goal(t) -> Frame(t+1): decode goal, move, render, encode, transport), mapper
   (Frame -> MapUpdate, with its own stage timings carried in ``MapUpdate.timing_ms``: integrate, project,
   prompt points, scorer round trip, semantic values, frontiers, snapshot), stopper (StepScores ->
   Decision), planner (the later of MapUpdate and Decision -> Goal).
3. **In-process breakdown of one step** on the same house with the same code (no bus): render, Frame
   encode / decode, Zenoh transport of a frame between two sessions, the mapper stages, snapshot
   (+ store write), Rerun logging of the mapper, ScoreRequest encode + oracle scoring, stopper decide(),
   planner plan_step(); and "mapper+planner per step, figures included".

External figures, not measured by this script: the reference code (Explore-EQA's public code) was stated in
the project's task brief to take about 200 ms per mapper+planner step with its figures off and about 5.8 s
with them on (it saves matplotlib figures every step); date, machine load, frames and n of that measurement
are not recorded. They are printed next to ours for orientation only, labelled as external, and no ratio is
formed from them (a ratio must come from two things timed in the same run). docs/results/performance.md records a
side-by-side run (same 40 rendered 640x480 frames, interleaved, load ~7): reference mapper+planner p50
564.6 ms against ours 40.1 ms. The figures here are p50 / p95 in milliseconds unless stated.

    python -m eqa_app.benches.pipeline [--steps 25] [--questions 2] [--sizes 640x480,320x240] [--skip-fleet]
"""

from __future__ import annotations

import logging
import math
import os
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

os.environ.setdefault("RERUN_TELEMETRY_ENABLED", "false")

from eqa import keys
from eqa.launcher import free_port
from eqa.messages import (
    Decision,
    EpisodeStart,
    Frame,
    Goal,
    MapUpdate,
    Question,
    ScoreRequest,
    StepScores,
    StopConfig,
    decode,
    encode,
)
from eqa.settings import Settings
from eqa_app.benches import harness
from eqa_app.stats import percentile as pct

# External figures (see the module docstring): not timed here, never divided by our timings.
EXTERNAL_REFERENCE_MS = {"figures off": 200.0, "figures on": 5800.0}
EXTERNAL_REFERENCE_SOURCE = "project task brief (date, load and method not recorded); not measured in this run"


def fmt(values: list[float]) -> str:
    return f"{pct(values, 50):7.1f} {pct(values, 95):7.1f}" if values else "      -       -"


def parse_size(text: str) -> tuple[int, int]:
    w, _, h = text.lower().partition("x")
    return int(w), int(h)


def questions(scene_id: str, n: int, steps: int, scenes_path: Path, seed: int = 7) -> list[Question]:
    from services.sim.library import load_or_generate
    from services.sim.questions import generate_questions

    scene = load_or_generate(scene_id, scenes_path)
    qs = generate_questions(scene, np.random.default_rng(seed))[:n]
    return [q.model_copy(update={"max_steps": min(q.max_steps or steps, steps)}) for q in qs]


# ---- 1 + 2: the real fleet ---------------------------------------------------------------------------------


class _Tap:
    """Arrival times of every message of one robot at the hub (frames counted, not decoded)."""

    def __init__(self, robot: str) -> None:
        self.robot = robot
        self.lock = threading.Lock()
        self.frames: list[float] = []
        self.events: list[tuple[float, str, Any]] = []

    def on_sample(self, sample: Any) -> None:
        now = time.perf_counter()
        key = str(sample.key_expr)
        if key.endswith("/sim/frame"):
            with self.lock:
                self.frames.append(now)
            return
        stream = "/".join(key.split("/")[-2:])
        if stream not in ("mapper/map", "mapper/scores", "stopper/decision", "planner/goal"):
            return
        try:
            msg = decode(sample.payload.to_bytes(), None)
        except Exception:  # a message that does not decode is not part of the timing
            return
        with self.lock:
            self.events.append((now, stream, msg))

    def breakdown(self) -> dict[str, list[float]]:
        with self.lock:
            frames, events = list(self.frames), list(self.events)
        first: dict[tuple[str, int], tuple[float, Any]] = {}
        for t, stream, msg in events:
            first.setdefault((stream, msg.step), (t, msg))
        out: dict[str, list[float]] = {}

        def add(name: str, ms: float) -> None:
            out.setdefault(name, []).append(ms)

        for step, t_frame in enumerate(frames):
            mapped = first.get(("mapper/map", step))
            sc = first.get(("mapper/scores", step))
            de = first.get(("stopper/decision", step))
            go = first.get(("planner/goal", step))
            if mapped is not None:
                add("mapper: Frame -> MapUpdate at the hub", (mapped[0] - t_frame) * 1e3)
                m: MapUpdate = mapped[1]
                for k, v in m.timing_ms.items():
                    add(f"  mapper {k}", v)
            if sc is not None and de is not None:
                add("stopper: StepScores -> Decision", (de[0] - sc[0]) * 1e3)
            if mapped is not None and de is not None and go is not None:
                add("planner: max(MapUpdate, Decision) -> Goal", (go[0] - max(mapped[0], de[0])) * 1e3)
            if go is not None and step + 1 < len(frames):
                add("sim: Goal -> Frame(t+1) (move, render, encode, transport)", (frames[step + 1] - go[0]) * 1e3)
            if step + 1 < len(frames):
                add("whole step: Frame(t) -> Frame(t+1)", (frames[step + 1] - t_frame) * 1e3)
        return out


def _cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process so far (Linux /proc)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return float("nan")
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _fleet_cpu(runner: Any) -> dict[str, float]:
    out: dict[str, float] = {}
    for child in runner.fleet.children:
        if child.proc is not None:
            out[child.service] = out.get(child.service, 0.0) + _cpu_s(child.proc.pid)
    return out


CPU: dict[str, dict[str, float]] = {}  # run label -> service -> CPU ms per step


def fleet_run(
    base: Settings, size: tuple[int, int], robots: int, qs: list[Question], record: bool, tap: bool
) -> tuple[float, int, float, dict[str, list[float]] | None]:
    from eqa_app.benchmark_runner import Runner

    settings = base.model_copy(update={"sim_width": size[0], "sim_height": size[1]})
    with Runner(settings, strategy="semantic", robots=robots, record=record) as runner:
        cpu0 = _fleet_cpu(runner)
        t_tap = None
        if tap:
            assert runner.fleet is not None
            t_tap = _Tap(runner.robots[0])
            runner.fleet.hub._keep(
                runner.fleet.hub.session.declare_subscriber(keys.robot_streams(t_tap.robot), t_tap.on_sample)
            )
            time.sleep(0.3)
        t0 = time.perf_counter()
        steps = 0
        for res in runner.run(qs):
            steps += len(res.steps)
            logging.getLogger("bench").info("%s: %d steps, %s", res.question.id, len(res.steps), res.reason)
        dt = time.perf_counter() - t0
        cpu1 = _fleet_cpu(runner)
    label = f"{size[0]}x{size[1]} robots={robots}{' rerun' if record else ''}"
    CPU[label] = {k: (cpu1[k] - cpu0.get(k, 0.0)) * 1e3 / max(steps, 1) for k in cpu1}
    return steps / dt, steps, dt, (t_tap.breakdown() if t_tap is not None else None)


# ---- 3: in-process breakdown -------------------------------------------------------------------------------


def zenoh_transport_ms(payloads: list[bytes], base: Settings) -> list[float]:
    """put -> subscriber callback latency of each payload between two real Zenoh sessions on loopback."""
    from eqa.bus import Bus

    port = free_port()
    hub = base.model_copy(update={"zenoh_listen": [f"tcp/127.0.0.1:{port}"], "zenoh_connect": []})
    peer = base.model_copy(update={"zenoh_listen": [], "zenoh_connect": [f"tcp/127.0.0.1:{port}"]})
    got = threading.Event()
    arrival: list[float] = []
    out: list[float] = []
    with Bus(hub, "bench", "rx") as rx, Bus(peer, "bench", "tx") as tx:

        def on_sample(sample: Any) -> None:
            sample.payload.to_bytes()
            arrival.append(time.perf_counter())
            got.set()

        rx._keep(rx.session.declare_subscriber("bench/frame", on_sample))
        time.sleep(0.5)
        for p in [payloads[0], *payloads]:  # the first one warms the route
            got.clear()
            t0 = time.perf_counter()
            tx.publish_raw("bench/frame", p)
            if not got.wait(5.0):
                raise RuntimeError("zenoh transport: no sample within 5 s")
            out.append((arrival[-1] - t0) * 1e3)
    return out[1:]


def in_process(base: Settings, scene_id: str, size: tuple[int, int], steps: int, tmp: Path) -> dict[str, list[float]]:
    from eqa.recording import EpisodeRecorder
    from eqa.store import EmbeddedStore
    from services.mapper.episode_map import EpisodeMap, Timer
    from services.mapper.service import MapperService
    from services.mapper.snapshots import snapshot_step
    from services.planner.sampling import step_rng
    from services.planner.step import Memory, PlannerParams, plan_step
    from services.sim.camera import camera_pose, intrinsics
    from services.sim.library import load_or_generate
    from services.sim.motion import START_CLEARANCE, sample_start_pose
    from services.sim.render import Renderer
    from services.stopper.state import EpisodeRecord, decide
    from services.vlm_scorer.backends import make_backend

    W, H = size
    scene = load_or_generate(scene_id, base.scenes_path)
    renderer = Renderer(scene)
    K = intrinsics(W, H)
    qs = questions(scene_id, 1, steps, base.scenes_path)
    start = EpisodeStart(
        episode_id="bench", robot="r0", question=qs[0], strategy="semantic", max_steps=steps + 1, seed=3,
        stop=StopConfig(rule="max_steps"),
    )
    episode_map = EpisodeMap(start)
    store = EmbeddedStore(tmp / "store.sqlite")
    rec_settings = base.model_copy(update={"data_dir": tmp, "record": True})
    recorder = EpisodeRecorder(rec_settings, "bench", "mapper")
    svc = MapperService.__new__(MapperService)
    svc.recorders = {"bench": recorder}
    svc.extensions = []  # the map's own recording is timed; the object and view extensions are off here
    backend = make_backend(base.model_copy(update={"scorer_backend": "oracle"}))
    stop_rec = EpisodeRecord.from_start(start, "r0")
    params = PlannerParams()
    memory = Memory()
    pose = sample_start_pose(scene, np.random.default_rng(3), START_CLEARANCE)
    t: dict[str, list[float]] = {}
    payloads: list[bytes] = []

    def lap(name: str, t0: float) -> float:
        now = time.perf_counter()
        t.setdefault(name, []).append((now - t0) * 1e3)
        return now

    def cpu(name: str, c0: float) -> float:
        now = time.process_time()
        t.setdefault(f"CPU {name}", []).append((now - c0) * 1e3)
        return now

    for step in range(steps):
        t0 = time.perf_counter()
        c0 = time.process_time()
        T = camera_pose(pose)
        r = renderer.render(T, K, W, H)
        frame = Frame(
            episode_id="bench", step=step, pose=pose, camera_pose=T, intrinsics=K, rgb=r.rgb, depth=r.depth,
            instances=r.instances, labels=renderer.labels(r.instances), scene=scene.id,
            floor_area_m2=scene.floor_area_m2,
        )
        t0 = lap("sim: render + labels", t0)
        cpu("sim: render + labels (all threads)", c0)
        payload = encode(frame)
        t0 = lap("frame encode", t0)
        frame = decode(payload, Frame)
        lap("frame decode", t0)
        payloads.append(payload)
        t_map = time.perf_counter()
        c_map = time.process_time()
        timer = Timer()
        episode_map.integrate(frame, timer)
        req = ScoreRequest(
            episode_id="bench", step=step, question=start.question, rgb=frame.rgb, prompt_points=episode_map.prompts,
            instances=frame.instances, labels=frame.labels, depth=frame.depth, seed=start.seed,
        )
        c_map = time.process_time() - c_map
        t0 = time.perf_counter()
        req_bytes = encode(req)
        req = decode(req_bytes, ScoreRequest)
        t0 = lap("scorer: request encode + decode", t0)
        scores = backend.score(req)
        lap("scorer: oracle backend", t0)
        t1 = time.perf_counter()
        c1 = time.process_time()
        episode_map.apply_scores(scores.lsv, scores.gsv)
        timer.lap("semantic_values", t1)
        episode_map.compute_frontiers(timer=timer)
        t1 = time.perf_counter()
        header, parts, obsolete = snapshot_step(episode_map)  # what the mapper service stores (incremental)
        for name, data in parts.items():
            store.set(f"mapper/episode/bench:{name}", data)
        store.set("mapper/episode/bench", header)
        for name in obsolete:
            store.delete(f"mapper/episode/bench:{name}")
        timer.lap("snapshot", t1)
        t1 = time.perf_counter()
        update_bytes = encode(episode_map.map_update(timer.ms))
        timer.lap("MapUpdate encode", t1)
        t.setdefault("CPU mapper step without Rerun (no scorer)", []).append(
            (c_map + time.process_time() - c1) * 1e3)
        mapper_ms = (time.perf_counter() - t_map) * 1e3 - t["scorer: oracle backend"][-1] - t[
            "scorer: request encode + decode"][-1]
        for k, v in timer.ms.items():
            t.setdefault(f"mapper {k}", []).append(v)
        t1 = time.perf_counter()
        c1 = time.process_time()
        MapperService._record(svc, episode_map, frame)
        cpu("mapper record (Rerun)", c1)
        record_ms = (time.perf_counter() - t1) * 1e3
        t.setdefault("mapper record (Rerun)", []).append(record_ms)
        t.setdefault("mapper step without Rerun (no scorer)", []).append(mapper_ms)
        ss = StepScores(
            episode_id="bench", step=step, answer_probs=scores.answer_probs, relevance=scores.relevance,
            lsv=scores.lsv, gsv=scores.gsv, backend="oracle", choices=start.question.choices,
        )
        t0 = time.perf_counter()
        decision = decide(stop_rec, ss)
        lap("stopper decide()", t0)
        if isinstance(decision, Decision) and decision.stop:
            stop_rec = EpisodeRecord.from_start(start, "r0")
        t0 = time.perf_counter()
        update = decode(update_bytes, MapUpdate)
        t0 = lap("planner: MapUpdate decode", t0)
        c0 = time.process_time()
        plan = plan_step(
            update.grid, update.free, update.occupied, update.pose, update.frontiers, "semantic", memory,
            step_rng(3, step), params,
        )
        plan_ms = (time.perf_counter() - t0) * 1e3
        cpu("planner plan_step()", c0)
        t.setdefault("planner plan_step()", []).append(plan_ms)
        goal = Goal(episode_id="bench", step=step, pose=plan.pose, path=plan.path, done=plan.done)
        t0 = time.perf_counter()
        decode(encode(goal), Goal)
        lap("goal encode + decode", t0)
        t.setdefault("mapper+planner, figures off", []).append(mapper_ms + plan_ms)
        t.setdefault("mapper+planner, figures included", []).append(mapper_ms + plan_ms + record_ms)
        memory = plan.memory
        if plan.done or plan.pose is None:
            yaw = pose.yaw + math.radians(60)
            pose = pose.model_copy(update={"yaw": math.atan2(math.sin(yaw), math.cos(yaw))})
            memory = Memory()
        else:
            pose = plan.pose
    recorder.close()
    store.close()
    t["frame transport (Zenoh, loopback)"] = zenoh_transport_ms(payloads, base)
    t["_frame_kB"] = [len(p) / 1e3 for p in payloads]
    return t


def main(argv: list[str] | None = None) -> int:
    ap = harness.parser(__doc__)
    ap.add_argument("--steps", type=int, default=25, help="steps per question (cap on max_steps)")
    ap.add_argument("--questions", type=int, default=2, help="questions per fleet run")
    ap.add_argument("--sizes", default="640x480,320x240", help="image sizes of the throughput runs")
    ap.add_argument("--scene", default="gen-00003")
    ap.add_argument("--robots", default="1,2", help="robot counts of the throughput runs")
    ap.add_argument("--skip-fleet", action="store_true", help="only the in-process breakdown")
    ap.add_argument("--skip-inprocess", action="store_true", help="only the fleet runs")
    ap.add_argument("-v", "--verbose", action="store_true")
    args = ap.parse_args(argv)
    try:
        sizes = [parse_size(s) for s in args.sizes.split(",") if s]
        robot_counts = [int(r) for r in args.robots.split(",") if r]
    except ValueError:
        print("error: --sizes like 640x480,320x240 and --robots like 1,2", file=sys.stderr)
        return 2
    if args.steps < 2 or args.questions < 1 or not sizes or any(r < 1 for r in robot_counts):
        print("error: --steps >= 2, --questions >= 1, at least one size, robots >= 1", file=sys.stderr)
        return 2
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING)
    tmp = Path(tempfile.mkdtemp(prefix="bench-pipeline-"))
    base = Settings(data_dir=tmp, zenoh_listen=[], zenoh_connect=[], record=False)
    print(f"pipeline bench: scene {args.scene}, {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}")

    if not args.skip_inprocess:
        w, h = sizes[0]
        t = in_process(base, args.scene, (w, h), args.steps, tmp / "inproc")
        kb = t.pop("_frame_kB")
        print(f"\n[in-process] one step at {w}x{h}, {args.steps} steps (frame {np.mean(kb):.0f} kB); ms   p50     p95")
        for k, v in t.items():
            print(f"  {k:44s} {fmt(v)}")
        mp = t["mapper+planner, figures included"]
        print(
            f"  -> mapper+planner per step with Rerun logging: p50 {pct(mp, 50):.0f} ms. External figure for the "
            f"reference code: ~{EXTERNAL_REFERENCE_MS['figures on']:.0f} ms with figures, "
            f"~{EXTERNAL_REFERENCE_MS['figures off']:.0f} ms without ({EXTERNAL_REFERENCE_SOURCE})"
        )

    if not args.skip_fleet:
        qs = questions(args.scene, args.questions, args.steps, base.scenes_path)
        print(f"\n[fleet] {len(qs)} questions x <= {args.steps} steps, oracle scorer, Rerun off: steps/s")
        for size in sizes:
            for robots in robot_counts:
                sps, n, dt, _ = fleet_run(base, size, robots, qs, record=False, tap=False)
                print(f"  {size[0]}x{size[1]} robots={robots}: {sps:5.2f} steps/s ({n} steps in {dt:.1f} s)")
        size = sizes[0]
        sps, n, dt, bd = fleet_run(base, size, 1, qs[:1], record=True, tap=True)
        print(
            f"\n[fleet] where a step goes: 1 robot, {size[0]}x{size[1]}, Rerun recording ON: {sps:.2f} steps/s "
            f"({n} steps); ms   p50     p95"
        )
        for k, v in sorted((bd or {}).items(), key=lambda kv: (kv[0].startswith("  "), kv[0])):
            print(f"  {k:58s} {fmt(v)}")
        services = sorted({k for v in CPU.values() for k in v})
        print(
            "\n[fleet] CPU time per step of each service process (ms; less sensitive to other load than wall time)"
        )
        print("  " + " " * 28 + "".join(f"{k:>11s}" for k in services) + "      total")
        for label, per in CPU.items():
            cells = "".join(f"{per.get(k, float('nan')):11.1f}" for k in services)
            print(f"  {label:28s}{cells}{sum(per.values()):11.1f}")
        print(
            "  (the 'rerun' row includes each process's one-time `import rerun`, about 0.8 s CPU, spread over the "
            "run's steps)"
        )
        mapper = (bd or {}).get("  mapper step", [])
        planner = (bd or {}).get("planner: max(MapUpdate, Decision) -> Goal", [])
        if mapper and planner:
            both = pct(mapper, 50) + pct(planner, 50)
            print(
                f"  -> mapper step (stage timings, scorer round trip included) + planner p50 = {both:.0f} ms "
                f"per step with figures on; external figure for the reference code: "
                f"~{EXTERNAL_REFERENCE_MS['figures on']:.0f} ms with figures, "
                f"~{EXTERNAL_REFERENCE_MS['figures off']:.0f} ms without ({EXTERNAL_REFERENCE_SOURCE})"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

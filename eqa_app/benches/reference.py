"""Our mapper + planner step against the reference code's per-step equivalent, on houses of four sizes: the
same rendered frames fed to both, interleaved frame by frame, in one run.

The reference is Explore-EQA's public code (github.com/Stanford-ILIAD/explore-eqa), its ``src/tsdf.py``
``TSDFPlanner``. This script holds none of its code and installs nothing: ``--reference DIR`` is a checkout the
user provides::

    git clone https://github.com/Stanford-ILIAD/explore-eqa DIR
    python -m venv REFVENV && REFVENV/bin/pip install numpy numba matplotlib scipy scikit-image scikit-learn
    python -m eqa_app.benches.reference --reference DIR --reference-python REFVENV/bin/python

(``--reference-python`` defaults to this interpreter, which works once it has scikit-image and scikit-learn.)
The reference runs in a worker process of that interpreter, started by this script; the two sides take turns
frame by frame (which goes first alternates), and each is timed in its own process, so machine load hits
both alike. Before the next side starts, the bench waits until the process that just ran has gone quiet
(thread pools may spin for a while after their work), and it prints how much CPU the other process used while
one side was timed, so that neither is charged for the other.

How the reference module is loaded: ``src/tsdf.py`` imports ``src/geom.py``, which imports ``src/habitat.py``,
whose top line is ``import habitat_sim`` (the simulator, not installable here). ``habitat_sim`` is used there
only inside ``make_simple_cfg`` and in no function this bench calls, so when it is not installed an empty
module named ``habitat_sim`` is registered before the import; any attribute read from it raises. Nothing of
the reference's computation is replaced. Its two planning functions build matplotlib figures as they go
(``plt.subplots``, ``imshow``, ``scatter``, ``colorbar``); the bench runs them with the Agg backend, never draws
or saves a figure, and closes them after the step, outside the timing. The module's ``plt`` is wrapped so
that the time spent in those matplotlib calls is added up (every call is forwarded to matplotlib unchanged):
"ref minus figure building" is the reference's step minus that sum, a derived figure.

Per step, each side (fixed semantic values instead of a scorer on both: ``0.5, 0.3, 0.2`` per prompt point,
global value ``0.6``):

* **ours** (this tree, default settings: 0.1 m voxels, truncation 5 voxels, z from -0.2 to 3.5 m, a grid that
  grows with what is seen): ``EpisodeMap.integrate`` (TSDF fusion with free-space carving and explored marks,
  robot footprint, 2D projection, prompt points), ``apply_scores`` (Eq. 3 values), ``compute_frontiers``
  (frontiers and their Eq. A6 weights), ``map_update`` and ``plan_step`` (strategy ``semantic``): "ours".
  "ours + snapshot" adds what eqa_app.benches.pipeline's "mapper+planner, figures off" also counts: the incremental
  snapshot written to an embedded store and the MapUpdate encoded and decoded; the reference has none.
* **reference** (its HM-EQA settings, ``cfg/vlm_exp.yaml``: ``tsdf_grid_size`` 0.1 m, truncation 5 voxels,
  bounds = the navigable area's bounding box, as ``get_scene_bnds`` takes them from the navmesh, and
  z from floor - 0.2 to floor + 3.5 m, allocated at the start; ``init_clearance`` 0.5 x 2; margins 0.6 H and
  0.25 W; ``visual_prompt`` and ``planner`` sections as in that file), what ``run_vlm_exp.py`` does per step
  without the VLM: the black-frame check, ``integrate``, ``find_prompt_points_within_view``, ``integrate_sem``
  (when at least ``min_num_prompt_points`` points; LSV scaled by n/3, GSV as ``exp(g / gsv_T) / gsv_F``) and
  ``find_next_pose`` (``flag_no_val_weight`` for the first 2 steps). The robot's yaw is passed in the
  reference's angle convention (``yaw - pi/2``).

Both are fed the same frames: a fixed trajectory per house (``eqa_app.benches.mapper.trajectory``: a farthest-point
spread of free cells visited in nearest-neighbour order), rendered once by our simulator at ``--width x
--height`` (RGB, depth along the optical axis, the camera-to-world pose in the OpenCV convention both sides
use, our intrinsics). Neither planner's output moves the camera (open loop), so both see the same frames.
Before the timed steps each side integrates two frames of a throw-away map (numba compilation). Wall time is
``perf_counter``; CPU is the process's CPU time over the step (all threads: the reference's numba kernels run
``parallel=True`` on every core), and the main thread's CPU time.

    python -m eqa_app.benches.reference --reference DIR [--reference-python PY] [--steps 40]
        [--houses gen-00014,gen-00028,gen-00004,gen-00000] [--out bench/results/perf/reference_step.png]
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import io
import json
import math
import os
import struct
import subprocess
import sys
import tempfile
import threading
import time
import traceback
import types
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

HOUSES = "gen-00014,gen-00028,gen-00004,gen-00000"  # generated benchmark houses of ~100, 240, 350, 490 m2
LSV = (0.5, 0.3, 0.2)  # fixed per-prompt-point values fed to both sides (no scorer in this bench)
GSV = 0.6
GET_IT = (
    "get the reference with:\n"
    "    git clone https://github.com/Stanford-ILIAD/explore-eqa DIR\n"
    "    python -m venv REFVENV && REFVENV/bin/pip install numpy numba matplotlib scipy scikit-image scikit-learn\n"
    "and run with --reference DIR --reference-python REFVENV/bin/python"
)

# The reference's HM-EQA settings (explore-eqa cfg/vlm_exp.yaml), passed to its functions as its runner does.
REF_CFG: dict[str, Any] = {
    "tsdf_grid_size": 0.1,
    "init_clearance": 0.5,
    "margin_w_ratio": 0.25,
    "margin_h_ratio": 0.6,
    "black_pixel_ratio": 0.5,
    "min_random_init_steps": 2,
    "gsv_T": 0.5,
    "gsv_F": 3,
    "planner": {
        "dist_T": 10, "unexplored_T": 0.2, "unoccupied_T": 2.0, "val_T": 0.5, "val_dir_T": 0.5,
        "max_val_check_frontier": 3, "smooth_sigma": 5, "eps": 1, "min_dist_from_cur": 0.5,
        "max_dist_from_cur": 3, "frontier_spacing": 1.5, "frontier_min_neighbors": 3,
        "frontier_max_neighbors": 4, "max_unexplored_check_frontier": 3, "max_unoccupied_check_frontier": 1,
    },
    "visual_prompt": {
        "cluster_threshold": 1.0, "num_prompt_points": 3, "num_max_unoccupied": 300,
        "min_points_for_clustering": 3, "point_min_dist": 2, "point_max_dist": 10, "cam_offset": 0.6,
        "min_num_prompt_points": 2, "circle_radius": 18,
    },
}


# ---- the channel between this process and the reference worker -----------------------------------------------


def send(stream: BinaryIO, head: dict[str, Any], arrays: dict[str, np.ndarray] | None = None) -> None:
    """One message: a JSON header and an optional ``.npz`` body (a format both numpy versions read)."""
    body = b""
    if arrays:
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        body = buf.getvalue()
    j = json.dumps(head).encode()
    stream.write(struct.pack("<IQ", len(j), len(body)) + j + body)
    stream.flush()


def recv(stream: BinaryIO) -> tuple[dict[str, Any] | None, dict[str, np.ndarray]]:
    raw = stream.read(12)
    if len(raw) < 12:
        return None, {}
    nj, nb = struct.unpack("<IQ", raw)
    head = json.loads(stream.read(nj))
    arrays: dict[str, np.ndarray] = {}
    if nb:
        with np.load(io.BytesIO(stream.read(nb))) as z:
            arrays = {k: z[k] for k in z.files}
    return head, arrays


# ---- the reference side (runs in the worker process; needs numpy and the reference's own dependencies) --------


class FigureClock:
    """Wall and CPU time spent inside matplotlib calls made through :class:`Timed` objects."""

    def __init__(self) -> None:
        self.wall = 0.0
        self.cpu = 0.0

    def reset(self) -> None:
        self.wall = self.cpu = 0.0


class Timed:
    """Forwards every attribute and call to a matplotlib object, adding the time of each call to a clock."""

    def __init__(self, obj: Any, clock: FigureClock) -> None:
        self._obj = obj
        self._clock = clock

    def __getattr__(self, name: str) -> Any:
        attr = getattr(self._obj, name)
        if not callable(attr):
            return attr
        clock = self._clock

        def call(*args: Any, **kwargs: Any) -> Any:
            args = tuple(a._obj if isinstance(a, Timed) else a for a in args)
            kwargs = {k: v._obj if isinstance(v, Timed) else v for k, v in kwargs.items()}
            w0, c0 = time.perf_counter(), time.process_time()
            try:
                return attr(*args, **kwargs)
            finally:
                clock.wall += time.perf_counter() - w0
                clock.cpu += time.process_time() - c0

        return call


class TimedPyplot:
    """The reference module's ``plt``: pyplot itself, except that ``subplots`` returns its figure and axes
    wrapped in :class:`Timed` (and is timed too)."""

    def __init__(self, pyplot: Any, clock: FigureClock) -> None:
        self._plt = pyplot
        self._clock = clock
        self.figures: list[Any] = []

    def __getattr__(self, name: str) -> Any:
        return getattr(self._plt, name)

    def subplots(self, *args: Any, **kwargs: Any) -> tuple[Timed, Any]:
        w0, c0 = time.perf_counter(), time.process_time()
        fig, axes = self._plt.subplots(*args, **kwargs)
        self._clock.wall += time.perf_counter() - w0
        self._clock.cpu += time.process_time() - c0
        self.figures.append(fig)
        arr = np.asarray(axes, dtype=object)
        if arr.ndim == 0:
            return Timed(fig, self._clock), Timed(axes, self._clock)
        if arr.ndim == 1:
            return Timed(fig, self._clock), [Timed(a, self._clock) for a in arr]
        return Timed(fig, self._clock), [[Timed(a, self._clock) for a in row] for row in arr]

    def close_all(self) -> None:
        for fig in self.figures:
            self._plt.close(fig)
        self.figures.clear()


def load_reference(ref_dir: Path) -> tuple[types.ModuleType, TimedPyplot, FigureClock]:
    """``src.tsdf`` of the checkout (see the module doc for the ``habitat_sim`` name and the wrapped ``plt``)."""
    import importlib
    import importlib.util

    os.environ.setdefault("MPLBACKEND", "Agg")
    if importlib.util.find_spec("habitat_sim") is None:
        absent = types.ModuleType("habitat_sim")

        def _missing(name: str) -> Any:
            raise AttributeError(f"habitat_sim.{name}: habitat_sim is not installed (the bench does not simulate)")

        absent.__getattr__ = _missing  # type: ignore[method-assign]
        sys.modules["habitat_sim"] = absent
    sys.path.insert(0, str(ref_dir))
    mod = importlib.import_module("src.tsdf")
    import matplotlib.pyplot as pyplot

    clock = FigureClock()
    plt = TimedPyplot(pyplot, clock)
    mod.plt = plt  # type: ignore[attr-defined]
    return mod, plt, clock


class RefHouse:
    """One house's ``TSDFPlanner`` and the reference's per-step calls (module doc)."""

    def __init__(self, mod: types.ModuleType, plt: TimedPyplot, clock: FigureClock, head: dict[str, Any]) -> None:
        import random

        self.plt, self.clock = plt, clock
        np.random.seed(head["seed"])  # the reference draws from numpy's and Python's global generators
        random.seed(head["seed"])
        t0 = time.perf_counter()
        self.planner = mod.TSDFPlanner(
            vol_bnds=np.asarray(head["bounds"], dtype=np.float64),
            voxel_size=REF_CFG["tsdf_grid_size"],
            floor_height_offset=0,
            pts_init=np.asarray(head["init"], dtype=np.float64),
            init_clearance=REF_CFG["init_clearance"] * 2,
        )
        self.setup_ms = (time.perf_counter() - t0) * 1e3
        self.floor = float(head["init"][2])

    def step(self, head: dict[str, Any], a: dict[str, np.ndarray]) -> dict[str, Any]:
        rgb, depth, K, T = a["rgb"], a["depth"], a["K"], a["T"]
        H, W = depth.shape
        pts = np.array([head["x"], head["y"], self.floor])
        angle = head["yaw"] - math.pi / 2  # the reference's heading: yaw = angle + pi/2 (src/tsdf.py's next_yaw)
        vp = REF_CFG["visual_prompt"]
        stages: dict[str, float] = {}
        self.clock.reset()
        w0, c0, t0 = time.perf_counter(), time.process_time(), time.thread_time()
        lap = w0
        n_points = -1
        if np.sum(np.sum(rgb, axis=-1) == 0) < REF_CFG["black_pixel_ratio"] * W * H:
            self.planner.integrate(
                color_im=rgb, depth_im=depth, cam_intr=K, cam_pose=T, obs_weight=1.0,
                margin_h=int(REF_CFG["margin_h_ratio"] * H), margin_w=int(REF_CFG["margin_w_ratio"] * W),
            )
            now = time.perf_counter()
            stages["integrate"], lap = (now - lap) * 1e3, now
            pix, _fig = self.planner.find_prompt_points_within_view(pts, W, H, K, T, **vp)
            now = time.perf_counter()
            stages["prompt points (+ 2D maps)"], lap = (now - lap) * 1e3, now
            n_points = len(pix)
            if n_points >= vp["min_num_prompt_points"]:
                lsv = np.array([LSV[i % len(LSV)] for i in range(n_points)]) * n_points / 3
                gsv = np.exp(GSV / REF_CFG["gsv_T"]) / REF_CFG["gsv_F"]
                self.planner.integrate_sem(sem_pix=lsv * gsv, radius=1.0, obs_weight=1.0)
            now = time.perf_counter()
            stages["integrate_sem"], lap = (now - lap) * 1e3, now
        self.planner.find_next_pose(
            pts=pts, angle=angle, flag_no_val_weight=head["step"] < REF_CFG["min_random_init_steps"],
            **REF_CFG["planner"],
        )
        now = time.perf_counter()
        stages["find_next_pose"] = (now - lap) * 1e3
        out = {
            "wall_ms": (now - w0) * 1e3,
            "cpu_ms": (time.process_time() - c0) * 1e3,
            "thread_ms": (time.thread_time() - t0) * 1e3,
            "fig_wall_ms": self.clock.wall * 1e3,
            "fig_cpu_ms": self.clock.cpu * 1e3,
            "stages": stages,
            "prompt_points": n_points,
        }
        self.plt.close_all()  # what the reference's runner does after saving them; not timed
        gc.collect()  # the closed figures' garbage is freed here, not inside the next timed step
        return out


def worker(ref_dir: str) -> int:
    """The reference side: answers ``house`` and ``step`` messages on stdin/stdout until ``exit``."""
    out, inp = sys.stdout.buffer, sys.stdin.buffer
    sys.stdout = sys.stderr  # the channel carries messages only
    try:
        mod, plt, clock = load_reference(Path(ref_dir))
    except Exception as exc:  # reported to the parent, which says how to get the reference
        send(out, {"error": f"{type(exc).__name__}: {exc}"})
        return 1
    import numba

    send(out, {"ok": True, "python": sys.version.split()[0], "numpy": np.__version__, "numba": numba.__version__,
               "numba_threads": int(numba.config.NUMBA_NUM_THREADS)})
    house: RefHouse | None = None
    while True:
        head, arrays = recv(inp)
        if head is None or head["op"] == "exit":
            return 0
        try:
            if head["op"] == "house":
                house = RefHouse(mod, plt, clock, head)
                reply: dict[str, Any] = {"setup_ms": house.setup_ms, "vol_dim": [int(v) for v in
                                                                                 house.planner._vol_dim]}
            elif head["op"] == "step" and house is not None:
                reply = house.step(head, arrays)
                if head.get("last_warmup"):
                    reply["threading_layer"] = numba.threading_layer()
            else:
                reply = {"error": f"unexpected message {head['op']!r}"}
        except Exception:  # the parent stops and prints it
            reply = {"error": traceback.format_exc()}
        send(out, reply)


class Reference:
    """The parent's handle on the worker process."""

    def __init__(self, python: str, ref_dir: Path) -> None:
        env = dict(os.environ, MPLBACKEND="Agg")
        # run by path, not as a module: the reference's interpreter has none of this repository's packages, and
        # this file imports none of them at module level
        self.proc = subprocess.Popen([python, str(Path(__file__).resolve()), "--worker", str(ref_dir)],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env)
        hello, _ = recv(self.proc.stdout)  # type: ignore[arg-type]
        if hello is None or "error" in hello:
            self.close()
            raise LookupError((hello or {}).get("error", "the worker exited before answering"))
        self.info = hello

    def call(self, head: dict[str, Any], arrays: dict[str, np.ndarray] | None = None) -> dict[str, Any]:
        send(self.proc.stdin, head, arrays)  # type: ignore[arg-type]
        reply, _ = recv(self.proc.stdout)  # type: ignore[arg-type]
        if reply is None:
            raise RuntimeError("the reference worker exited")
        if "error" in reply:
            raise RuntimeError(f"reference worker: {reply['error']}")
        return reply

    def close(self) -> None:
        if self.proc.poll() is None:
            with contextlib.suppress(OSError):  # a worker that died already has nothing to be told
                send(self.proc.stdin, {"op": "exit"})  # type: ignore[arg-type]
            try:
                self.proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


# ---- our side (this process) -----------------------------------------------------------------------------------


class OursHouse:
    """This tree's mapper and planner on one house, driven in process (module doc)."""

    def __init__(self, scene_id: str, steps: int, seed: int, tmp: Path) -> None:
        from eqa.messages import EpisodeStart, Question
        from eqa.store import EmbeddedStore
        from services.mapper.episode_map import EpisodeMap
        from services.planner.step import Memory, PlannerParams

        q = Question(text="Where is the sofa?", choices=["a", "b", "c", "d"], scene=scene_id)
        start = EpisodeStart(episode_id="bench", robot="r0", question=q, strategy="semantic", max_steps=steps + 1,
                             seed=seed)
        self.map = EpisodeMap(start)
        self.memory = Memory()
        self.params = PlannerParams()
        self.seed = seed
        self.store = EmbeddedStore(tmp / f"store-{scene_id}-{time.monotonic_ns()}.sqlite")

    def step(self, frame: Any) -> dict[str, Any]:
        from eqa.messages import MapUpdate, decode, encode
        from services.mapper.episode_map import Timer
        from services.mapper.snapshots import snapshot_step
        from services.planner.sampling import step_rng
        from services.planner.step import Memory, plan_step

        em = self.map
        timer = Timer()
        w0, c0, t0 = time.perf_counter(), time.process_time(), time.thread_time()
        em.integrate(frame, timer)
        t1 = time.perf_counter()
        em.apply_scores([LSV[i % len(LSV)] for i in range(len(em.prompts))], GSV)
        timer.lap("semantic_values", t1)
        em.compute_frontiers(timer=timer)
        update = em.map_update(timer.ms)
        t1 = time.perf_counter()
        plan = plan_step(update.grid, update.free, update.occupied, update.pose, update.frontiers, "semantic",
                         self.memory, step_rng(self.seed, frame.step), self.params)
        timer.lap("plan_step", t1)
        w1, c1, th1 = time.perf_counter(), time.process_time(), time.thread_time()
        header, parts, obsolete = snapshot_step(em)  # what the mapper service stores, and the bus bytes
        self.store.set_many([*((f"mapper/episode/bench:{k}", v) for k, v in parts.items()),
                             ("mapper/episode/bench", header)],
                            then_delete=[f"mapper/episode/bench:{k}" for k in obsolete])
        decode(encode(em.map_update(timer.ms)), MapUpdate)
        w2, c2 = time.perf_counter(), time.process_time()
        self.memory = Memory() if plan.done or plan.pose is None else plan.memory
        gc.collect()  # as on the reference's side: no collection of earlier garbage inside a timed step
        return {
            "wall_ms": (w1 - w0) * 1e3,
            "cpu_ms": (c1 - c0) * 1e3,
            "thread_ms": (th1 - t0) * 1e3,
            "full_wall_ms": (w2 - w0) * 1e3,
            "full_cpu_ms": (c2 - c0) * 1e3,
            "stages": dict(timer.ms),
            "prompt_points": len(em.prompts),
            "observed_m2": float(em.maps.observed.sum()) * em.resolution**2 if em.maps is not None else 0.0,
        }

    def close(self) -> None:
        self.store.close()


# ---- keeping the two sides apart -------------------------------------------------------------------------------


def run_ns(pid: int, skip_tid: int | None = None) -> int:
    """CPU nanoseconds the threads of process ``pid`` have run so far (``/proc/<pid>/task/*/schedstat``;
    ``skip_tid``: a thread left out). 0 where the kernel does not expose it."""
    total = 0
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return 0
    for tid in tids:
        if skip_tid is not None and int(tid) == skip_tid:
            continue
        try:
            with open(f"/proc/{pid}/task/{tid}/schedstat") as fh:
                total += int(fh.read().split()[0])
        except (OSError, ValueError, IndexError):
            continue
    return total


def settle(pid: int, quiet_ns: int = 200_000, window_s: float = 0.005, max_s: float = 2.0) -> float:
    """Wait until process ``pid`` runs less than ``quiet_ns`` in a ``window_s`` window (thread pools that spin
    after their work, e.g. OpenMP's or OpenBLAS's, go to sleep after a while); the seconds waited."""
    t0 = time.perf_counter()
    last = run_ns(pid)
    while time.perf_counter() - t0 < max_s:
        time.sleep(window_s)
        now = run_ns(pid)
        if now - last < quiet_ns:
            break
        last = now
    return time.perf_counter() - t0


# ---- the run ---------------------------------------------------------------------------------------------------


def uptime() -> str:
    a, b, c = os.getloadavg()
    return f"load average {a:.2f} {b:.2f} {c:.2f}"


def ref_commit(ref_dir: Path) -> str:
    try:
        rev = subprocess.run(["git", "-C", str(ref_dir), "rev-parse", "HEAD"], check=True, capture_output=True,
                             text=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(ref_dir), "status", "--porcelain", "--untracked-files=no"],
                               check=True, capture_output=True, text=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown (not a git checkout)"
    return rev + (" (with local changes)" if dirty else "")


def render_frames(scene: Any, steps: int, width: int, height: int, seed: int) -> list[Any]:
    from eqa.messages import Frame
    from eqa_app.benches.mapper import trajectory
    from services.sim.camera import camera_pose, intrinsics
    from services.sim.render import Renderer

    renderer = Renderer(scene)
    K = intrinsics(width, height)
    frames = []
    for i, p in enumerate(trajectory(scene, steps, seed)):
        T = camera_pose(p)
        r = renderer.render(T, K, width, height)
        frames.append(Frame(episode_id="bench", step=i, pose=p, camera_pose=T, intrinsics=K, rgb=r.rgb,
                            depth=r.depth))
    return frames


def ref_bounds(scene: Any) -> list[list[float]]:
    """The reference's volume bounds for a house: the navigable area's bounding box (``get_scene_bnds``
    reads the navmesh's), z from floor - 0.2 to floor + 3.5 m (our floors are at z = 0)."""
    nav, ox, oy = scene.navigable_grid(0.1)
    rr, cc = np.nonzero(nav)
    x0, x1 = ox + cc.min() * 0.1, ox + (cc.max() + 1) * 0.1
    y0, y1 = oy + rr.min() * 0.1, oy + (rr.max() + 1) * 0.1
    return [[float(x0), float(x1)], [float(y0), float(y1)], [-0.2, 3.5]]


def frame_arrays(frame: Any) -> dict[str, np.ndarray]:
    return {"rgb": np.asarray(frame.rgb), "depth": np.asarray(frame.depth, np.float32),
            "K": np.asarray(frame.intrinsics, np.float64), "T": np.asarray(frame.camera_pose, np.float64)}


def run_house(ref: Reference, scene: Any, frames: list[Any], seed: int, tmp: Path, warmup: bool = False
              ) -> tuple[list[dict[str, Any]], list[dict[str, Any]], dict[str, Any]]:
    bounds = ref_bounds(scene)
    p0 = frames[0].pose
    setup = ref.call({"op": "house", "bounds": bounds, "init": [p0.x, p0.y, 0.0], "seed": seed})
    ours = OursHouse(scene.id, len(frames), seed, tmp)
    o_rows: list[dict[str, Any]] = []
    r_rows: list[dict[str, Any]] = []
    try:
        for i, f in enumerate(frames):
            head = {"op": "step", "step": f.step, "x": f.pose.x, "y": f.pose.y, "yaw": f.pose.yaw,
                    "last_warmup": warmup and i == len(frames) - 1}
            arrays = frame_arrays(f)
            for side in ("ours", "ref") if i % 2 == 0 else ("ref", "ours"):
                if side == "ours":
                    other0 = run_ns(ref.proc.pid)
                    row = ours.step(f)
                    row["other_ms"] = (run_ns(ref.proc.pid) - other0) / 1e6
                    o_rows.append(row | {"first": i % 2 == 0})
                    settle(os.getpid())
                else:
                    send_arrays = arrays
                    other0 = run_ns(os.getpid(), skip_tid=threading.get_native_id())
                    row = ref.call(head, send_arrays)
                    row["other_ms"] = (run_ns(os.getpid(), skip_tid=threading.get_native_id()) - other0) / 1e6
                    row["settle_ms"] = settle(ref.proc.pid) * 1e3
                    r_rows.append(row)
    finally:
        ours.close()
    setup["bounds"] = bounds
    return o_rows, r_rows, setup


def plot(rows: list[dict[str, Any]], out: Path, title: str) -> None:
    """p50 per step against house area, wall time and CPU time side by side (p95 as a band)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    area = [r["area"] for r in rows]
    fig, axes = plt.subplots(1, 2, figsize=(9.0, 4.2), dpi=100, sharey=True)
    series = (("ref", "reference (Explore-EQA src/tsdf.py)", "tab:red", "-"),
              ("ref_nofig", "reference minus its figure building (derived)", "tab:red", ":"),
              ("ours_full", "ours + snapshot and MapUpdate encode/decode", "tab:blue", "--"),
              ("ours", "ours (mapper + planner)", "tab:blue", "-"))
    for ax, kind in zip(axes, ("wall", "CPU"), strict=True):
        for key, label, color, style in series:
            k = key if kind == "wall" else f"{key}_cpu"
            p50 = [r[k]["p50"] for r in rows]
            ax.plot(area, p50, style, color=color, marker="o", label=f"{label}, p50")
            if style == "-":
                ax.fill_between(area, p50, [r[k]["p95"] for r in rows], color=color, alpha=0.12, lw=0)
        ax.set_yscale("log")
        ax.set_xlabel("house floor area (m$^2$)")
        ax.set_title(f"{kind} ms per step (p50; band to p95)", fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, fontsize=7, loc="lower center", ncol=2)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout(rect=(0, 0.1, 1, 1))
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)


def summary(values: list[float]) -> dict[str, float]:
    from eqa_app.stats import percentile as pct

    return {"p50": pct(values, 50), "p95": pct(values, 95)}


def main(argv: list[str] | None = None) -> int:
    from eqa_app.benches import harness

    ap = harness.parser(__doc__)
    ap.add_argument("--reference", type=Path, help="a checkout of github.com/Stanford-ILIAD/explore-eqa")
    ap.add_argument("--reference-python", default=sys.executable,
                    help="interpreter that can import the reference (numpy, numba, matplotlib, scipy, "
                         "scikit-image, scikit-learn); default: this one")
    ap.add_argument("--houses", default=HOUSES, help=f"generated house ids (default {HOUSES})")
    ap.add_argument("--steps", type=int, default=40, help="frames per house (default 40)")
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--seed", type=int, default=0, help="trajectory and planner seed")
    ap.add_argument("--out", type=Path, default=Path("bench/results/perf/reference_step.png"),
                    help="PNG of p50 per step against house area")
    ap.add_argument("--json", type=Path, help="also write every step's timings here")
    ap.add_argument("--plot-only", type=Path, metavar="JSON",
                    help="only draw --out again from the --json file of an earlier run")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        return worker(args.worker)
    if args.plot_only:
        saved = json.loads(args.plot_only.read_text())
        plot(saved["rows"], args.out, saved["title"])
        print(f"plot: {args.out} ({args.out.stat().st_size / 1e3:.0f} kB)")
        return 0
    if args.reference is None:
        print(f"error: --reference DIR is required; {GET_IT}", file=sys.stderr)
        return 2
    houses = [h.strip() for h in args.houses.split(",") if h.strip()]
    if not houses or not (2 <= args.steps <= 1000) or not (16 <= args.width <= 4096) or not (12 <= args.height <= 4096):
        print("error: at least one house, 2 <= steps <= 1000, 16 <= width <= 4096, 12 <= height <= 4096",
              file=sys.stderr)
        return 2
    ref_dir = args.reference.resolve()
    if not (ref_dir / "src" / "tsdf.py").is_file():
        print(f"error: {ref_dir} is not a checkout of explore-eqa (no src/tsdf.py); {GET_IT}", file=sys.stderr)
        return 2
    try:
        ref = Reference(args.reference_python, ref_dir)
    except (LookupError, OSError) as exc:
        print(f"error: the reference does not import with {args.reference_python}: {exc}\n{GET_IT}",
              file=sys.stderr)
        return 2

    from eqa_app.stats import percentile as pct
    from services.sim.library import load_or_generate

    tmp = Path(tempfile.mkdtemp(prefix="bench-reference-"))
    load_start = os.getloadavg()[0]
    commit = ref_commit(ref_dir)
    info = ref.info
    print(f"reference bench, {time.strftime('%Y-%m-%d %H:%M:%S %Z')}, {os.cpu_count()} CPUs, {uptime()}")
    print(f"reference: {ref_dir} at {commit}; worker python {info['python']}, numpy {info['numpy']}, "
          f"numba {info['numba']} ({info['numba_threads']} threads)")
    print(f"frames {args.width}x{args.height}, {args.steps} per house, seed {args.seed}; the two sides "
          "interleaved per frame")
    scenes = [load_or_generate(h, tmp / "scenes") for h in houses]
    for s in scenes:
        print(f"  {s.id}: floor area {s.floor_area_m2:.1f} m2")

    rows: list[dict[str, Any]] = []
    raw: dict[str, Any] = {}
    try:
        warm = render_frames(scenes[0], 2, args.width, args.height, args.seed)
        w_ours, w_ref, _ = run_house(ref, scenes[0], warm, args.seed, tmp, warmup=True)
        print(f"warm-up (2 frames, not counted): ours {w_ours[0]['wall_ms']:.0f} ms, reference "
              f"{w_ref[0]['wall_ms']:.0f} ms on the first frame; reference numba threading layer "
              f"{w_ref[-1].get('threading_layer', '?')}")
        for scene in sorted(scenes, key=lambda s: s.floor_area_m2):
            frames = render_frames(scene, args.steps, args.width, args.height, args.seed)
            load0 = os.getloadavg()[0]
            o, r, setup = run_house(ref, scene, frames, args.seed, tmp)
            load1 = os.getloadavg()[0]
            row = {
                "house": scene.id, "area": scene.floor_area_m2, "steps": len(frames), "load": (load0, load1),
                "ref_vol_dim": setup["vol_dim"], "ref_setup_ms": setup["setup_ms"],
                "ours": summary([x["wall_ms"] for x in o]), "ours_cpu": summary([x["cpu_ms"] for x in o]),
                "ours_thread": summary([x["thread_ms"] for x in o]),
                "ours_full": summary([x["full_wall_ms"] for x in o]),
                "ours_full_cpu": summary([x["full_cpu_ms"] for x in o]),
                "ref": summary([x["wall_ms"] for x in r]), "ref_cpu": summary([x["cpu_ms"] for x in r]),
                "ref_thread": summary([x["thread_ms"] for x in r]),
                "ref_fig": summary([x["fig_wall_ms"] for x in r]),
                "ref_nofig": summary([x["wall_ms"] - x["fig_wall_ms"] for x in r]),
                "ref_nofig_cpu": summary([x["cpu_ms"] - x["fig_cpu_ms"] for x in r]),
                "observed_m2": o[-1]["observed_m2"],
            }
            rows.append(row)
            raw[scene.id] = {"ours": o, "ref": r, "setup": setup}
            print(f"\n{scene.id}: {scene.floor_area_m2:.1f} m2, {len(frames)} steps, load {load0:.2f} -> {load1:.2f}; "
                  f"reference volume {setup['vol_dim']} voxels over {setup['bounds']} (allocated in "
                  f"{setup['setup_ms']:.0f} ms, not counted); ours observed {row['observed_m2']:.0f} m2 at the end")
            print("  ms per step                           wall p50  wall p95   CPU p50   CPU p95  main-thread p50")
            for label, w, c, th in (
                ("ours (mapper + planner)", "ours", "ours_cpu", "ours_thread"),
                ("ours + snapshot, encode/decode", "ours_full", "ours_full_cpu", None),
                ("reference", "ref", "ref_cpu", "ref_thread"),
                ("  of which its figure building", "ref_fig", None, None),
                ("reference minus figure building", "ref_nofig", "ref_nofig_cpu", None),
            ):
                cells = f"{row[w]['p50']:9.1f} {row[w]['p95']:9.1f}"
                cells += f" {row[c]['p50']:9.1f} {row[c]['p95']:9.1f}" if c else " " * 20
                cells += f" {row[th]['p50']:12.1f}" if th else ""
                print(f"  {label:36s}{cells}")
            for name, side in (("ours", o), ("reference", r)):
                keys = list(dict.fromkeys(k for x in side for k in x["stages"]))
                parts = ", ".join(f"{k} {pct([x['stages'].get(k, 0.0) for x in side], 50):.1f}" for k in keys)
                print(f"  {name} stages p50: {parts}")
            first = [x["wall_ms"] for x in o if x["first"]]
            after = [x["wall_ms"] for x in o if not x["first"]]
            print(f"  ours wall p50 when run before the reference's step {pct(first, 50):.1f} ms (n {len(first)}), "
                  f"after it {pct(after, 50):.1f} ms (n {len(after)}); prompt points >= 2 on "
                  f"{sum(x['prompt_points'] >= 2 for x in o)} steps (ours), "
                  f"{sum(x['prompt_points'] >= 2 for x in r)} steps (reference: integrate_sem ran)")
            print(f"  CPU the other side used while one was timed: the reference's process during our steps "
                  f"p50 {pct([x['other_ms'] for x in o], 50):.2f} / max {max(x['other_ms'] for x in o):.2f} ms; "
                  f"our other threads during the reference's steps p50 {pct([x['other_ms'] for x in r], 50):.2f} / "
                  f"max {max(x['other_ms'] for x in r):.2f} ms; waited for the reference's process to go quiet "
                  f"p50 {pct([x['settle_ms'] for x in r], 50):.0f} / max {max(x['settle_ms'] for x in r):.0f} ms")
            print(f"  ratio ours/reference p50: wall {row['ours']['p50'] / row['ref']['p50']:.3f}, "
                  f"CPU {row['ours_cpu']['p50'] / row['ref_cpu']['p50']:.3f}; ours + snapshot / reference "
                  f"{row['ours_full']['p50'] / row['ref']['p50']:.3f}; ours / reference minus figures "
                  f"{row['ours']['p50'] / row['ref_nofig']['p50']:.3f}")
    finally:
        ref.close()

    print(f"\nsummary ({uptime()}), ms per step, p50 (p95); ratios of p50s from this run")
    print("| house | floor m2 | steps | ours wall | ours CPU | ours + snapshot wall | reference wall | reference CPU "
          "| reference minus figure building, wall | same, CPU | ours/ref wall | ours/ref CPU "
          "| ours/(ref minus figures) wall | same, CPU |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        def cell(k: str, r: dict[str, Any] = r) -> str:
            return f"{r[k]['p50']:.1f} ({r[k]['p95']:.1f})"

        def ratio(a: str, b: str, r: dict[str, Any] = r) -> str:
            return f"{r[a]['p50'] / r[b]['p50']:.3f}"

        print(f"| {r['house']} | {r['area']:.0f} | {r['steps']} | {cell('ours')} | {cell('ours_cpu')} | "
              f"{cell('ours_full')} | {cell('ref')} | {cell('ref_cpu')} | {cell('ref_nofig')} | "
              f"{cell('ref_nofig_cpu')} | {ratio('ours', 'ref')} | {ratio('ours_cpu', 'ref_cpu')} | "
              f"{ratio('ours', 'ref_nofig')} | {ratio('ours_cpu', 'ref_nofig_cpu')} |")
    lo, hi = rows[0], rows[-1]
    if len(rows) > 1:
        print(f"largest / smallest house ({hi['area']:.0f} / {lo['area']:.0f} m2 = {hi['area'] / lo['area']:.2f}x): "
              + ", ".join(f"{name} p50 x{hi[k]['p50'] / lo[k]['p50']:.2f}" for name, k in (
                  ("ours", "ours"), ("ours + snapshot", "ours_full"), ("reference", "ref"),
                  ("reference minus figures", "ref_nofig"))))
    title = (f"mapper + planner step, {args.width}x{args.height}, {args.steps} frames per house, interleaved; "
             f"load average {load_start:.2f} -> {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs")
    plot(rows, args.out, title)
    print(f"plot: {args.out} ({args.out.stat().st_size / 1e3:.0f} kB)")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"rows": rows, "steps": raw, "reference_commit": commit,
                                          "title": title}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""HELIOS object layer benchmarks: update time against the number of Gaussians, memory of the
object-only layer against the same layer over every observed surface (paper Fig. 4), and a multi-view fusion
figure like the paper's Fig. 2.

    python -m eqa_app.benches.objects [--parts time,memory,fusion] [--width 640 --height 480] [--steps 30]
                                  [--house 5] [--out bench/results]

* time: synthetic 640x480 frames (a wall 3 m away, a detected object 2.5 m away covering a growing share of
  the image, plus Gaussians out of view) -> p50 of the update of a frame that re-observes the layer and of
  the frame that creates it, against the Gaussians in view and in the layer. Torch threads: 1 (the mapper
  shares the cores with the other services).
* memory: a 30-step trajectory through a generated house rendered by open3d; the simulated detector asked for
  the task classes (chair, table) -> layer bytes per step, and on the same frames the same layer told that
  every pixel without a detection is a "surface" class (so it models the whole observed scene, as the
  paper's full-scene variant), with its update time.
* fusion: two views of an armchair in house 5; in the first the detector mislabels it as a chair, in the
  second it reports the sofa only; the class probabilities of the armchair's and the sofa's instances after
  view 1 and after fusing view 2.

Every figure made with the simulated detector says so: "simulated detector, not a real detector". Timings on
a shared 2-core machine are noisy: compare the columns of one run, not runs.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("RERUN_TELEMETRY_ENABLED", "false")
from eqa_app.benches import harness

harness.use_test_support()

import torch  # noqa: E402
from tqdm import tqdm  # noqa: E402

from eqa_app.stats import percentile as pct  # noqa: E402
from services.mapper.objects.config import ObjectLayerConfig  # noqa: E402
from services.mapper.objects.gaussians import GaussianStore  # noqa: E402
from services.mapper.objects.layer import ObjectLayer, pixel_classes  # noqa: E402

LABEL = "simulated detector, not a real detector"


def synthetic_frame(w: int, h: int, frac: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    f = (w / 2) / math.tan(math.radians(60))
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
    depth = np.full((h, w), 3.0, np.float32)
    cls = np.full((h, w), 2, np.int64)
    side = math.sqrt(frac)
    bh, bw = max(1, int(h * side)), max(1, int(w * side))
    y0, x0 = (h - bh) // 2, (w - bw) // 2
    depth[y0 : y0 + bh, x0 : x0 + bw] = 2.5
    cls[y0 : y0 + bh, x0 : x0 + bw] = 0
    return depth, cls, K


def part_time(args: argparse.Namespace) -> dict:
    """Cases are timed round-robin (one frame of each case per round) so that load changes during the run hit
    every case alike."""
    torch.set_num_threads(1)
    cases = [(f, 0) for f in (0.02, 0.08, 0.2, 0.45, 0.9)] + [(0.2, 20_000), (0.2, 50_000)]
    built = []
    for frac, extra in tqdm(cases, desc="update time: building the layers"):
        depth, cls, K = synthetic_frame(args.width, args.height, frac)
        layer = ObjectLayer(["object", "receptacle"], ObjectLayerConfig(max_gaussians=200_000))
        if extra:  # Gaussians elsewhere in the house (behind the camera): projected and culled every frame
            g = torch.Generator().manual_seed(0)
            box = torch.tensor([20.0, 20.0, 2.0])
            means = torch.rand(extra, 3, generator=g) * box - torch.tensor([10.0, 10.0, 25.0])
            layer.store.append(GaussianStore(
                means, torch.full((extra,), 0.03), torch.full((extra,), 0.8), torch.ones(extra, 3),
                torch.full((extra,), -1, dtype=torch.long), torch.zeros(extra, dtype=torch.long),
            ))
        t0 = time.perf_counter()
        first = layer.update(depth, cls, np.eye(4), K, 1)
        built.append((frac, extra, depth, cls, K, layer, first.created, (time.perf_counter() - t0) * 1000))
    times: list[list[float]] = [[] for _ in built]
    for step in tqdm(range(2, 2 + args.repeats), desc="update time: rounds"):
        for k, (_, _, depth, cls, K, layer, _, _) in enumerate(built):
            t0 = time.perf_counter()
            layer.update(depth, cls, np.eye(4), K, step)
            times[k].append((time.perf_counter() - t0) * 1000)
    rows = []
    for (frac, _, _, _, _, layer, created, create_ms), ts in zip(built, times, strict=True):
        rows.append({
            "object_share": frac, "gaussians_in_view": created, "gaussians_total": len(layer.store),
            "create_frame_ms": round(create_ms, 1), "update_p50_ms": round(pct(ts, 50), 1),
            "update_p95_ms": round(pct(ts, 95), 1), "layer_mb": round(layer.nbytes() / 1e6, 3),
        })
        print(rows[-1])
    return {"width": args.width, "height": args.height, "render_scale": ObjectLayerConfig().render_scale,
            "torch_threads": 1, "rows": rows}


def house_frames(args: argparse.Namespace):
    from eqa_app.benches.mapper import trajectory
    from services.sim.camera import camera_pose, intrinsics
    from services.sim.housegen import generate_house
    from services.sim.render import Renderer

    scene = generate_house(args.house)
    renderer = Renderer(scene)
    K = intrinsics(args.width, args.height)
    for pose in trajectory(scene, args.steps, seed=args.seed):
        T = camera_pose(pose)
        yield pose, T, K, renderer.render(T, K, args.width, args.height), renderer


def part_memory(args: argparse.Namespace) -> dict:
    from eqa.messages import DetectRequest
    from services.vlm_scorer.detector.oracle import OracleDetector

    torch.set_num_threads(1)
    classes, th = ["chair", "table"], [0.25, 0.35]
    det = OracleDetector()
    big = ObjectLayerConfig(max_gaussians=2_000_000, max_new_per_frame=100_000)
    objects = ObjectLayer(classes, big)
    full = ObjectLayer([*classes, "surface"], big)
    from eqa.messages import EpisodeStart, Frame, Question
    from services.mapper.episode_map import EpisodeMap

    q = Question(text="Where is the chair?", choices=["a", "b"], scene=f"gen-{args.house}")
    episode_map = EpisodeMap(EpisodeStart(episode_id="bench", robot="r0", question=q, max_steps=args.steps))
    rows = []
    frames = house_frames(args)
    for step, (pose, T, K, fr, renderer) in enumerate(
        tqdm(frames, total=args.steps, desc="memory: objects vs full scene")
    ):
        t0 = time.perf_counter()  # the mapper's core step on the same frame, side by side
        episode_map.integrate(Frame(episode_id="bench", step=step, pose=pose, camera_pose=T, intrinsics=K, rgb=fr.rgb,
                           depth=fr.depth))
        episode_map.compute_frontiers()
        t_core = (time.perf_counter() - t0) * 1000
        req = DetectRequest(episode_id="bench-objects", step=step, rgb=fr.rgb, classes=classes, thresholds=th,
                            instances=fr.instances, labels=renderer.labels(fr.instances), depth=fr.depth,
                            seed=args.seed)
        dets = [(d.cls, d.score, d.full_mask(*fr.depth.shape)) for d in det.detect(req)]
        pc = pixel_classes(dets, objects.classes, fr.depth.shape)
        t0 = time.perf_counter()
        objects.update(fr.depth, pc, T, K, step)
        t_obj = (time.perf_counter() - t0) * 1000
        pc_full = pixel_classes(dets, full.classes, fr.depth.shape)
        pc_full[(pc_full == full.other) & (fr.depth > 0)] = full.class_index("surface")
        t0 = time.perf_counter()
        full.update(fr.depth, pc_full, T, K, step)
        t_full = (time.perf_counter() - t0) * 1000
        rows.append({"step": step, "objects_gaussians": len(objects.store), "objects_mb": objects.nbytes() / 1e6,
                     "full_gaussians": len(full.store), "full_mb": full.nbytes() / 1e6,
                     "objects_ms": round(t_obj, 1), "full_ms": round(t_full, 1), "mapper_core_ms": round(t_core, 1)})
    last = rows[-1]
    summary = {
        "house": f"gen-{args.house}", "steps": args.steps, "classes": classes, "seed": args.seed,
        "objects_mb_final": round(last["objects_mb"], 3), "full_mb_final": round(last["full_mb"], 3),
        "objects_gaussians_final": last["objects_gaussians"], "full_gaussians_final": last["full_gaussians"],
        "objects_ms_p50": round(pct([r["objects_ms"] for r in rows], 50), 1),
        "full_ms_p50": round(pct([r["full_ms"] for r in rows], 50), 1),
        "objects_ms_p95": round(pct([r["objects_ms"] for r in rows], 95), 1),
        "full_ms_p95": round(pct([r["full_ms"] for r in rows], 95), 1),
        "mapper_core_ms_p50": round(pct([r["mapper_core_ms"] for r in rows], 50), 1),
        "objects_gaussians_p95_in_layer": int(pct([r["objects_gaussians"] for r in rows], 95)),
    }
    print(summary)
    return {"summary": summary, "rows": rows}


def part_fusion(args: argparse.Namespace) -> dict:
    from support.objects import detect, fuse, instances_near, ring_views

    from services.sim.housegen import generate_house
    from services.sim.render import Renderer
    from services.vlm_scorer.detector.oracle import OracleDetector, OracleDetectorParams

    scene = generate_house(5)
    renderer = Renderer(scene)
    armchair = next(i for i in scene.objects() if i.category == "armchair")
    sofa = next(i for i in scene.objects() if i.category == "sofa")
    classes, th = ["chair", "sofa"], [0.25, 0.35]
    views = ring_views(scene, renderer, armchair.id, 320, 240, radius=1.8, n=24, min_pixels=200)
    # the two views that show the sofa best (both show the armchair): the sofa is detected in both
    views = sorted(views, key=lambda v: -int((v.frame.instances == sofa.id).sum()))[:2]
    if len(views) < 2:
        raise SystemExit("no two views of the armchair in house 5")
    v1, v2 = views
    honest = OracleDetector(OracleDetectorParams(recall=1.0, similar_fp=0.0, confusion=0.0, background_fp=0.0))
    d1 = detect(honest, renderer, v1, classes, th, 0)
    d1.append(("chair", 0.6, v1.frame.instances == armchair.id))  # the mislabel of view 1
    d2 = detect(honest, renderer, v2, classes, th, 1)
    layer = ObjectLayer(classes, ObjectLayerConfig(render_scale=1.0))
    fuse(layer, v1, d1, 0)
    before = {
        "armchair": instances_near(layer, armchair.position, 0.8),
        "sofa": instances_near(layer, sofa.position, 1.2),
    }
    fuse(layer, v2, d2, 1)

    def probs(layer_: ObjectLayer, info) -> list[float]:
        """S_c over the Gaussians inside the object's ground-truth box (its instance may split as it flips)."""
        lo = np.asarray(info.position) - np.asarray(info.size) / 2 - 0.1
        hi = np.asarray(info.position) + np.asarray(info.size) / 2 + 0.1
        m = layer_.store.means.numpy()
        inside = torch.as_tensor(np.all((m >= lo) & (m <= hi), axis=1))
        e = layer_.store.gamma[inside] / layer_.store.gamma[inside].sum(1, keepdim=True)
        return e.mean(0).tolist()

    layer1 = ObjectLayer(classes, ObjectLayerConfig(render_scale=1.0))
    fuse(layer1, v1, d1, 0)
    result = {
        "classes": layer.classes,
        "armchair": {"after_view_1": probs(layer1, armchair), "after_fusion": probs(layer, armchair)},
        "sofa": {"after_view_1": probs(layer1, sofa), "after_fusion": probs(layer, sofa)},
        "instances_after_view_1": {k: len(v) for k, v in before.items()},
    }
    print(json.dumps(result))
    plot_fusion(args.out / "objects_fusion.png", v1, v2, d1, d2, layer.classes, result)
    return result


def plot_fusion(path: Path, v1, v2, d1, d2, classes: list[str], result: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from scipy import ndimage

    colours = {"chair": (1.0, 1.0, 0.0), "sofa": (0.0, 1.0, 1.0)}
    fig, axes = plt.subplots(1, 4, figsize=(16, 3.8), gridspec_kw={"width_ratios": [1.3, 1.3, 1, 1]})
    for ax, v, dets, title in ((axes[0], v1, d1, "view 1: armchair detected as chair"),
                               (axes[1], v2, d2, "view 2: armchair not detected")):
        img = v.frame.rgb.astype(np.float32) / 255
        for name, score, mask in dets:
            edge = mask & ~ndimage.binary_erosion(mask, iterations=2)
            img[edge] = colours.get(name, (1, 1, 1))
            ys, xs = np.nonzero(mask)
            ax.text(xs.min(), max(ys.min() - 4, 8), f"{name} {score:.2f}", color=colours.get(name, "w"), fontsize=8)
        ax.imshow(img)
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    x = np.arange(len(classes))
    for ax, key in ((axes[2], "armchair"), (axes[3], "sofa")):
        ax.bar(x - 0.2, result[key]["after_view_1"], 0.4, label="after view 1")
        ax.bar(x + 0.2, result[key]["after_fusion"], 0.4, label="after fusing view 2")
        ax.set_xticks(x, classes)
        ax.set_ylim(0, 1)
        ax.set_title(f"{key}: class probability S_c", fontsize=9)
    axes[3].legend(fontsize=8)
    fig.suptitle(f"HELIOS multi-view fusion (house gen-5) - {LABEL}", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_time_memory(path: Path, time_res: dict | None, mem_res: dict | None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
    if time_res:
        rows = [r for r in time_res["rows"] if r["gaussians_total"] == r["gaussians_in_view"]]
        axes[0].plot([r["gaussians_in_view"] for r in rows], [r["update_p50_ms"] for r in rows], "o-",
                     label="re-observing frame (p50)")
        axes[0].plot([r["gaussians_in_view"] for r in rows], [r["create_frame_ms"] for r in rows], "s--",
                     label="creating frame")
        axes[0].set_xlabel("Gaussians in view")
        axes[0].set_ylabel("update time per frame (ms)")
        axes[0].set_title(f"{time_res['width']}x{time_res['height']}, render scale {time_res['render_scale']}, "
                          "1 torch thread", fontsize=9)
        axes[0].legend(fontsize=8)
    if mem_res:
        rows = mem_res["rows"]
        axes[1].plot([r["step"] for r in rows], [r["objects_mb"] for r in rows], label="objects only (HELIOS)")
        axes[1].plot([r["step"] for r in rows], [r["full_mb"] for r in rows], label="every observed surface")
        axes[1].set_xlabel("step")
        axes[1].set_ylabel("layer memory (MB)")
        axes[1].set_title(f"memory, {mem_res['summary']['house']} ({LABEL})", fontsize=9)
        axes[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = harness.parser(__doc__)
    ap.add_argument("--parts", default="time,memory,fusion", help="comma-separated: time, memory, fusion")
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--steps", type=int, default=30, help="memory: trajectory length")
    ap.add_argument("--house", type=int, default=5, help="memory: generated house seed")
    ap.add_argument("--seed", type=int, default=1, help="memory: detector and trajectory seed (an evaluation seed)")
    ap.add_argument("--repeats", type=int, default=9, help="time: frames timed per case (round-robin)")
    ap.add_argument("--out", type=Path, default=harness.RESULTS)
    args = ap.parse_args(argv)
    parts = {p.strip() for p in args.parts.split(",") if p.strip()}
    unknown = parts - {"time", "memory", "fusion"}
    if unknown:
        ap.error(f"unknown parts {sorted(unknown)}: choose from time, memory, fusion")
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "objects.json"
    out: dict = json.loads(path.read_text()) if path.exists() else {}  # parts not run now are kept
    out["label"] = LABEL
    if "time" in parts:
        out["time"] = part_time(args)
    if "memory" in parts:
        out["memory"] = part_memory(args)
    if "fusion" in parts:
        out["fusion"] = part_fusion(args)
    if "time" in parts or "memory" in parts:
        plot_time_memory(args.out / "objects_time_memory.png", out.get("time"), out.get("memory"))
    path.write_text(json.dumps(out, indent=1))
    print(f"wrote {path} and the PNGs beside it")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

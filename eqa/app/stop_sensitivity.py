"""Stopping under a miscalibrated perception model: record each episode's perceptions once, re-score offline.

SIMULATED PERCEPTION MODEL, not a VLM. The oracle's miscalibration modes (``OracleParams.miscal_*``, documented
in ``services/vlm_scorer/backends/oracle.py``) change only the answer distribution f and the relevance Rel of a
step, never LSV / GSV, so the robot's path is the same at every level. This tool therefore:

1. **records** full-length episodes (``max_steps``) with the pure cores in one process per worker (sim render ->
   mapper -> oracle scorer -> planner, the functions the services call; no bus, no store, as
   ``bench/tune_oracle.py``), keeping per step what the oracle perceived: the target instances and the
   related-but-wrong ones with their image share and distance, the view's clutter, and the level-0 scores;
2. **re-scores** those perceptions at any miscalibration level (the draws are seeded per (question, step) as in
   the service; at level 0 the re-scored f and Rel are checked equal to the recorded ones) into
   :class:`services.stopper.calibration.Trace` objects that the benchmark's evaluation replays through the
   stopper's own decision function.

    python bench/stop_sensitivity.py record --seeds 1 2 3 --limit 60      # once (minutes)
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import pickle
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

log = logging.getLogger("stop_sensitivity")

DEFAULT_DIR = Path("var/sensitivity")


@dataclasses.dataclass
class PerceptionStep:
    targets: list[Any]  # oracle View tuples (label, image share, distance)
    related: list[Any]
    clutter: float
    probs: list[float]  # level-0 scores as the service computed them
    relevance: float


@dataclasses.dataclass
class PerceptionEpisode:
    question: Any  # eqa.messages.Question (with its ground truth; the oracle never reads it)
    seed: int
    strategy: str
    steps: list[PerceptionStep]
    seconds: float = 0.0


def benchmark_questions(seed: int, split: str, limit: int | None, scenes_dir: Any) -> list[Any]:
    """The ``split`` questions of benchmark ``seed``; ``limit`` keeps the category mix (round-robin)."""
    from services.sim.questions import benchmark

    bench = benchmark(seed=seed, scenes_dir=scenes_dir)
    qs = {"calibration": bench.calibration, "test": bench.test}[split]
    if limit is None or limit >= len(qs):
        return list(qs)
    by_cat: dict[str, list[Any]] = {}
    for q in qs:
        by_cat.setdefault(q.category or "", []).append(q)
    out: list[Any] = []
    while len(out) < limit:
        for cat in sorted(by_cat):
            if by_cat[cat] and len(out) < limit:
                out.append(by_cat[cat].pop(0))
    return out


def run_episode(args: tuple[Any, str, int, int]) -> PerceptionEpisode:
    """One full-length episode with the pure cores in this process (the services' step functions)."""
    try:
        from eqa.app.benchmark_runner import question_seed
    except ImportError:  # before the application layer moved (issue 18)
        from eqa.harness import question_seed  # type: ignore[no-redef]
    from eqa.messages import EpisodeStart, Frame, ScoreRequest
    from eqa.settings import Settings
    from services.mapper.episode_map import EpisodeMap
    from services.planner.sampling import step_rng
    from services.planner.step import Memory, plan_step
    from services.sim import camera
    from services.sim.motion import pose_error
    from services.sim.render import Renderer
    from services.sim.service import load_scene
    from services.vlm_scorer.backends.oracle import OracleBackend, parse_target

    question, strategy, w, h = args
    t0 = time.monotonic()
    settings = Settings()
    scene = load_scene(settings, question.scene)
    renderer = Renderer(scene)
    oracle = OracleBackend.from_settings(settings)
    if oracle.p.miscalibrated:
        raise RuntimeError("record with the oracle at miscalibration level 0 (unset EQA_ORACLE_MISCAL_*)")
    seed = question_seed(question.id)
    start = EpisodeStart(episode_id=f"sens-{question.id}", robot="r0", question=question, strategy=strategy,
                         max_steps=question.max_steps, seed=seed)
    emap = EpisodeMap(start)
    K = camera.intrinsics(w, h)
    pose = question.start_pose
    memory = Memory()
    target = parse_target(question)
    blind = question.model_copy(update={"answer": None, "evidence_ids": []})
    steps: list[PerceptionStep] = []
    for step in range(question.max_steps):
        cam = camera.camera_pose(pose)
        r = renderer.render(cam, K, w, h)
        frame = Frame(episode_id=start.episode_id, step=step, pose=pose, camera_pose=cam, intrinsics=K,
                      rgb=r.rgb, depth=r.depth, instances=r.instances, labels=renderer.labels(r.instances))
        emap.integrate(frame)
        req = ScoreRequest(episode_id=start.episode_id, step=step, question=blind, rgb=frame.rgb,
                           prompt_points=emap.prompts, instances=frame.instances, labels=frame.labels,
                           depth=frame.depth, seed=seed)
        scores = oracle.score(req)
        steps.append(PerceptionStep(oracle.target_views(req, target), oracle.related_views(req, target),
                                    oracle.clutter(req), list(scores.answer_probs), float(scores.relevance)))
        emap.apply_scores(scores.lsv, scores.gsv)
        emap.compute_frontiers()
        mu = emap.map_update()
        if step + 1 >= question.max_steps:
            break
        plan = None
        for attempt in range(4):
            plan = plan_step(mu.grid, mu.free, mu.occupied, mu.pose, mu.frontiers, strategy, memory,
                             step_rng(seed, step, attempt))
            if plan.done or plan.pose is None or pose_error(scene, plan.pose) is None:
                break
            memory.refused.append((plan.pose.x, plan.pose.y))
        if plan is None or plan.done or plan.pose is None:
            break
        memory, pose = plan.memory, plan.pose
    return PerceptionEpisode(question, seed, strategy, steps, time.monotonic() - t0)


def recording_path(out: Path, seed: int, split: str, limit: int | None, strategy: str, size: str) -> Path:
    return out / f"seed{seed}-{split}-{'all' if limit is None else limit}-{strategy}-{size}.pkl"


def record(questions: list[Any], strategy: str, w: int, h: int, workers: int, path: Path,
           progress: bool = True) -> list[PerceptionEpisode]:
    """Record ``questions`` (resumable: a partial file is extended, never recomputed)."""
    from tqdm import tqdm

    done: list[PerceptionEpisode] = pickle.loads(path.read_bytes()) if path.is_file() else []
    have = {e.question.id for e in done}
    todo = [q for q in questions if q.id not in have]
    if todo:
        t0 = time.monotonic()
        path.parent.mkdir(parents=True, exist_ok=True)
        with ProcessPoolExecutor(workers) as pool, tqdm(total=len(questions), initial=len(questions) - len(todo),
                                                       desc=path.stem, unit="ep", file=sys.stderr,
                                                       disable=not progress) as bar:
            for i, ep in enumerate(pool.map(run_episode, [(q, strategy, w, h) for q in todo])):
                done.append(ep)
                bar.update(1)
                if i % 10 == 9:  # checkpoint
                    _write(path, done)
        _write(path, done)
        log.info("%s: %d episodes in %.1f min", path.name, len(todo), (time.monotonic() - t0) / 60)
    by_id = {e.question.id: e for e in done}
    return [by_id[q.id] for q in questions if q.id in by_id]


def _write(path: Path, episodes: list[PerceptionEpisode]) -> None:
    tmp = path.with_suffix(".tmp")
    tmp.write_bytes(pickle.dumps(episodes))
    tmp.replace(path)


def rescore(ep: PerceptionEpisode, params: Any, check_level0: bool = False) -> Any:
    """The episode's :class:`Trace` under the oracle knobs ``params`` (f and Rel re-drawn as the service
    draws them). ``check_level0``: assert that the level-0 re-score equals what was recorded."""
    import numpy as np

    from eqa.messages import Question, ScoreRequest
    from services.stopper.calibration import Trace, TraceStep
    from services.vlm_scorer.backends.oracle import OracleBackend, parse_target

    q: Question = ep.question
    oracle = OracleBackend(params)
    t = parse_target(q)
    blind = q.model_copy(update={"answer": None, "evidence_ids": []})
    choices = list(q.choices)
    steps = []
    for step, s in enumerate(ep.steps):
        req = ScoreRequest.model_construct(episode_id="rescore", step=step, question=blind, seed=ep.seed,
                                           rgb=np.zeros((1, 1, 3), np.uint8))
        probs, rel = oracle.miscalibrated_scores(req, choices, t, s.targets, s.related, s.clutter)
        if check_level0 and (probs != s.probs or rel != s.relevance):
            raise AssertionError(f"{q.id} step {step}: level-0 re-score differs from the recorded scores")
        steps.append(TraceStep(answer_probs=probs, relevance=rel))
    return Trace(question_id=q.id, scene=q.scene, category=q.category, choices=choices, answer=q.answer,
                 max_steps=q.max_steps, strategy=ep.strategy, steps=steps)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("record", help="record perceptions of the calibration and test splits")
    r.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    r.add_argument("--limit", type=int, default=None, help="questions per split and seed (category mix kept); "
                   "the test split gets 2/3 of it, as eqa bench stop")
    r.add_argument("--strategy", default="semantic")
    r.add_argument("--size", default="320x240")
    r.add_argument("--workers", type=int, default=1)
    r.add_argument("--out", type=Path, default=DEFAULT_DIR)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    from eqa.settings import Settings

    settings = Settings()
    w, h = (int(v) for v in args.size.split("x"))
    for seed in args.seeds:
        for split in ("calibration", "test"):
            lim = args.limit if split == "calibration" or args.limit is None else max(1, args.limit * 2 // 3)
            qs = benchmark_questions(seed, split, lim, settings.scenes_path)
            record(qs, args.strategy, w, h, args.workers,
                   recording_path(args.out, seed, split, lim, args.strategy, args.size))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

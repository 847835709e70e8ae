"""Find what loses the semantic signal, on the TUNING seed only: exploration variants side by side, in-process.

Runs full-length episodes with the pure cores in one process per worker (sim render -> mapper -> oracle scorer
-> planner: the functions the services call, no bus, no store) for several *variants* (a strategy plus
mapper / planner knob overrides) on the same questions, and prints per variant: success at 0.5 T and T
(Explore-EQA Fig. 7: argmax f at the most relevant step so far), the share of episodes that see the evidence
(the simulated perception model's evidence quality > 0 on the asked object) within 0.25 / 0.5 / 1.0 T, the
median first-evidence step (x T), and paired sign tests against the first variant.

It refuses the evaluation seeds (``eqa.seeds.check_tuning_seed``): knobs chosen by looking at these numbers
are chosen on seed 11 and the published figures come from seeds 1, 2, 3 through the real services
(``eqa bench explore --seeds 1 2 3``). Scorer: the SIMULATED PERCEPTION MODEL (oracle), not a VLM.

    python -m eqa_app.benches.tune_explore --limit 60 --variant fbe --variant semantic \\
        --variant semantic:planner.distance_decay_m=0 --variant target_oracle --variant perfect_sv

A variant is ``STRATEGY[:KNOB=VALUE,...]`` with knobs ``mapper.<MapperConfig field>``,
``planner.<PlannerParams field>``, ``prompt.<PromptConfig field>`` or ``frontier.<FrontierConfig field>``.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from eqa_app.benches import harness

log = logging.getLogger("tune_explore")


@dataclasses.dataclass
class Episode:
    question_id: str
    category: str
    max_steps: int
    answer: str
    f: list[list[float]]
    rel: list[float]
    quality: list[float]  # best evidence quality of the asked object(s) per step (0: not seen)
    path_m: float = 0.0
    # per sampled planning step: (P(chosen frontier set) of the frontier nearest the target under this
    # variant, the same under fbe's uniform x distance decay, under the Eq. A6 weights alone, log-weight
    # spread (max - min ln w) over the candidates, distance-decay spread ((max - min geodesic) / decay))
    diag: list[tuple[float, float, float, float, float]] = dataclasses.field(default_factory=list)
    # per step, for the evidence-ceiling diagnosis (--ceiling): distance (m) from the robot to the nearest
    # ground-truth target (Question.targets), whether that target lies inside the camera's horizontal field of
    # view, and the largest pixel count of an asked object in the frame (0: not in the image at all)
    geo: list[tuple[float, bool, int]] = dataclasses.field(default_factory=list)
    objects: int = 0  # evidence objects of the question (0: the evidence is a room, e.g. "is there a X? no")


def parse_variant(text: str) -> tuple[str, dict[str, Any]]:
    strategy, _, rest = text.partition(":")
    knobs: dict[str, Any] = {}
    for item in filter(None, rest.split(",")):
        k, _, v = item.partition("=")
        if "." not in k:
            raise SystemExit(f"knob {k!r}: write mapper.X, planner.X, prompt.X or frontier.X")
        knobs[k] = None if v.lower() == "none" else float(v)
    return strategy, knobs


def configs(knobs: dict[str, Any]) -> tuple[Any, Any]:
    from services.mapper.episode_map import MapperConfig
    from services.mapper.frontiers import FrontierConfig
    from services.mapper.prompt_points import PromptConfig
    from services.planner.step import PlannerParams

    groups: dict[str, dict[str, Any]] = {"mapper": {}, "planner": {}, "prompt": {}, "frontier": {}}
    for k, v in knobs.items():
        g, name = k.split(".", 1)
        ints = ("count", "max_commit_steps", "max_cluster_cells", "view_bins", "view_agree")
        groups[g][name] = int(v) if name in ints and v else v
    mc = MapperConfig(**groups["mapper"])
    if groups["prompt"]:
        mc = dataclasses.replace(mc, prompt=PromptConfig(**groups["prompt"]))
    if groups["frontier"]:
        mc = dataclasses.replace(mc, frontier=FrontierConfig(**groups["frontier"]))
    return mc, PlannerParams(**groups["planner"])


def run_episode(args: tuple[Any, str, dict[str, Any], int, int]) -> Episode:
    """One full-length episode with the pure cores in this process (:func:`eqa_app.core_runner.run_episode_loop`)."""
    from eqa.messages import EpisodeStart
    from eqa.settings import Settings
    from eqa_app.benchmark_runner import question_seed, yardstick_paths
    from eqa_app.core_runner import EpisodeCores, StepHooks, run_episode_loop
    from services.mapper.episode_map import EpisodeMap
    from services.sim import camera
    from services.sim.library import load_or_generate
    from services.sim.render import Renderer
    from services.vlm_scorer.backends.oracle import OracleBackend, parse_target

    question, strategy, knobs, w, h, horizon = args
    mconf, pparams = configs(knobs)
    budget = math.ceil(horizon * int(question.max_steps))
    settings = Settings()
    scene = load_or_generate(question.scene, settings.scenes_path)
    oracle = OracleBackend.from_settings(settings)
    seed = question_seed(question.id)
    start = EpisodeStart(episode_id=f"tune-{question.id}", robot="r0", question=question, strategy=strategy,
                         max_steps=question.max_steps, seed=seed,
                         target_paths=yardstick_paths(question, strategy, settings.scenes_path, scene))
    target = parse_target(question)
    f: list[list[float]] = []
    rel: list[float] = []
    qual: list[float] = []
    diag: list[tuple[float, float, float, float, float]] = []
    geo: list[tuple[float, bool, int]] = []
    path = [0.0]
    ev = set(question.evidence_ids)
    half_fov = math.radians(camera.HFOV_DEG) / 2

    class Diagnosis(StepHooks):
        def scored(self, step: int, frame: Any, request: Any, scores: Any) -> None:
            views = [v for v in oracle.target_views(request, target) if not ev or v[0].id in ev]
            seen = oracle.seen_targets(views)
            qual.append(max((q for _, q in seen), default=0.0))
            pixels = max((round(share * w * h) for _, share, _ in views), default=0)
            geo.append(_geometry(frame.pose, question.targets, half_fov, pixels))
            f.append(list(scores.answer_probs))
            rel.append(float(scores.relevance))

        def moved(self, step: int, step_map: Any, plan: Any, before: Any) -> None:
            if plan.sampled and plan.geodesic_m and question.targets:
                diag.append(_diag(step_map.frontiers, plan, question.targets, pparams.distance_decay_m))
            path[0] += math.hypot(plan.pose.x - before.x, plan.pose.y - before.y)

    cores = EpisodeCores(scene, Renderer(scene), oracle, EpisodeMap(start, mconf), pparams, w, h)
    run_episode_loop(question, strategy, cores, episode_id=start.episode_id, seed=seed, steps=budget,
                     hooks=Diagnosis())
    assert question.answer is not None
    return Episode(question.id, question.category or "", int(question.max_steps), question.answer, f, rel, qual,
                   path[0], diag, geo, len(question.evidence_ids))


def _geometry(pose: Any, targets: list[tuple[float, float]], half_fov: float, pixels: int) -> tuple[float, bool, int]:
    """(distance to the nearest target, whether it is inside the horizontal field of view, asked-object pixels)."""
    if not targets:
        return math.inf, False, pixels
    d, x, y = min((math.hypot(x - pose.x, y - pose.y), x, y) for x, y in targets)
    bearing = math.atan2(y - pose.y, x - pose.x) - pose.yaw
    return d, abs(math.atan2(math.sin(bearing), math.cos(bearing))) <= half_fov, pixels


def _diag(frontiers: list[Any], plan: Any, targets: list[tuple[float, float]], decay: float | None
          ) -> tuple[float, float, float, float, float]:
    geo = np.asarray(plan.geodesic_m, dtype=np.float64)
    cand = np.isfinite(geo)
    t = np.asarray(targets, dtype=np.float64)
    dt = np.array([np.sqrt(((t - np.array([fr.x, fr.y])) ** 2).sum(-1)).min() for fr in frontiers])
    dt = np.where(cand, dt, np.inf)
    best = int(np.argmin(dt))
    p = np.asarray(plan.probabilities, dtype=np.float64)
    dec = np.exp(-(geo - geo[cand].min()) / decay) if decay else np.ones_like(geo)
    dec = np.where(cand, dec, 0.0)
    fbe = dec / dec.sum()
    w = np.array([fr.weight for fr in frontiers], dtype=np.float64)
    w = np.where(cand, w, 0.0)
    pw = w / w.sum() if w.sum() > 0 else fbe
    lw = np.log(np.maximum(w[cand], 1e-300))
    spread_d = float((geo[cand].max() - geo[cand].min()) / decay) if decay else 0.0
    return float(p[best]), float(fbe[best]), float(pw[best]), float(lw.max() - lw.min()), spread_d


def answer_at(ep: Episode, budget: float) -> bool:
    from eqa.messages import letters
    from services.stopper.conformal import fallback_answer

    n = max(1, min(math.floor(budget * ep.max_steps + 1e-9), len(ep.rel)))
    f, r = np.asarray(ep.f[:n]), np.asarray(ep.rel[:n])
    return letters(len(ep.f[0]))[fallback_answer(f, r)] == ep.answer


def first_evidence(ep: Episode) -> float | None:
    k = next((i for i, q in enumerate(ep.quality) if q > 0), None)
    return None if k is None else k / ep.max_steps


NEAR_M = 3.0  # "came near the evidence": within 3 m of an evidence object's centre (the planner's step length)


def ceiling_reason(ep: Episode, budget: float = 1.0) -> str:
    """Why an episode did or did not see the evidence within ``budget`` x T (the evidence-ceiling diagnosis):
    ``seen``; ``room`` (no evidence object: the evidence is a room); ``small`` (an asked object was in the image
    but under the perception model's pixel threshold or too far); ``near, faced`` (within NEAR_M, inside the
    horizontal field of view, yet no pixel of it: occluded, or outside the 30 deg down-tilted camera's vertical view);
    ``near, not faced`` (within NEAR_M, never inside the field of view); ``never near`` (never within NEAR_M)."""
    n = min(len(ep.quality), math.floor(budget * ep.max_steps + 1e-9))
    if any(q > 0 for q in ep.quality[:n]):
        return "seen"
    if not ep.objects:
        return "room"
    geo = ep.geo[:n]
    if any(px > 0 for _, _, px in geo):
        return "small"
    near = [infov for d, infov, _ in geo if d <= NEAR_M]
    if not near:
        return "never near"
    return "near, faced" if any(near) else "near, not faced"


CEILING_REASONS = ("seen", "small", "near, faced", "near, not faced", "never near", "room")


def summarise(name: str, eps: list[Episode], base: list[Episode] | None) -> dict[str, Any]:
    from eqa_app.stats import sign_test_p

    out: dict[str, Any] = {"variant": name, "n": len(eps)}
    for b in (0.5, 1.0):
        out[f"success@{b}"] = float(np.mean([answer_at(e, b) for e in eps]))
    fe = [first_evidence(e) for e in eps]
    for b in (0.25, 0.5, 1.0):
        out[f"evidence@{b}"] = float(np.mean([x is not None and x < b for x in fe]))
    seen = sorted(x for x in fe if x is not None)
    # median first-evidence step over all episodes (never seen = beyond T)
    allv = sorted(x if x is not None else math.inf for x in fe)
    out["median_first_evidence"] = float(allv[len(allv) // 2]) if allv else math.nan
    out["mean_first_evidence_if_seen"] = float(np.mean(seen)) if seen else math.nan
    rows = [x for e in eps for x in getattr(e, "diag", [])]  # (older recordings have no diag)
    d = np.asarray(rows) if rows else np.zeros((0, 5))
    if len(d):
        out["p_best"] = float(d[:, 0].mean())  # mass on the frontier nearest the target, this variant
        out["p_best_fbe"] = float(d[:, 1].mean())  # the same frontiers under uniform x decay
        out["p_best_weights_only"] = float(d[:, 2].mean())
        out["log_w_spread_median"] = float(np.median(d[:, 3]))
        out["decay_spread_median"] = float(np.median(d[:, 4]))
    if base is not None:
        byid = {e.question_id: e for e in base}
        for b in (0.5, 1.0):
            a_only = sum(answer_at(e, b) and not answer_at(byid[e.question_id], b) for e in eps)
            b_only = sum(answer_at(byid[e.question_id], b) and not answer_at(e, b) for e in eps)
            out[f"vs_first@{b}"] = (a_only, b_only, sign_test_p(a_only, b_only))
        ea = sum(first_evidence(e) is not None and first_evidence(byid[e.question_id]) is None for e in eps)
        eb = sum(first_evidence(e) is None and first_evidence(byid[e.question_id]) is not None for e in eps)
        out["evidence_vs_first"] = (ea, eb, sign_test_p(ea, eb))
    return out


def tuning_questions(seed: int, split: str, limit: int | None, settings: Any) -> list[Any]:
    """The benchmark questions of ``seed`` (category mix kept under ``limit``, round robin)."""
    from eqa_app.bench_cli import _benchmark

    bench = _benchmark(seed, settings)
    qs = {"calibration": bench.calibration, "test": bench.test, "all": bench.calibration + bench.test}[split]
    if limit is None:
        return qs
    by_cat: dict[str, list[Any]] = {}
    for q in qs:
        by_cat.setdefault(q.category or "", []).append(q)
    mixed: list[Any] = []
    while len(mixed) < min(limit, len(qs)):
        for cat in sorted(by_cat):
            if by_cat[cat] and len(mixed) < limit:
                mixed.append(by_cat[cat].pop(0))
    return mixed


def main(argv: list[str] | None = None) -> int:
    from eqa.seeds import TUNING_SEED, check_tuning_seed

    p = harness.parser(__doc__)
    p.add_argument("--seed", type=int, default=TUNING_SEED, help=f"benchmark seed (default the tuning seed "
                   f"{TUNING_SEED}; evaluation seeds are refused)")
    p.add_argument("--variant", action="append", default=[], help="STRATEGY[:knob=value,...] (repeatable)")
    p.add_argument("--limit", type=int, default=60, help="questions (category mix kept)")
    p.add_argument("--split", default="all", choices=["calibration", "test", "all"])
    p.add_argument("--size", default="320x240")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--out", default="var/tune_explore", help="episodes are cached here per variant")
    p.add_argument("--horizon", type=float, default=1.0,
                   help="run each episode to HORIZON x T steps (default 1; e.g. 2 to see whether the step budget "
                        "T is what limits the evidence); success and evidence 'within T' are read from its first T "
                        "steps, which do not depend on the horizon")
    p.add_argument("--ceiling", action="store_true",
                   help="also print the evidence-ceiling diagnosis per variant: why episodes did not see an asked "
                        "object within T (never near it, near but not facing it, facing it but occluded or out of "
                        "the tilted view, in the image under the pixel threshold), and the share seen within "
                        "HORIZON x T")
    args = p.parse_args(argv)
    if not 1.0 <= args.horizon <= 4.0:
        p.error("--horizon must be between 1 and 4")
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        check_tuning_seed(args.seed)
    except ValueError as exc:
        p.error(str(exc))
    import pickle

    from tqdm import tqdm

    from eqa.settings import Settings

    w, h = (int(v) for v in args.size.split("x"))
    qs = tuning_questions(args.seed, args.split, args.limit, Settings())
    variants = args.variant or ["fbe", "semantic"]
    results: dict[str, list[Episode]] = {}
    outdir = Path(args.out)
    outdir.mkdir(parents=True, exist_ok=True)
    for v in variants:
        strategy, knobs = parse_variant(v)
        tag = "" if args.horizon == 1.0 else f"-h{args.horizon:g}"
        cache = outdir / f"seed{args.seed}-{args.split}-{args.size}{tag}-{v.replace('/', '_')}.pkl"
        have: dict[str, Episode] = pickle.loads(cache.read_bytes()) if cache.exists() else {}
        todo = [q for q in qs if q.id not in have]
        t0 = time.monotonic()
        if todo:
            with ProcessPoolExecutor(args.workers) as pool:
                jobs = [(q, strategy, knobs, w, h, args.horizon) for q in todo]
                for ep in tqdm(pool.map(run_episode, jobs), total=len(todo), file=sys.stderr, unit="ep", desc=v[:40]):
                    have[ep.question_id] = ep
                    cache.write_bytes(pickle.dumps(have))
            log.info("%s: %d episodes in %.1f min", v, len(todo), (time.monotonic() - t0) / 60)
        results[v] = [have[q.id] for q in qs]
    base = results[variants[0]]
    print(f"seed {args.seed} ({args.split}, {len(qs)} questions, {args.size}); scorer: oracle (SIMULATED PERCEPTION "
          "MODEL, not a VLM); evidence = the asked object perceived (quality > 0)")
    rows = []
    for i, v in enumerate(variants):
        r = summarise(v, results[v], None if i == 0 else base)
        rows.append(r)
        extra = ""
        if i:
            a, b, pv = r["vs_first@0.5"]
            c, d, pw = r["vs_first@1.0"]
            e, g, pe = r["evidence_vs_first"]
            extra = f"  vs first: 0.5T {a}/{b} p{pv:.2g}  T {c}/{d} p{pw:.2g}  evidence {e}/{g} p{pe:.2g}"
        print(f"{v[:60]:<60} succ {r['success@0.5']:.3f} {r['success@1.0']:.3f}  ev@.25/.5/1 "
              f"{r['evidence@0.25']:.2f} {r['evidence@0.5']:.2f} {r['evidence@1.0']:.2f}  "
              f"med first {r['median_first_evidence']:.2f}{extra}")
        if "p_best" in r:
            print(f"    P(frontier nearest the target): this {r['p_best']:.3f}, fbe-with-decay {r['p_best_fbe']:.3f}, "
                  f"weights alone {r['p_best_weights_only']:.3f}; median spread ln w {r['log_w_spread_median']:.2f}, "
                  f"decay {r['decay_spread_median']:.2f}")
        if args.ceiling:
            r["ceiling"] = {b: {k: sum(ceiling_reason(e, b) == k for e in results[v]) for k in CEILING_REASONS}
                            for b in sorted({1.0, args.horizon})}
            for b, counts in r["ceiling"].items():
                print(f"    within {b:g} T: " + ", ".join(f"{k} {c}" for k, c in counts.items()))
    if args.ceiling:  # what any strategy could reach: eqa_app/ceiling.py (the same numbers as eqa bench --ceiling)
        from eqa_app.ceiling import benchmark_ceilings, ceiling_cdf

        ceilings = benchmark_ceilings(qs, Settings(), w, h)
        shares = ceiling_cdf(ceilings, [0.25, 0.5, 1.0])
        print(f"ceiling (evidence perceivable at all, {len(ceilings)} questions): within 0.25 / 0.5 / 1 T "
              + " / ".join(f"{v:.2f}" for v in shares))
        within = {f"evidence@{b}": v for b, v in zip((0.25, 0.5, 1.0), shares, strict=True)}
        rows.append({"variant": "ceiling", "n": len(ceilings), **within})
    (outdir / f"summary-seed{args.seed}.json").write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

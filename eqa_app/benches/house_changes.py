"""How much the simulator's house changes touch the benchmark's questions: for each question of a benchmark split,
whether rounds 1..k of changes of its house (``gen-<seed>-c<k>``, services/sim/changes.py) affect it (its answer or
its evidence changed), change its answer, or leave it without ground truth; and the time to build a round.

    python -m eqa_app.benches.house_changes --seeds 1 2 3 --rounds 4 --split test \
        --out bench/results/homes-api/house-changes.json

Ground truth of the simulator's scene graph only: no scorer, detector or robot runs. The figures say how many of a
home's questions a benchmark with changes between them asks about something that changed (the denominator of a
wrong-singleton rate on changed questions).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from collections import Counter, defaultdict
from pathlib import Path

from eqa_app.stats import wilson_ci
from services.sim.change_impact import impact
from services.sim.changes import MAX_ROUNDS, next_house
from services.sim.library import load_or_generate
from services.sim.questions import benchmark


def share(k: int, n: int) -> dict[str, float | int]:
    lo, hi = wilson_ci(k, n)
    return {"k": k, "n": n, "share": round(k / n, 4) if n else 0.0, "ci95": [round(lo, 4), round(hi, 4)]}


def run_seed(seed: int, rounds: int, split: str, scenes_dir: Path, limit: int | None) -> dict[str, object]:
    bench = benchmark(seed, scenes_dir)
    questions = bench.test if split == "test" else bench.calibration if split == "calibration" else bench.questions
    questions = questions[:limit] if limit else questions
    by_scene: dict[str, list] = defaultdict(list)
    for q in questions:
        by_scene[q.scene].append(q)
    rows = []
    round_s: list[float] = []
    kinds: Counter[str] = Counter()
    for scene_id, qs in sorted(by_scene.items()):
        house = load_or_generate(scene_id, scenes_dir)
        changes = []
        for k in range(1, rounds + 1):
            t0 = time.perf_counter()
            house, made = next_house(house, k)
            round_s.append(time.perf_counter() - t0)
            changes += made
            kinds.update(c.kind for c in made)
            for q in qs:
                im = impact(q, changes, house)
                rows.append({"k": k, "category": q.category, "affected": im.affected,
                             "answer_changed": im.answer_changed and im.question is not None,
                             "no_ground_truth": im.question is None})
    out: dict[str, object] = {"seed": seed, "split": split, "questions": len(questions), "houses": len(by_scene),
                              "changes_made": dict(sorted(kinds.items())),
                              "round_build_s_mean": round(sum(round_s) / max(1, len(round_s)), 4)}
    out["by_rounds"] = summarize(rows, rounds)
    out["_rows"] = rows
    return out


def summarize(rows: list[dict], rounds: int) -> dict[str, dict[str, object]]:
    out: dict[str, dict[str, object]] = {}
    for k in range(1, rounds + 1):
        at = [r for r in rows if r["k"] == k]
        n = len(at)
        entry: dict[str, object] = {
            "affected": share(sum(r["affected"] for r in at), n),
            "answer_changed": share(sum(r["answer_changed"] for r in at), n),
            "no_ground_truth": share(sum(r["no_ground_truth"] for r in at), n),
        }
        cats = sorted({r["category"] for r in at})
        entry["affected_by_category"] = {
            c: share(sum(r["affected"] for r in at if r["category"] == c), sum(r["category"] == c for r in at))
            for c in cats
        }
        out[str(k)] = entry
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--rounds", type=int, default=4, help=f"k = 1..rounds (at most {MAX_ROUNDS})")
    ap.add_argument("--split", choices=["test", "calibration", "all"], default="test")
    ap.add_argument("--limit", type=int, default=None, help="first N questions of the split per seed")
    ap.add_argument("--scenes-dir", default=None, help="default: a temporary directory")
    ap.add_argument("--out", default=None, help="JSON summary")
    args = ap.parse_args(argv)
    if not 1 <= args.rounds <= MAX_ROUNDS:
        ap.error(f"--rounds must be 1..{MAX_ROUNDS}")
    with tempfile.TemporaryDirectory() as tmp:
        scenes_dir = Path(args.scenes_dir) if args.scenes_dir else Path(tmp)
        t0 = time.perf_counter()
        per_seed = [run_seed(s, args.rounds, args.split, scenes_dir, args.limit) for s in args.seeds]
        wall = time.perf_counter() - t0
    rows = [r for s in per_seed for r in s.pop("_rows")]  # type: ignore[union-attr]
    summary = {
        "command": "python -m eqa_app.benches.house_changes " + " ".join(sys.argv[1:] if argv is None else argv),
        "what": "share of benchmark questions whose answer or evidence rounds 1..k of house changes touch; "
                "simulator ground truth (scene graph), no perception model",
        "seeds": args.seeds, "split": args.split, "rounds": args.rounds,
        "pooled": summarize(rows, args.rounds), "per_seed": per_seed, "wall_s": round(wall, 1),
    }
    text = json.dumps(summary, indent=1)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(text + "\n")
    for k, e in summary["pooled"].items():
        a, c, g = e["affected"], e["answer_changed"], e["no_ground_truth"]
        print(f"k={k}: affected {a['share']:.3f} {a['ci95']} (n={a['n']}), answer changed {c['share']:.3f}, "
              f"no ground truth {g['share']:.3f}")
    print(f"wall {wall:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

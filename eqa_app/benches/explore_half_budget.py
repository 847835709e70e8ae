"""Does a strategy reach at a fraction of the budget what ``semantic`` reaches at the full budget T?

Reads stored trace sets (``eqa bench explore`` exports them as ``<dir>/bench-<strategy>-oracle-320x240-seed<S>-x<V>
-cores.jsonl.gz``) of the evaluation seeds and pairs, question by question, the strategy's answer at ``--budget``
x T with semantic's at T: the questions only one of the two gets right, the exact sign test and the 95 % interval
of the difference (eqa_app.evaluation's helpers). Scorer of the stored runs: oracle, a simulated perception
model, not a VLM/detector.

    python -m eqa_app.benches.explore_half_budget --strategies gain perfect_gain target_oracle \\
        --traces bench/results/explore-seeds/traces bench/results/explore-strategies/traces \\
                 bench/results/explore-yardsticks/traces bench/results/explore-perfect/traces
"""

from __future__ import annotations

from pathlib import Path

from eqa.seeds import EVALUATION_SEEDS
from eqa_app import evaluation as ev
from eqa_app import stats
from eqa_app.benches import harness
from services.stopper.calibration import Trace, read_jsonl


def load(dirs: list[Path], strategy: str) -> dict[str, Trace]:
    """Every stored cores-runner trace of ``strategy`` on the evaluation seeds, by question id."""
    out: dict[str, Trace] = {}
    for d in dirs:
        for seed in EVALUATION_SEEDS:
            for f in sorted(d.glob(f"bench-{strategy}-oracle-320x240-seed{seed}-x*-cores.jsonl.gz")):
                out.update({t.question_id: t for _, t in read_jsonl(f)})
    return out


def main(argv: list[str] | None = None) -> int:
    p = harness.parser(__doc__)
    p.add_argument("--strategies", nargs="+", required=True)
    p.add_argument("--traces", nargs="+", type=Path, required=True, metavar="DIR")
    p.add_argument("--budget", type=float, default=0.5, help="the strategy's budget, x T (default 0.5)")
    args = p.parse_args(argv)
    semantic = load(args.traces, "semantic")
    print(f"scorer oracle (simulated perception model, not a VLM/detector); seeds {list(EVALUATION_SEEDS)}")
    for name in args.strategies:
        runs = load(args.traces, name)
        ids = [q for q in runs if q in semantic]
        a = sum(ev.correct_at_budget(runs[q], args.budget) and not ev.correct_at_budget(semantic[q], 1.0) for q in ids)
        b = sum(ev.correct_at_budget(semantic[q], 1.0) and not ev.correct_at_budget(runs[q], args.budget) for q in ids)
        d, lo, hi = stats.paired_diff_ci(a, b, len(ids))
        print(f"{name} at {args.budget:g} T vs semantic at T: n {len(ids)}, right only it {a} / only semantic {b}, "
              f"sign p {stats.sign_test_p(a, b):.2g}, difference {d:+.3f} [{lo:+.3f}, {hi:+.3f}]")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

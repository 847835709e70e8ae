"""Answer memory against the paper's single-view answer, on recorded traces (offline).

SIMULATED PERCEPTION MODEL (oracle scorer), not a VLM. The answer rules need only the per-step answer
distributions f(x^t) and relevances Rel(x^t), which the traces hold, so the episodes are re-scored offline:
the robot's path does not depend on the answer rule (LSV/GSV drive it), except where CP stops earlier or later,
which the replay models exactly as :func:`services.stopper.state.decide` does (a test checks they agree).

Data (all ``semantic`` exploration, 320x240, full-length ``max_steps`` runs):

* evaluation seeds 1-3: test splits = ``bench/results/explore-seeds/traces`` (200 per seed);
  calibration splits recorded with ``eqa_app.stop_sensitivity`` (``--recordings DIR``, the first ``--n-cal``
  of the round-robin category order);
* tuning seed 11: calibration + test recordings; K and the fusion are chosen there only, by the answer
  accuracy at the full budget (ties: the smaller K).

Printed and stored (``bench/results/answer_rules.json``): for the chosen rule and the single-view rule,
(a) the answer at the full budget, pooled and per category, paired exact sign test and bootstrap CI of the
difference; (b) CP at several eps, each rule calibrated per seed on its own calibration split *with its own
rule*: coverage of the sequence-level set next to 1 - eps, success, normalised steps, paired tests.

    PYTHONPATH=. .venv/bin/python -m eqa_app.benches.answer_rules --recordings var/answer-rules --record
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from eqa.messages import letters
from eqa.seeds import EVALUATION_SEEDS, TUNING_SEED
from eqa_app.benches import harness
from eqa_app.stats import paired_outcomes, wilson_ci
from eqa_app.stop_sensitivity import Outcome as Out
from eqa_app.stop_sensitivity import load_recording, recording_path
from services.stopper.answer_memory import FUSIONS, AnswerRule, transform
from services.stopper.calibration import read_jsonl
from services.stopper.conformal import conformal_quantile, nonconformity
from services.stopper.replay import replay_arrays

LABEL = "simulated perception model, not a VLM"
TRACES = Path("bench/results/explore-seeds/traces")
K_GRID = (1, 2, 3, 4, 6, 8)
EPS_EVAL = (0.1, 0.2, 0.3)


@dataclass
class Ep:
    qid: str
    category: str
    f: np.ndarray
    rel: np.ndarray
    truth: int
    max_steps: int


def from_trace(t: Any) -> Ep:
    f, rel = t.arrays()
    return Ep(t.question_id, t.category or "", f, rel, letters(len(t.choices)).index(t.answer), t.max_steps)


def from_recording(e: Any) -> Ep:
    q = e.question
    return Ep(q.id, q.category or "", np.asarray([s.probs for s in e.steps], dtype=np.float64),
              np.asarray([s.relevance for s in e.steps], dtype=np.float64),
              letters(len(q.choices)).index(q.answer), q.max_steps)


def kappa(ep: Ep, rule: AnswerRule) -> float:
    f, r = transform(ep.f, ep.rel, rule)
    return nonconformity(f, r, ep.truth)


def replay(ep: Ep, rule: AnswerRule, q_hat: float | None) -> Out:
    """What ``decide`` does with the answer rule ``rule``: CP with ``q_hat`` (None = run to the limit)."""
    stop = replay_arrays(ep.f, ep.rel, ep.max_steps, "max_steps" if q_hat is None else "cp", q_hat, rule)
    return Out(stop.answer == ep.truth, (stop.step + 1) / ep.max_steps, stop.covers(ep.truth))


def paired(a: list[Out], b: list[Out]) -> dict[str, float]:
    """a - b on the same episodes (:func:`eqa_app.stats.paired_outcomes`, 4000 bootstrap resamples)."""
    return paired_outcomes(a, b, n_boot=4000)


def load(recordings: Path, seed: int, split: str, n: int | None) -> list[Ep]:
    if split == "test" and seed in EVALUATION_SEEDS:
        path = TRACES / f"bench-semantic-oracle-320x240-seed{seed}-x1-cores.jsonl.gz"
        eps = [from_trace(t) for _, t in read_jsonl(path)]
    else:
        eps = [from_recording(e) for e in load_recording(recording_path(recordings, seed, split, "semantic",
                                                                            "320x240"))]
    return eps[:n] if n else eps


def tune(eps: list[Ep]) -> tuple[AnswerRule, list[dict[str, Any]]]:
    """The rule with the best full-budget accuracy on the tuning seed's episodes (ties: smaller K, loglinear)."""
    rows = []
    base = np.mean([replay(e, AnswerRule(), None).correct for e in eps])
    rows.append({"rule": "single", "accuracy": float(base)})
    best = (base, 0, AnswerRule())
    for fusion in FUSIONS:
        for k in K_GRID:
            rule = AnswerRule(k, fusion)  # type: ignore[arg-type]
            acc = float(np.mean([replay(e, rule, None).correct for e in eps]))
            rows.append({"rule": rule.name, "accuracy": acc})
            if acc > best[0] + 1e-12:
                best = (acc, k, rule)
    return best[2], rows


def cp_eval(cal: list[Ep], test: list[Ep], rule: AnswerRule, eps: float) -> tuple[float, list[Out]]:
    q_hat = conformal_quantile([kappa(e, rule) for e in cal], eps)
    return q_hat, [replay(e, rule, q_hat) for e in test]


RECORD_PLAN = ((TUNING_SEED, "calibration", 60), (TUNING_SEED, "test", 60),
               *((s, "calibration", 100) for s in EVALUATION_SEEDS))


def record_missing(recordings: Path) -> None:
    """Record (resumably) what this benchmark reads besides the stored test traces: :data:`RECORD_PLAN`,
    the first questions of each split in :func:`eqa_app.stop_sensitivity.benchmark_questions`' order."""
    from eqa.settings import Settings
    from eqa_app.stop_sensitivity import benchmark_questions, record
    from services.sim.questions import benchmark

    scenes = Settings().scenes_path
    benches: dict[int, Any] = {}
    for seed, split, limit in RECORD_PLAN:
        if seed not in benches:
            benches[seed] = benchmark(seed=seed, scenes_dir=scenes)
        qs = benchmark_questions(seed, split, limit, scenes, benches[seed])
        record(qs, "semantic", 320, 240, 1, recording_path(recordings, seed, split, "semantic", "320x240"))


def main(argv: list[str] | None = None) -> int:
    p = harness.parser(__doc__)
    p.add_argument("--recordings", type=Path, required=True, help="stop_sensitivity recordings (calibration splits)")
    p.add_argument("--record", action="store_true", help="first record what is missing (RECORD_PLAN; ~20 min "
                   "of CPU on an idle core, 2.4 s per episode)")
    p.add_argument("--n-cal", type=int, default=None, help="calibration episodes per evaluation seed (default all)")
    p.add_argument("--out", type=Path, default=Path("bench/results/answer_rules.json"))
    p.add_argument("--rule", default=None, help="skip tuning and evaluate this rule (e.g. memory-3-loglinear)")
    a = p.parse_args(argv)
    if a.record:
        record_missing(a.recordings)

    tuning = load(a.recordings, TUNING_SEED, "calibration", None) + load(a.recordings, TUNING_SEED, "test", None)
    chosen, tune_rows = tune(tuning)
    if a.rule:
        chosen = AnswerRule.from_name(a.rule)
    print(f"scorer: oracle ({LABEL}); tuning seed {TUNING_SEED}: n = {len(tuning)} episodes")
    for r in tune_rows:
        print(f"  {r['rule']:<22} full-budget accuracy {r['accuracy']:.3f}")
    print(f"chosen on seed {TUNING_SEED}: {chosen.name}")
    single = AnswerRule()
    res: dict[str, Any] = {"scorer": f"oracle ({LABEL})", "tuning_seed": TUNING_SEED, "n_tuning": len(tuning),
                           "tuning": tune_rows, "chosen": chosen.name, "evaluation_seeds": list(EVALUATION_SEEDS),
                           "per_seed_n": {}, "full_budget": {}, "cp": {}}
    data = {s: (load(a.recordings, s, "calibration", a.n_cal), load(a.recordings, s, "test", None))
            for s in EVALUATION_SEEDS}
    res["per_seed_n"] = {str(s): {"calibration": len(c), "test": len(t)} for s, (c, t) in data.items()}
    test_all = [e for _, t in data.values() for e in t]
    cats = sorted({e.category for e in test_all})

    def by_cat(outs_a: list[Out], outs_b: list[Out]) -> dict[str, Any]:
        out = {"all": paired(outs_a, outs_b)}
        for c in cats:
            ia = [o for o, e in zip(outs_a, test_all, strict=True) if e.category == c]
            ib = [o for o, e in zip(outs_b, test_all, strict=True) if e.category == c]
            out[c] = paired(ia, ib)
        return out

    fa = [replay(e, chosen, None) for e in test_all]
    fb = [replay(e, single, None) for e in test_all]
    res["full_budget"] = by_cat(fa, fb)
    print(f"\n(a) answer at the full budget, seeds {list(EVALUATION_SEEDS)} test splits pooled: {chosen.name} (a) vs "
          f"single view (b)")
    for c, r in res["full_budget"].items():
        print(f"  {c:<15} n={r['n']:>3}  {r['success_a']:.3f} vs {r['success_b']:.3f}  diff {r['diff']:+.3f} "
              f"[{r['ci_low']:+.3f}, {r['ci_high']:+.3f}]  only a/b right {r['a_only']}/{r['b_only']}  p={r['p']:.3g}")
    for eps in EPS_EVAL:
        outs: dict[str, list[Out]] = {"a": [], "b": []}
        qh: dict[str, dict[str, float]] = {"a": {}, "b": {}}
        for s, (cal, test) in data.items():
            for key, rule in (("a", chosen), ("b", single)):
                q, o = cp_eval(cal, test, rule, eps)
                qh[key][str(s)] = q
                outs[key] += o
        cov = {}
        for key in ("a", "b"):
            k = sum(bool(o.covered) for o in outs[key])
            n = len(outs[key])
            lo, hi = wilson_ci(k, n)
            cov[key] = {"coverage": k / n, "ci_low": lo, "ci_high": hi, "n": n}
        cov_cat = {key: {c: float(np.mean([bool(o.covered) for o, e in zip(outs[key], test_all, strict=True)
                                           if e.category == c])) for c in cats} for key in ("a", "b")}
        res["cp"][f"{eps:g}"] = {"q_hat": qh, "coverage": cov, "coverage_by_category": cov_cat,
                                 "paired": by_cat(outs["a"], outs["b"])}
        r = res["cp"][f"{eps:g}"]["paired"]["all"]
        print(f"\n(b) CP eps={eps:g} (1-eps={1 - eps:.2f}), each rule calibrated on its own rule per seed:")
        for key, name in (("a", chosen.name), ("b", "single")):
            c = cov[key]
            print(f"  {name:<22} coverage {c['coverage']:.3f} [{c['ci_low']:.3f}, {c['ci_high']:.3f}] n={c['n']}  "
                  f"q_hat {', '.join(f'{v:.3f}' for v in qh[key].values())}")
        print(f"  success {r['success_a']:.3f} vs {r['success_b']:.3f} diff {r['diff']:+.3f} [{r['ci_low']:+.3f}, "
              f"{r['ci_high']:+.3f}] p={r['p']:.3g}; steps {r['steps_a']:.3f} vs {r['steps_b']:.3f} "
              f"diff {r['steps_diff']:+.3f} [{r['steps_ci_low']:+.3f}, {r['steps_ci_high']:+.3f}]")
        for c in cats:
            rc = res["cp"][f"{eps:g}"]["paired"][c]
            print(f"    {c:<15} n={rc['n']:>3} success {rc['success_a']:.3f} vs {rc['success_b']:.3f} p={rc['p']:.3g}"
                  f"  coverage {cov_cat['a'][c]:.3f} vs {cov_cat['b'][c]:.3f}")
    harness.write_json(a.out, res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

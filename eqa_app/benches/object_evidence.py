"""Object evidence for questions against VLM-only answers, on existence and counting questions.

SIMULATED PERCEPTION MODEL (oracle scorer) and SIMULATED DETECTOR, not a VLM / detector. Two steps:

1. ``record``: full-length ``semantic`` episodes with the services' pure cores in this process (as
   :func:`eqa_app.stop_sensitivity.run_episode`: sim render -> mapper -> oracle scorer -> planner, the same
   path and seeds, so the VLM scores are those of the benchmark traces), plus, per step, the question's target
   class in the HELIOS object layer (:class:`services.mapper.question_objects.QuestionObjects`, detections from
   the simulated detector) and its :class:`~services.stopper.object_evidence.ObjectEvidence`. The object layer
   does not steer the robot, so the path is the benchmark's.
2. ``eval``: the combination's knobs (psi_min, weight) are chosen on the tuning seed 11 only (full-budget
   accuracy); on seeds 1-3 VLM-only and combined answers are compared at the full budget and under CP (each
   calibrated per seed on its calibration split with its own rule), paired, per category, with coverage.

    PYTHONPATH=. .venv/bin/python -m eqa_app.benches.object_evidence record --seeds 11 1 2 3 --n 30 --out DIR
    PYTHONPATH=. .venv/bin/python -m eqa_app.benches.object_evidence eval --out DIR
"""

from __future__ import annotations

import dataclasses
import pickle
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from eqa_app.benches import harness

LABEL = "simulated perception model and simulated detector, not a VLM / detector"
EPS_EVAL = (0.1, 0.2, 0.3)


@dataclasses.dataclass
class ObjEpisode:
    qid: str
    category: str
    choices: list[str]
    truth: int
    max_steps: int
    probs: list[list[float]]
    relevance: list[float]
    evidence: list[dict[str, Any]]
    seconds: float


def run_episode(question: Any) -> ObjEpisode:
    """One full-length semantic episode with the pure cores in this process
    (:func:`eqa_app.core_runner.run_episode_loop`), the mapper's question-object layer fed by the detector."""
    from eqa.messages import DetectResult, EpisodeStart, letters
    from eqa.settings import Settings
    from eqa_app.benchmark_runner import question_seed
    from eqa_app.core_runner import EpisodeCores, StepHooks, run_episode_loop
    from services.mapper.episode_map import EpisodeMap
    from services.mapper.question_objects import QuestionObjects
    from services.planner.step import PlannerParams
    from services.sim.render import Renderer
    from services.sim.service import load_scene
    from services.vlm_scorer.backends.oracle import OracleBackend
    from services.vlm_scorer.detector import make_detector

    t0 = time.monotonic()
    settings = Settings()
    scene = load_scene(settings, question.scene)
    oracle = OracleBackend.from_settings(settings)
    detector = make_detector(settings)
    seed = question_seed(question.id)
    start = EpisodeStart(episode_id=f"sens-{question.id}", robot="r0", question=question, strategy="semantic",
                         max_steps=question.max_steps, seed=seed)
    room_kind = question.query.get("room_kind")
    rects = [r.rect for r in scene.rooms if r.kind == room_kind] if room_kind else None
    objects = QuestionObjects(question, rects, scene.floor_area_m2)
    probs: list[list[float]] = []
    rels: list[float] = []
    evs: list[dict[str, Any]] = []

    class Evidence(StepHooks):
        def scored(self, step: int, frame: Any, request: Any, scores: Any) -> None:
            dreq = objects.detect_request(frame, seed)
            objects.integrate(frame, DetectResult(request_id=dreq.request_id, episode_id=start.episode_id, step=step,
                                                  detections=detector.detect(dreq),
                                                  backend=settings.detector_backend))
            probs.append(list(scores.answer_probs))
            rels.append(float(scores.relevance))

        def mapped(self, step: int, emap: Any, step_map: Any) -> None:
            observed = emap.maps.observed if emap.maps is not None else None
            evs.append(objects.evidence(observed, emap.grid()).model_dump())

    cores = EpisodeCores(scene, Renderer(scene), oracle, EpisodeMap(start), PlannerParams(), 320, 240)
    run_episode_loop(question, "semantic", cores, episode_id=start.episode_id, seed=seed, hooks=Evidence())
    return ObjEpisode(question.id, question.category or "", list(question.choices),
                      letters(len(question.choices)).index(question.answer), question.max_steps, probs, rels, evs,
                      time.monotonic() - t0)


def object_questions(seed: int, split: str, n: int, bench: Any) -> list[Any]:
    """The first ``n`` existence / counting questions of the split, alternating categories."""
    from services.sim.questions import category_round_robin

    qs = {"calibration": bench.calibration, "test": bench.test}[split]
    return category_round_robin(qs, n, categories=("existence", "counting"))


def record(seeds: list[int], n: int, out: Path) -> None:
    from tqdm import tqdm

    from eqa.settings import Settings
    from services.sim.questions import benchmark

    out.mkdir(parents=True, exist_ok=True)
    for seed in seeds:
        bench = benchmark(seed=seed, scenes_dir=Settings().scenes_path)
        for split in ("calibration", "test"):
            path = out / f"objects-seed{seed}-{split}.pkl"
            done: list[ObjEpisode] = pickle.loads(path.read_bytes()) if path.is_file() else []
            have = {e.qid for e in done}
            todo = [q for q in object_questions(seed, split, n, bench) if q.id not in have]
            for q in tqdm(todo, desc=f"seed{seed}-{split}", unit="ep", file=sys.stderr):
                done.append(run_episode(q))
                path.write_bytes(pickle.dumps(done))
            secs = [e.seconds for e in done]
            print(f"seed {seed} {split}: {len(done)} episodes, {np.mean(secs):.1f} s/episode", flush=True)


def _load(out: Path, seed: int, split: str) -> list[ObjEpisode]:
    path = out / f"objects-seed{seed}-{split}.pkl"
    return pickle.loads(path.read_bytes()) if path.is_file() else []  # our own recording, never a foreign file


def combined(ep: ObjEpisode, params: Any) -> np.ndarray:
    from services.stopper.object_evidence import ObjectEvidence, combined_steps

    evs = [ObjectEvidence.model_validate(e) for e in ep.evidence]
    return combined_steps(np.asarray(ep.probs), evs, ep.choices, params)


def replay(ep: ObjEpisode, f: np.ndarray, q_hat: float | None) -> tuple[bool, float, bool | None]:
    """As :func:`services.stopper.state.decide` (single-view answer rule) on the distributions ``f``: CP with
    ``q_hat`` (None = run to the limit)."""
    from services.stopper.replay import replay_arrays

    stop = replay_arrays(f, np.asarray(ep.relevance), ep.max_steps, "max_steps" if q_hat is None else "cp", q_hat)
    return stop.answer == ep.truth, (stop.step + 1) / ep.max_steps, stop.covers(ep.truth)


def evaluate(out: Path, seeds: list[int], tuning_seed: int) -> dict[str, Any]:
    from eqa_app.benches.answer_rules import Out, paired
    from eqa_app.stats import wilson_ci
    from services.stopper.conformal import conformal_quantile, nonconformity
    from services.stopper.object_evidence import EvidenceParams

    tune_eps = _load(out, tuning_seed, "calibration") + _load(out, tuning_seed, "test")
    grid = [EvidenceParams(psi_min=pm, weight=w) for pm in (0.1, 0.2, 0.3, 0.5) for w in (0.25, 0.5, 0.75)]
    vlm_only = EvidenceParams(weight=0.0)

    def acc(params: Any, eps: list[ObjEpisode]) -> float:
        return float(np.mean([replay(e, combined(e, params), None)[0] for e in eps])) if eps else float("nan")

    rows = [{"params": dataclasses.asdict(p), "accuracy": acc(p, tune_eps)} for p in grid]
    base = acc(vlm_only, tune_eps)
    best = max(rows, key=lambda r: (r["accuracy"], -r["params"]["weight"]))
    chosen = EvidenceParams(**best["params"]) if best["accuracy"] > base else vlm_only
    print(f"scorer: oracle ({LABEL}); tuning seed {tuning_seed}: n = {len(tune_eps)}; VLM-only accuracy {base:.3f}")
    for r in rows:
        print(f"  psi_min={r['params']['psi_min']:.1f} weight={r['params']['weight']:.2f}: {r['accuracy']:.3f}")
    print(f"chosen: {dataclasses.asdict(chosen)}")
    res: dict[str, Any] = {"scorer": LABEL, "tuning_seed": tuning_seed, "n_tuning": len(tune_eps),
                           "tuning": rows, "tuning_vlm_only": base, "chosen": dataclasses.asdict(chosen),
                           "seeds": seeds, "n": {}, "full_budget": {}, "cp": {}}
    data = {s: (_load(out, s, "calibration"), _load(out, s, "test")) for s in seeds}
    res["n"] = {str(s): {"calibration": len(c), "test": len(t)} for s, (c, t) in data.items()}
    test = [e for _, t in data.values() for e in t]
    cats = sorted({e.category for e in test})

    def outs(params: Any, q: dict[int, float] | None) -> list[Out]:
        r = []
        for s, (_, t) in data.items():
            for e in t:
                c, st, cov = replay(e, combined(e, params), None if q is None else q[s])
                r.append(Out(c, st, cov))
        return r

    def by_cat(a: list[Out], b: list[Out]) -> dict[str, Any]:
        d = {"all": paired(a, b)}
        for c in cats:
            d[c] = paired([o for o, e in zip(a, test, strict=True) if e.category == c],
                          [o for o, e in zip(b, test, strict=True) if e.category == c])
        return d

    res["full_budget"] = by_cat(outs(chosen, None), outs(vlm_only, None))
    print(f"\n(a) full budget, seeds {seeds} test pooled: combined (a) vs VLM-only (b)")
    for c, r in res["full_budget"].items():
        print(f"  {c:<10} n={r['n']:>3} {r['success_a']:.3f} vs {r['success_b']:.3f} diff {r['diff']:+.3f} "
              f"[{r['ci_low']:+.3f}, {r['ci_high']:+.3f}] only a/b {r['a_only']}/{r['b_only']} p={r['p']:.3g}")
    for eps in EPS_EVAL:
        qs: dict[str, dict[int, float]] = {}
        for key, params in (("a", chosen), ("b", vlm_only)):
            qs[key] = {}
            for s, (cal, _) in data.items():
                kap = [nonconformity(combined(e, params), np.asarray(e.relevance), e.truth) for e in cal]
                qs[key][s] = conformal_quantile(kap, eps)
        oa, ob = outs(chosen, qs["a"]), outs(vlm_only, qs["b"])
        cov = {}
        for key, o in (("a", oa), ("b", ob)):
            k = sum(bool(x.covered) for x in o)
            lo, hi = wilson_ci(k, len(o))
            cov[key] = {"coverage": k / len(o), "ci_low": lo, "ci_high": hi, "n": len(o)}
        res["cp"][f"{eps:g}"] = {"q_hat": {k: {str(s): v for s, v in d.items()} for k, d in qs.items()},
                                 "coverage": cov, "paired": by_cat(oa, ob)}
        r = res["cp"][f"{eps:g}"]["paired"]["all"]
        print(f"\n(b) CP eps={eps:g}: coverage combined {cov['a']['coverage']:.3f} [{cov['a']['ci_low']:.3f}, "
              f"{cov['a']['ci_high']:.3f}] vs VLM-only {cov['b']['coverage']:.3f} (1-eps {1 - eps:.2f}, "
              f"n={cov['a']['n']}); success {r['success_a']:.3f} vs {r['success_b']:.3f} p={r['p']:.3g}; steps "
              f"{r['steps_a']:.3f} vs {r['steps_b']:.3f} diff {r['steps_diff']:+.3f} [{r['steps_ci_low']:+.3f}, "
              f"{r['steps_ci_high']:+.3f}]")
    return res


def main(argv: list[str] | None = None) -> int:
    from eqa.seeds import EVALUATION_SEEDS, TUNING_SEED

    p = harness.parser(__doc__)
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("record", help="record episodes with the object layer (resumable)")
    r.add_argument("--seeds", type=int, nargs="+", default=[TUNING_SEED, *EVALUATION_SEEDS])
    r.add_argument("--n", type=int, default=30, help="existence/counting questions per split and seed")
    r.add_argument("--out", type=Path, required=True)
    e = sub.add_parser("eval", help="tune on seed 11, compare on seeds 1-3")
    e.add_argument("--out", type=Path, required=True)
    e.add_argument("--results", type=Path, default=Path("bench/results/answer_rules_objects.json"))
    a = p.parse_args(argv)
    if a.cmd == "record":
        record(a.seeds, a.n, a.out)
        return 0
    res = evaluate(a.out, list(EVALUATION_SEEDS), TUNING_SEED)
    harness.write_json(a.results, res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Object evidence: the floor plan's rooms (as eqa_app/benches/object_evidence.py) against the whole
explored map (what the product does: the mapper has no floor plan), from the SAME object layer per episode,
both against VLM-only answers. Full budget, single-view answer rule, test split of the evaluation seeds, the
knobs fixed at the settings' defaults (psi_min, weight: chosen on the tuning seed 11 by
eqa_app.benches.object_evidence).
No CP here (that needs calibration recordings per variant).

SIMULATED PERCEPTION MODEL (oracle scorer) and SIMULATED DETECTOR, not a VLM / detector.

    PYTHONPATH=. .venv/bin/python -m eqa_app.benches.object_evidence_region --out /tmp/wm --n 32 \\
        --json bench/results/object_evidence_region.json

Records resumably into ``--out`` (one pickle per seed), prints per category the success of VLM-only,
floor-plan evidence and whole-map evidence with paired tests (bootstrap 95 % CI, exact sign test).
"""

from __future__ import annotations

import dataclasses
import json
import pickle
import sys
from pathlib import Path
from typing import Any

import numpy as np

from eqa_app.benches import harness


def record(out: Path, n: int, seeds: list[int]) -> None:
    from tqdm import tqdm

    import eqa_app.benches.object_evidence as bench_obj
    import services.mapper.question_objects as qo_mod
    from eqa.settings import Settings
    from services.sim.questions import benchmark

    whole: list[dict[str, Any]] = []

    class Both(qo_mod.QuestionObjects):
        """The bench's region as usual; the product's region (whole map, no floor area) from the same layer."""

        def evidence(self, explored: Any, grid: Any) -> Any:
            rects, area = self.rects, self.floor_area_m2
            self.rects, self.floor_area_m2 = None, None
            whole.append(super().evidence(explored, grid).model_dump())
            self.rects, self.floor_area_m2 = rects, area
            return super().evidence(explored, grid)

    qo_mod.QuestionObjects = Both  # type: ignore[misc]  # run_episode imports it by name when called
    out.mkdir(parents=True, exist_ok=True)
    for seed in seeds:
        path = out / f"seed{seed}.pkl"
        done = pickle.loads(path.read_bytes()) if path.is_file() else []  # our own recording
        have = {e[0].qid for e in done}
        bench = benchmark(seed=seed, scenes_dir=Settings().scenes_path)
        todo = [q for q in bench_obj.object_questions(seed, "test", n, bench) if q.id not in have]
        for q in tqdm(todo, desc=f"seed{seed}", unit="ep", file=sys.stderr):
            whole.clear()
            ep = bench_obj.run_episode(q)
            done.append((ep, dataclasses.replace(ep, evidence=list(whole))))
            path.write_bytes(pickle.dumps(done))


def evaluate(out: Path, seeds: list[int]) -> dict[str, Any]:
    import eqa_app.benches.object_evidence as bench_obj
    from eqa.settings import Settings
    from eqa_app.benches.answer_rules import Out, paired
    from services.mapper.question_objects import WHOLE_MAP_CATEGORIES
    from services.stopper.object_evidence import EvidenceParams

    s = Settings()
    params = EvidenceParams(psi_min=s.object_evidence_psi_min, weight=s.object_evidence_weight)
    vlm = EvidenceParams(weight=0.0)
    pairs = [x for seed in seeds for x in pickle.loads((out / f"seed{seed}.pkl").read_bytes())]

    def outs(eps: list[Any], p: Any) -> list[Any]:
        return [Out(*bench_obj.replay(e, bench_obj.combined(e, p), None)[:2]) for e in eps]

    res: dict[str, Any] = {"label": bench_obj.LABEL, "params": dataclasses.asdict(params), "seeds": seeds,
                           "rule": "full budget, single-view answer"}
    for cat in ("all", "counting", "existence"):
        sel = [x for x in pairs if cat == "all" or x[0].category == cat]
        plan, wm = [x[0] for x in sel], [x[1] for x in sel]
        o_v, o_p, o_w = outs(plan, vlm), outs(plan, params), outs(wm, params)
        # the product: whole-map evidence for WHOLE_MAP_CATEGORIES only, the VLM alone for the others
        o_prod = [w if e.category in WHOLE_MAP_CATEGORIES else v for e, w, v in zip(plan, o_w, o_v, strict=True)]
        res[cat] = {"n": len(sel), "vlm_only": float(np.mean([o.correct for o in o_v])),
                    "floor_plan": float(np.mean([o.correct for o in o_p])),
                    "whole_map": float(np.mean([o.correct for o in o_w])),
                    "whole_map_vs_vlm": paired(o_w, o_v), "floor_plan_vs_vlm": paired(o_p, o_v),
                    "whole_map_vs_floor_plan": paired(o_w, o_p),
                    "product": float(np.mean([o.correct for o in o_prod])), "product_vs_vlm": paired(o_prod, o_v)}
        r = res[cat]
        print(f"{cat:10s} n={r['n']:3d}  VLM-only {r['vlm_only']:.3f}  floor plan {r['floor_plan']:.3f}  "
              f"whole map {r['whole_map']:.3f}  | whole-VLM {r['whole_map_vs_vlm']['diff']:+.3f} "
              f"[{r['whole_map_vs_vlm']['ci_low']:+.3f}, {r['whole_map_vs_vlm']['ci_high']:+.3f}] "
              f"p {r['whole_map_vs_vlm']['p']:.3f}  | whole-plan {r['whole_map_vs_floor_plan']['diff']:+.3f} "
              f"p {r['whole_map_vs_floor_plan']['p']:.3f}")
        pv = r["product_vs_vlm"]
        print(f"{'':10s} product rule (whole map for {', '.join(WHOLE_MAP_CATEGORIES)}) {r['product']:.3f}: "
              f"{pv['diff']:+.3f} [{pv['ci_low']:+.3f}, {pv['ci_high']:+.3f}] p {pv['p']:.3f} "
              f"({pv['a_only']} vs {pv['b_only']} discordant)")
    res["whole_map_categories"] = list(WHOLE_MAP_CATEGORIES)
    res["seconds_per_episode"] = float(np.mean([x[0].seconds for x in pairs]))
    return res


def main(argv: list[str] | None = None) -> int:
    ap = harness.parser(__doc__)
    ap.add_argument("--out", type=Path, required=True, help="recording directory (resumable)")
    ap.add_argument("--n", type=int, default=32, help="existence+counting test questions per seed (alternating)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3], help="evaluation seeds")
    ap.add_argument("--eval-only", action="store_true", help="do not record, evaluate what is in --out")
    ap.add_argument("--json", type=Path, help="write the figures here")
    a = ap.parse_args(argv)
    if a.n < 1:
        ap.error("--n must be >= 1")
    if not a.eval_only:
        record(a.out, a.n, a.seeds)
    res = evaluate(a.out, a.seeds)
    if a.json:
        a.json.write_text(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""The in-process episode loop (:func:`eqa_app.core_runner.core_episode`) produces the fleet's traces.

Tuning-seed (11) questions run through a real fleet (sim, mapper, planner, stopper and an oracle scorer as
separate processes over Zenoh, real Redis; :class:`eqa_app.benchmark_runner.Runner`) and through the
in-process loop; every step's answer distribution and relevance must agree within 1e-6 (float32 rounding of
the bus), for the Eq. A6 strategies and the deterministic rules vlfm / gain / topo. The three fbe questions are
ones where the simulator refuses goals within their 20 steps, so the
planner service's refusal handling and the loop's (:mod:`services.planner.refusals`) are compared where they
act; the oracle scorer is a simulated perception model, not a VLM.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from support.fleet import fleet_settings

from eqa.seeds import TUNING_SEED
from eqa_app import core_runner
from eqa_app.benchmark_runner import Runner
from services.sim.library import load_or_generate
from services.sim.questions import benchmark_candidates

STEPS = 20
# (house index of the tuning seed's benchmark, category, strategy)
CASES = {
    "fbe": [(1, "counting"), (1, "location"), (1, "state")],  # the simulator refuses a goal in each
    "semantic": [(0, "existence")],
    # the deterministic frontier rules (services/planner/frontier_rules.py): the same maps must give the same
    # choices, commitments and refusal handling in both runners
    "vlfm": [(0, "existence")],
    "gain": [(1, "location")],
    "topo": [(1, "counting")],
}


def _question(settings, index: int, category: str):
    load_or_generate(f"gen-{TUNING_SEED * 10000 + index:05d}", settings.scenes_path)
    q = benchmark_candidates(TUNING_SEED, index, settings.scenes_path)[category][0]
    return q.model_copy(update={"max_steps": min(int(q.max_steps), STEPS)})


def _steps(trace_steps) -> list[tuple[list[float], float]]:
    return [(list(s.answer_probs), float(s.relevance)) for s in trace_steps]


def test_in_process_loop_gives_the_fleets_traces(tmp_path: Path, redis_url: str, monkeypatch) -> None:
    settings = fleet_settings(tmp_path, redis_url, scorer_backend="oracle")
    refusals: list[str] = []
    real_refusal = core_runner.goal_refusal

    def counted(scene, plan):  # the simulator's own goal check, counted
        reason = real_refusal(scene, plan)
        if reason is not None:
            refusals.append(reason)
        return reason

    monkeypatch.setattr(core_runner, "goal_refusal", counted)
    compared = 0
    for strategy, cases in CASES.items():
        questions = [_question(settings, index, category) for index, category in cases]
        with Runner(settings, strategy=strategy, robots=2, scorers=1, step_timeout_s=240) as runner:
            fleet = {r.question.id: r for r in runner.run(questions)}
        for q in questions:
            res = fleet[q.id]
            assert res.end is not None and not res.reason.startswith("failed"), res.reason
            cores = core_runner.core_episode((q, strategy, settings.model_dump()))
            got, want = _steps(cores.steps), [(list(s.answer_probs), float(s.relevance)) for s in res.steps]
            assert len(got) == len(want), (q.id, strategy, len(got), len(want), cores.end_reason, res.reason)
            for t, ((f_core, r_core), (f_fleet, r_fleet)) in enumerate(zip(got, want, strict=True)):
                assert np.allclose(f_core, f_fleet, rtol=0, atol=1e-6), (q.id, strategy, t, f_core, f_fleet)
                assert abs(r_core - r_fleet) <= 1e-6, (q.id, strategy, t, r_core, r_fleet)
            compared += 1
    assert compared == sum(len(c) for c in CASES.values())
    assert refusals, "no goal was refused: the cases no longer exercise the refusal policy"

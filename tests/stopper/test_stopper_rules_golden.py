"""Every stop rule over recorded score sequences gives the decisions recorded in ``tests/data/stop_rules_golden.json``.

The fixture holds the inputs (the first 30 steps of three fbe seed-1 and three semantic seed-2 fleet traces of the
oracle scorer -- a simulated perception model, not a VLM -- and one question whose choices the scorer proposes) and
the decisions :func:`services.stopper.state.decide` returned for them, for CP at three q_hat with and without the
answer memory, entropy and relevance at their default and two thresholds, and max_steps. Decisions must stay
byte-identical (as JSON) whatever the stop rules' code looks like."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from support.factories import episode_start, question

from eqa.messages import StepScores, StopConfig
from services.stopper.state import CalibrationChoice, EpisodeRecord, decide

FIXTURE = json.loads((Path(__file__).resolve().parents[1] / "data" / "stop_rules_golden.json").read_text())
SEQUENCES = {s["question_id"]: s for s in FIXTURE["sequences"]}


def _episode(seq: dict, config: dict) -> EpisodeRecord:
    q = question(id=seq["question_id"], scene="gen-1", text="q?", choices=seq["choices"], answer=seq["answer"],
                 category=seq["category"])
    start = episode_start(q, max_steps=seq["max_steps"],
                          stop=StopConfig(rule=config["rule"], eps=0.2, threshold=config.get("threshold")))
    episode = EpisodeRecord.from_start(start, "r")
    if config["rule"] == "cp":
        episode.calibration = CalibrationChoice(q_hat=config["q_hat"], eps=0.2, asked_eps=0.2, n=100,
                                                source="fixture", backend="oracle", answer_rule=None)
        episode.answer_memory = config["answer_memory"]
        episode.answer_fusion = config["answer_fusion"]
    episode.threshold = config.get("threshold")
    return episode


@pytest.mark.parametrize("case", FIXTURE["cases"], ids=lambda c: f"{c['sequence']}-{json.dumps(c['config'])}")
def test_rule_decisions_unchanged(case: dict) -> None:
    seq = SEQUENCES[case["sequence"]]
    episode = _episode(seq, case["config"])
    got = []
    for i, st in enumerate(seq["steps"][: len(case["decisions"])]):
        d = decide(episode, StepScores(episode_id="e", step=i, answer_probs=st["answer_probs"],
                                       relevance=st["relevance"], backend="oracle"))
        # (warm_calibrated is a warm start's calibration flag: None for these cold episodes, and not in the fixture)
        got.append(None if d is None else json.loads(d.model_dump_json(exclude={"sent_at"})))
        if got[-1] is not None and got[-1].get("warm_calibrated", "absent") is None:
            del got[-1]["warm_calibrated"]
    assert got == case["decisions"]


def test_fixture_covers_every_rule() -> None:
    rules = {c["config"]["rule"] for c in FIXTURE["cases"]}
    assert rules == {"cp", "entropy", "relevance", "max_steps"}
    assert sum(1 for c in FIXTURE["cases"] for d in c["decisions"] if d and not d["stop"]) > 100

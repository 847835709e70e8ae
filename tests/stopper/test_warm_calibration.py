"""Warm starts and their conformal tables: a table records whether its traces were cold or warm and the memory
bounds of the warm ones; `eqa calibrate` refuses cold and warm traces together; the stopper stops a warm start
on the warm table, or says in every decision that its stopping is not calibrated for warm starts; the first
question in an empty home is a cold one."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from eqa.messages import MemoryBounds, MemoryScore, Question, StepScores, StopConfig, WarmStart
from services.stopper import synthetic
from services.stopper.calibration import CalibrationTable, Trace, calibrate
from services.stopper.conformal import CalibrationError
from services.stopper.state import WARM_NOT_CALIBRATED, EpisodeRecord, decide, resolve_calibration

REPO = Path(__file__).resolve().parents[2]
BOUNDS = MemoryBounds(max_views=24, warm_views=24, memory_steps=0, warm_budget=0.15, warm_area="observed",
                      stale_weight=0.0)
WARM = WarmStart(version=3, bounds=BOUNDS)


def _traces(n: int, seed: int, prefix: str) -> list[Trace]:
    return [synthetic.to_trace(e, f"{prefix}{i:03d}") for i, e in enumerate(synthetic.episodes(n, seed))]


def _warm(traces: list[Trace], warm: WarmStart | None = WARM) -> list[Trace]:
    return [t.model_copy(update={"memory_steps": 2, "warm": warm}) for t in traces]


def test_a_table_records_cold_or_warm_and_mixed_traces_are_refused() -> None:
    cold, warm = _traces(20, 1, "c"), _warm(_traces(20, 2, "w"))
    assert calibrate(cold, [0.2]).provenance["home"] == {"warm": False}
    assert calibrate(warm, [0.2]).provenance["home"] == {"warm": True, "bounds": BOUNDS.model_dump()}
    # a trace that says nothing of its start but has memory steps (an older warm trace) is warm
    old = [t.model_copy(update={"warm": None}) for t in warm]
    assert calibrate(old, [0.2]).provenance["home"] == {"warm": True, "bounds": None}
    with pytest.raises(CalibrationError, match=r"mixed cold and warm traces: 20 cold .* 20 warm"):
        calibrate([*cold, *warm], [0.2])
    other = _warm(_traces(20, 3, "o"), WarmStart(version=1, bounds=BOUNDS.model_copy(update={"max_views": 48})))
    with pytest.raises(CalibrationError, match="2 different memory bounds"):
        calibrate([*warm, *other], [0.2])
    with pytest.raises(CalibrationError, match="not recorded"):
        calibrate([*warm, *(t.model_copy(update={"question_id": "x" + t.question_id}) for t in old[:5])], [0.2])


def test_eqa_calibrate_from_traces_refuses_mixed_cold_and_warm_traces(tmp_path: Path) -> None:
    path = tmp_path / "mixed.jsonl"
    path.write_text("".join(t.model_dump_json() + "\n" for t in [*_traces(15, 1, "c"), *_warm(_traces(15, 2, "w"))]))
    env = {**os.environ, "EQA_DATA_DIR": str(tmp_path / "var"), "EQA_REDIS_URL": "", "EQA_LOG_LEVEL": "WARNING"}
    p = subprocess.run([sys.executable, "-m", "eqa_app.calibrate", "calibrate", "--no-progress", "--from-traces",
                        str(path), "--name", "mixed", "--eps", "0.2"], cwd=REPO, env=env, capture_output=True,
                       text=True, timeout=120)
    assert p.returncode == 2 and "mixed cold and warm traces: 15 cold" in p.stderr, p.stderr


def _question() -> Question:
    return Question(id="q", text="What colour is the sofa?", choices=["red", "blue", "green", "grey"],
                    scene="gen-00001", answer="B", category="identification")


def _record(home_table: CalibrationTable | None, missing: str = "") -> EpisodeRecord:
    cold = calibrate(_traces(40, 5, "c"), [0.2], name="cold")
    record = EpisodeRecord(episode_id="ep", robot="r0", question=_question(), strategy="semantic",
                           stop=StopConfig(rule="cp", eps=0.2), max_steps=10, choices=_question().choices)
    record.calibration, _ = resolve_calibration(cold, "store", 0.2, "cold")
    if home_table is not None:
        record.warm_calibration, _ = resolve_calibration(home_table, "store", 0.2, home_table.name)
    record.warm_missing = missing
    return record


def _step0(warm: WarmStart | None) -> StepScores:
    memory = [MemoryScore(answer_probs=[0.25] * 4, relevance=0.1)] * (2 if warm else 0)
    return StepScores(episode_id="ep", step=0, answer_probs=[0.3, 0.3, 0.2, 0.2], relevance=0.2, memory=memory,
                      warm=warm)


def test_a_warm_start_stops_on_the_warm_table_and_a_cold_start_on_the_cold_one() -> None:
    warm_table = calibrate(_warm(_traces(40, 6, "w")), [0.2], name="warm")
    record = _record(warm_table)
    cold_q = record.calibration.q_hat  # type: ignore[union-attr]
    warm_q = warm_table.lookup(0.2)[0].q_hat  # type: ignore[index]
    assert warm_q != cold_q
    first = decide(record.model_copy(deep=True), _step0(None))  # the first question in an empty home: cold
    assert first is not None and first.q_hat == cold_q and first.warm_calibrated is None
    assert WARM_NOT_CALIBRATED not in first.reason
    rec = record.model_copy(deep=True)
    d = decide(rec, _step0(WARM))
    assert d is not None and d.q_hat == warm_q and d.warm_calibrated is True and WARM_NOT_CALIBRATED not in d.reason
    later = decide(rec, StepScores(episode_id="ep", step=1, answer_probs=[0.3, 0.3, 0.2, 0.2], relevance=0.2))
    assert later is not None and later.q_hat == warm_q and later.warm_calibrated is True
    assert rec.trace() is not None and rec.trace().warm == WARM  # type: ignore[union-attr]


def test_a_warm_start_without_a_matching_warm_table_says_its_stopping_is_not_calibrated() -> None:
    # no warm table named: the cold table, and every decision says so
    rec = _record(None, "no warm table is named (EQA_HOME_CALIBRATION_NAME is empty)")
    cold_q = rec.calibration.q_hat  # type: ignore[union-attr]
    d = decide(rec, _step0(WARM))
    assert d is not None and d.q_hat == cold_q and d.warm_calibrated is False
    assert WARM_NOT_CALIBRATED in d.reason and "EQA_HOME_CALIBRATION_NAME is empty" in d.reason
    d1 = decide(rec, StepScores(episode_id="ep", step=1, answer_probs=[0.3, 0.3, 0.2, 0.2], relevance=0.2))
    assert d1 is not None and d1.warm_calibrated is False and WARM_NOT_CALIBRATED in d1.reason
    # a warm table of other memory bounds: its q_hat, with the mismatch named
    other = calibrate(_warm(_traces(40, 6, "w"), WarmStart(version=1, bounds=BOUNDS.model_copy(
        update={"warm_budget": 1.0}))), [0.2], name="warm-full-budget")
    d = decide(_record(other), _step0(WARM))
    assert d is not None and d.warm_calibrated is False and "warm_budget 1.0 vs 0.15" in d.reason
    # a table of cold episodes named as the warm one
    cold_named = calibrate(_traces(40, 7, "c"), [0.2], name="cold-again")
    d = decide(_record(cold_named), _step0(WARM))
    assert d is not None and d.warm_calibrated is False and "calibrated on cold episodes" in d.reason

"""Calibration traces, tables and `eqa calibrate` (real stores, real subprocesses)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from eqa.store import EmbeddedStore, Store
from services.stopper import calibration, synthetic
from services.stopper.calibration import (
    CalibrationTable,
    Trace,
    TraceStore,
    calibrate,
    load_table,
    save_table,
    table_key,
)
from services.stopper.conformal import CalibrationError, conformal_quantile
from services.stopper.state import backend_mismatch, resolve_calibration

REPO = Path(__file__).resolve().parents[2]


def _traces(n: int, seed: int = 0) -> list[Trace]:
    return [synthetic.to_trace(e, f"q{i:04d}") for i, e in enumerate(synthetic.episodes(n, seed))]


def test_trace_store_roundtrip_sets_and_episodes(store: Store) -> None:
    ts = TraceStore(store)
    traces = _traces(5)
    odd = traces[0].model_copy(update={"question_id": "hm/eqa [1]?*:x"})  # glob and separator characters
    for t in [*traces[1:], odd]:
        ts.save("calibration-semantic-oracle", t)
    assert ts.has("calibration-semantic-oracle", "hm/eqa [1]?*:x")
    assert not ts.has("calibration-semantic-oracle", "q0000")
    assert not ts.has("other-set", "q0001")
    loaded = ts.load("calibration-semantic-oracle")
    assert sorted(t.question_id for t in loaded) == sorted(["q0001", "q0002", "q0003", "q0004", "hm/eqa [1]?*:x"])
    assert {t.question_id: t for t in loaded}["q0002"] == traces[2]
    ts.save_episode("ep-1", traces[3])
    assert ts.trace_for_episode("ep-1") == traces[3]
    assert ts.trace_for_episode("ep-unknown") is None
    with pytest.raises(ValueError, match="trace set name"):
        ts.save("bad name!", traces[0])


def test_trace_with_nan_is_refused_and_nothing_stored(store: Store) -> None:
    ts = TraceStore(store)
    good = _traces(1)[0]
    steps = [s.model_copy() for s in good.steps]
    steps[1] = steps[1].model_copy(update={"answer_probs": [float("nan")] * 4})
    broken = Trace.model_construct(**{**good.__dict__, "steps": steps})
    with pytest.raises(ValueError, match="NaN"):
        ts.save("s", broken)
    assert not ts.has("s", good.question_id)
    with pytest.raises(ValueError, match="NaN"):
        Trace.model_validate({**good.model_dump(), "steps": [s.model_dump() for s in steps]})


def test_calibrate_kappas_and_q_hat(store: Store) -> None:
    traces = _traces(120, seed=4)
    table = calibrate(traces, [0.5, 0.1, 0.2], name="t1", provenance={"source": "synthetic"})
    assert table.n == 120 and table.eps_grid == [0.1, 0.2, 0.5]
    for t, k in zip(traces, table.kappas, strict=True):
        f, rel = t.arrays()
        y = "ABCD".index(t.answer or "")
        assert k == pytest.approx(1 - min(rel[s] * (f[s, y] - 1) for s in range(len(rel))))
        assert 1.0 <= k <= 2.0
    for e in table.entries:
        assert e.q_hat == conformal_quantile(table.kappas, e.eps)
    save_table(store, table)
    again, where = load_table(store, "t1")
    assert again == table and "store" in where


def test_calibrate_refuses_small_sets_bad_traces_and_leaves_the_store_alone(store: Store) -> None:
    save_table(store, calibrate(_traces(30), [0.2], name="keep"))
    before = store.get(table_key("keep"))
    with pytest.raises(CalibrationError, match=r"undefined for eps 0.05.*ceil\(1/eps\) - 1 = 19"):
        calibrate(_traces(18), [0.05, 0.2], name="keep")
    no_truth = _traces(30)
    no_truth[3] = no_truth[3].model_copy(update={"answer": None})
    with pytest.raises(CalibrationError, match="no ground-truth answer"):
        calibrate(no_truth, [0.2], name="keep")
    with pytest.raises(CalibrationError, match="duplicate"):
        calibrate(_traces(30) + _traces(1), [0.2], name="keep")
    with pytest.raises(CalibrationError, match="no calibration traces"):
        calibrate([], [0.2])
    assert store.get(table_key("keep")) == before


def test_lookup_nearest_lower_eps_and_packaged_fallback(
    store: Store, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    table = calibrate(_traces(60), [0.1, 0.3], name="pkg")
    entry, exact = table.lookup(0.3) or (None, None)
    assert entry is not None and exact and entry.eps == 0.3
    entry, exact = table.lookup(0.25) or (None, None)
    assert entry is not None and not exact and entry.eps == 0.1
    assert table.lookup(0.05) is None
    choice, why = resolve_calibration(table, "x", 0.25, "pkg")
    assert choice is not None and choice.eps == 0.1 and "nearest stored eps=0.1" in choice.note and not why
    choice, why = resolve_calibration(table, "x", 0.05, "pkg")
    assert choice is None and "eqa calibrate" in why
    # scores of another backend than the table's: said in every reason (Claim 1 holds for the calibrated model)
    oracle_table = table.model_copy(update={"provenance": {"scorer_backend": "oracle"}})
    choice, _ = resolve_calibration(oracle_table, "x", 0.3, "pkg")
    assert choice is not None and choice.backend == "oracle"
    assert backend_mismatch(choice, "oracle") == "" and backend_mismatch(choice, None) == ""
    assert "calibrated on the oracle scorer, these scores come from hf" in backend_mismatch(choice, "hf")
    choice, why = resolve_calibration(None, "nowhere", 0.2, "pkg")
    assert choice is None and "eqa calibrate --name pkg" in why

    monkeypatch.setattr(calibration, "DATA_DIR", tmp_path)
    assert load_table(store, "pkg")[0] is None
    (tmp_path / "pkg.json").write_text(table.model_dump_json())
    loaded, where = load_table(store, "pkg")
    assert loaded == table and "pkg.json" in where
    store.set(table_key("pkg"), b"{not json")  # a corrupt stored table is skipped, not used
    loaded, where = load_table(store, "pkg")
    assert loaded == table and "pkg.json" in where


# ---- the CLI, as a real process ---------------------------------------------------------------------------


def _env(data_dir: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("EQA_")}
    env.update(EQA_DATA_DIR=str(data_dir), EQA_LOG_LEVEL="WARNING", RERUN_TELEMETRY_ENABLED="false")
    return env


def _cli(args: list[str], data_dir: Path, **kw: object) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "eqa_app.calibrate", "calibrate", "--no-progress", *args],
        cwd=REPO,
        env=_env(data_dir),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        **kw,  # type: ignore[call-overload]
    )


def _run(args: list[str], data_dir: Path) -> tuple[int, str, str]:
    p = _cli(args, data_dir)
    out, err = p.communicate(timeout=60)
    return p.returncode, out, err


def _stored_table(data_dir: Path, name: str) -> CalibrationTable | None:
    s = EmbeddedStore(data_dir / "store.sqlite")
    try:
        raw = s.get(table_key(name))
        return None if raw is None else CalibrationTable.model_validate_json(raw)
    finally:
        s.close()


def test_calibrate_cli_killed_halfway_resumes_to_the_same_q_hat(tmp_path: Path) -> None:
    traces = _traces(40, seed=11)
    lines = [t.model_dump_json() + "\n" for t in traces]
    full = tmp_path / "traces.jsonl"
    full.write_text("".join(lines))
    common = ["--set-name", "cal-test", "--name", "resume", "--eps", "0.1,0.2,0.5"]

    # reference: one uninterrupted run in its own data dir
    code, out, err = _run(["--from-traces", str(full), *common], tmp_path / "ref")
    assert code == 0, err
    assert "N=40" in out
    reference = _stored_table(tmp_path / "ref", "resume")
    assert reference is not None

    # interrupted run: the traces arrive through a FIFO; SIGKILL once half of them are stored
    data = tmp_path / "var"
    fifo = tmp_path / "traces.fifo"
    os.mkfifo(fifo)
    proc = _cli(["--from-traces", str(fifo), *common], data)
    half = len(lines) // 2
    with open(fifo, "w") as w:  # blocks until the CLI opens the FIFO
        w.write("".join(lines[:half]))
        w.flush()
        deadline = time.monotonic() + 30
        store = EmbeddedStore(data / "store.sqlite")
        try:
            ts = TraceStore(store)
            while not all(ts.has("cal-test", t.question_id) for t in traces[:half]):
                assert time.monotonic() < deadline, "the CLI did not store the traces it read"
                assert proc.poll() is None, proc.communicate()
                time.sleep(0.05)
            proc.kill()
            proc.wait(timeout=10)
            assert len(ts.load("cal-test")) == half
        finally:
            store.close()
    proc.communicate()
    assert _stored_table(data, "resume") is None, "a killed run stores no table"

    code, out, err = _run(["--from-traces", str(full), *common], data)
    assert code == 0, err
    resumed = _stored_table(data, "resume")
    assert resumed is not None
    assert resumed.kappas == reference.kappas and resumed.n == 40
    assert [(e.eps, e.q_hat) for e in resumed.entries] == [(e.eps, e.q_hat) for e in reference.entries]


def test_calibrate_cli_bad_input(tmp_path: Path) -> None:
    good = _traces(12)
    path = tmp_path / "t.jsonl"
    path.write_text("".join(t.model_dump_json() + "\n" for t in good))
    data = tmp_path / "var"

    code, _, err = _run(["--from-traces", str(path), "--eps", "0.2,1.5"], data)
    assert code == 2 and "(0, 1)" in err and err.count("\n") == 1
    code, _, err = _run(["--from-traces", str(path), "--eps", "0.05", "--name", "small"], data)
    assert code == 2 and "undefined" in err and "19" in err
    assert _stored_table(data, "small") is None
    bad = json.loads(good[0].model_dump_json())
    bad["question_id"] = "nan-one"
    bad["steps"][0]["answer_probs"][0] = float("nan")
    path2 = tmp_path / "nan.jsonl"
    path2.write_text(good[1].model_dump_json() + "\n" + json.dumps(bad) + "\n")
    code, _, err = _run(["--from-traces", str(path2), "--eps", "0.5", "--name", "nan"], data)
    assert code == 2 and "nan.jsonl:2" in err and "NaN" in err
    assert _stored_table(data, "nan") is None
    code, _, err = _run(["--from-traces", str(tmp_path / "missing.jsonl")], data)
    assert code == 2 and "does not exist" in err
    code, _, err = _run(
        ["--from-traces", str(path), "--eps", "0.5", "--name", "ok", "--out", str(tmp_path / "ok.json")], data
    )
    assert code == 0, err
    assert CalibrationTable.model_validate_json((tmp_path / "ok.json").read_text()) == _stored_table(data, "ok")

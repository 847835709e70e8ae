"""Benchmark traces on disk (services/stopper/calibration.py read_jsonl / write_jsonl): the stored sets are gzip
JSONL, written with deterministic bytes, and every reader takes .jsonl and .jsonl.gz alike."""

from __future__ import annotations

import gzip
from pathlib import Path

import pytest

from eqa_app.bench_cli import trace_file
from eqa_app.calibrate import main as calibrate_main
from services.stopper import synthetic
from services.stopper.calibration import CalibrationError, read_jsonl, write_jsonl


def _traces(n: int, seed: int = 0) -> list:
    return [synthetic.to_trace(e, f"q{i:04d}") for i, e in enumerate(synthetic.episodes(n, seed))]


def test_gzip_round_trip_with_the_same_bytes_each_time(tmp_path: Path) -> None:
    traces = _traces(12, seed=3)
    a, b, plain = tmp_path / "a.jsonl.gz", tmp_path / "b.jsonl.gz", tmp_path / "c.jsonl"
    write_jsonl(a, traces)
    write_jsonl(b, traces)
    write_jsonl(plain, traces)
    assert a.read_bytes() == b.read_bytes(), "an export of the same traces must not change the committed file"
    assert a.read_bytes()[:2] == b"\x1f\x8b" and gzip.decompress(a.read_bytes()) == plain.read_bytes()
    assert [t for _, t in read_jsonl(a)] == traces == [t for _, t in read_jsonl(plain)]
    assert not list(tmp_path.glob("*.tmp"))


def test_a_malformed_compressed_line_is_named(tmp_path: Path) -> None:
    path = tmp_path / "bad.jsonl.gz"
    path.write_bytes(gzip.compress(b'{"question_id": "q"}\n'))
    with pytest.raises(CalibrationError, match=r"bad\.jsonl\.gz:1"):
        list(read_jsonl(path))


def test_trace_file_prefers_the_compressed_name_and_keeps_an_existing_plain_one(tmp_path: Path) -> None:
    assert trace_file(tmp_path, "set") == tmp_path / "set.jsonl.gz"
    (tmp_path / "old.jsonl").write_text("")
    assert trace_file(tmp_path, "old") == tmp_path / "old.jsonl"


def test_calibrate_from_compressed_traces_gives_the_plain_file_table(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.delenv("EQA_REDIS_URL", raising=False)
    traces = _traces(60, seed=5)
    outs = []
    for name in ("t.jsonl", "t.jsonl.gz"):
        monkeypatch.setenv("EQA_DATA_DIR", str(tmp_path / name / "var"))
        write_jsonl(tmp_path / name / name, traces)
        table = tmp_path / name / "table.json"
        assert calibrate_main(["calibrate", "--from-traces", str(tmp_path / name / name), "--name", "gz",
                               "--eps", "0.1,0.2", "--no-progress", "--out", str(table)]) == 0
        outs.append(capsys.readouterr().out)
        assert "N=60" in outs[-1]
    q = [line for out in outs for line in out.splitlines() if "q_hat" in line]
    assert q and q[: len(q) // 2] == q[len(q) // 2:]

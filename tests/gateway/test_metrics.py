"""eqa.metrics in one process: nothing is counted while off, the store's calls are timed once each (a nested
call is part of the outer one) and their errors counted by type, several apps and services share one
registry, and the exposition parses with prometheus_client's own parser."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path

import pytest
from prometheus_client.parser import text_string_to_metric_families

from eqa import logs, metrics
from eqa.settings import Settings
from eqa.store import EmbeddedStore, StoreError


def _value(name: str, **labels: str) -> float:
    text = metrics.exposition().decode()
    total = 0.0
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            if s.name == name and set(labels.items()) <= set(s.labels.items()):
                total += s.value
    return total


@pytest.fixture
def counting() -> Iterator[None]:
    was = metrics.enabled()
    metrics.enable()
    try:
        yield
    finally:
        metrics.enable(was)


def test_nothing_is_counted_while_off(tmp_path: Path) -> None:
    was = metrics.enabled()
    metrics.enable(False)
    try:
        before = (_value("eqa_resends_total", service="t-off"), _value("eqa_store_seconds_count", op="get"))
        metrics.inc(metrics.RESENDS, "t-off", "frame")
        with metrics.timer(metrics.STEP_SECONDS, "t-off", "frame"):
            pass
        EmbeddedStore(tmp_path / "s.sqlite").get("k")
        assert (_value("eqa_resends_total", service="t-off"), _value("eqa_store_seconds_count", op="get")) == before
        assert _value("eqa_step_seconds_count", service="t-off") == 0
        assert metrics.serve(Settings(data_dir=tmp_path), "t-off") is None  # port 0: no server, still off
        assert not metrics.enabled()
    finally:
        metrics.enable(was)


def test_store_calls_are_timed_once_and_errors_counted_by_type(tmp_path: Path, counting: None) -> None:
    store = EmbeddedStore(tmp_path / "s.sqlite")
    ops = ("set_if_absent", "get", "set", "read")
    before = {op: _value("eqa_store_seconds_count", backend="sqlite", op=op) for op in ops}
    errors = _value("eqa_store_errors_total", backend="sqlite", op="read")
    assert store.set_if_absent("k", b"v") and not store.set_if_absent("k", b"w")  # each calls get (and set)
    after = {op: _value("eqa_store_seconds_count", backend="sqlite", op=op) for op in ops}
    assert after["set_if_absent"] - before["set_if_absent"] == 2
    assert after["get"] == before["get"] and after["set"] == before["set"]  # nested: not counted again
    with pytest.raises(StoreError):
        store.read("stream", after="not-an-id")
    assert _value("eqa_store_errors_total", backend="sqlite", op="read", error="StoreError") == errors + 1
    assert _value("eqa_store_seconds_count", backend="sqlite", op="read") == before["read"] + 1


def test_two_gateway_apps_and_services_in_one_process_share_the_registry(tmp_path: Path, counting: None) -> None:
    from gateway.app import create_app

    settings = Settings(data_dir=tmp_path)
    paths = [{getattr(r, "path", None) for r in create_app(settings).routes} for _ in range(2)]
    assert all("/metrics" in p for p in paths)
    metrics.inc(metrics.STEP_CLAIMS, "svc-a", "won")
    metrics.inc(metrics.STEP_CLAIMS, "svc-b", "won")
    for service in ("svc-a", "svc-b"):
        assert _value("eqa_step_claims_total", service=service, outcome="won") >= 1


def test_json_lines_carry_the_bound_context(capsys: pytest.CaptureFixture[str]) -> None:
    import json
    import sys

    handler = logs.handler(sys.stderr, "probe", "json")
    logger = logging.getLogger("eqa.test.json")
    logger.addHandler(handler)
    logger.propagate = False
    logger.setLevel(logging.INFO)
    try:
        logs.set_process(service="probe", instance="probe-1")
        logger.warning("outside")
        with logs.bind(episode="ep-1", robot="r0", step=3):
            logger.info("inside %d", 7)
            try:
                raise RuntimeError("boom")
            except RuntimeError:
                logger.exception("failed")
    finally:
        logger.removeHandler(handler)
        logs._PROCESS.clear()
    lines = [json.loads(x) for x in capsys.readouterr().err.splitlines()]
    assert [x["message"] for x in lines] == ["outside", "inside 7", "failed"]
    assert "episode" not in lines[0] and lines[0]["service"] == "probe" and lines[0]["instance"] == "probe-1"
    assert {k: lines[1][k] for k in ("episode", "robot", "step", "service")} == {
        "episode": "ep-1", "robot": "r0", "step": 3, "service": "probe"}
    assert lines[1]["level"] == "INFO" and lines[1]["logger"] == "eqa.test.json"
    assert "RuntimeError: boom" in lines[2]["exc"]
    with pytest.raises(ValueError, match="EQA_LOG_FORMAT"):
        logs.handler(sys.stderr, "probe", "xml")

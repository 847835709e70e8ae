"""The alerts of deploy/prometheus-rules.yml: Prometheus' own checker accepts them, their unit tests
(deploy/prometheus-rules.test.yml) pass under ``promtool test rules``, every alert has a test case where it
fires and one where it stays silent, and the rules and the test series name only metrics and labels the code
exports (eqa/metrics.py, gateway/metrics.py)."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest
import yaml
from prometheus_client import Counter, Gauge, Histogram
from support.promtool import SKIP_REASON, promtool

from eqa import metrics as kernel_metrics
from gateway import metrics as gateway_metrics

REPO = Path(__file__).resolve().parents[2]
RULES = REPO / "deploy" / "prometheus-rules.yml"
RULE_TESTS = REPO / "deploy" / "prometheus-rules.test.yml"
SCRAPE_LABELS = {"job", "instance"}  # added by Prometheus to every scraped series
METRIC_RE = re.compile(r"\b(eqa_[a-z_]+)")


def _alerts() -> dict[str, str]:
    groups = yaml.safe_load(RULES.read_text())["groups"]
    return {r["alert"]: r["expr"] for g in groups for r in g["rules"] if "alert" in r}


def _exported() -> dict[str, set[str] | None]:
    """Series names the code exports and their label names (None: labels not known statically)."""
    out: dict[str, set[str] | None] = {}
    for module in (kernel_metrics, gateway_metrics):
        for obj in vars(module).values():
            labels = set(getattr(obj, "_labelnames", ()))
            if isinstance(obj, Counter):
                out[f"{obj._name}_total"] = labels
            elif isinstance(obj, Histogram):
                for suffix in ("_bucket", "_count", "_sum"):
                    out[obj._name + suffix] = labels | ({"le"} if suffix == "_bucket" else set())
            elif isinstance(obj, Gauge):
                out[obj._name] = labels
    for family in gateway_metrics.COLLECTOR.collect():  # the gauges read at scrape time
        out[family.name] = None
    return out


def _tool() -> str:
    found = promtool()
    if found is None:
        pytest.skip(SKIP_REASON)
    return found


def test_promtool_accepts_the_rules():
    out = subprocess.run([_tool(), "check", "rules", str(RULES)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stdout + out.stderr
    assert f"SUCCESS: {len(_alerts())} rules found" in out.stdout, out.stdout


def test_the_rules_unit_tests_pass():
    out = subprocess.run([_tool(), "test", "rules", str(RULE_TESTS)], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "SUCCESS" in out.stdout, out.stdout


def test_every_alert_has_a_firing_and_a_silent_case():
    cases: dict[str, set[bool]] = {}
    for test in yaml.safe_load(RULE_TESTS.read_text())["tests"]:
        for case in test.get("alert_rule_test", []):
            cases.setdefault(case["alertname"], set()).add(bool(case.get("exp_alerts")))
    for alert in _alerts():
        assert cases.get(alert) == {True, False}, f"{alert}: test cases {cases.get(alert)} (need firing and silent)"
    assert set(cases) <= set(_alerts()), f"tests name unknown alerts: {set(cases) - set(_alerts())}"


def test_the_rules_and_their_tests_use_exported_metrics_and_labels():
    exported = _exported()
    assert "eqa_gateway_service_instances" in exported and "eqa_step_seconds_count" in exported
    for alert, expr in _alerts().items():
        for name in METRIC_RE.findall(expr):
            assert name in exported, f"{alert} uses {name}, which the code does not export"
    for test in yaml.safe_load(RULE_TESTS.read_text())["tests"]:
        for series in test["input_series"]:
            m = re.fullmatch(r"(\w+)\{(.*)\}", series["series"])
            assert m, series
            name, labels = m.group(1), set(re.findall(r"(\w+)=", m.group(2)))
            if name == "up":
                continue
            assert name in exported, f"test series {name} is not exported by the code"
            known = exported[name]
            if known is not None:
                assert labels - SCRAPE_LABELS == known, f"{name}: labels {sorted(labels)}, code has {sorted(known)}"

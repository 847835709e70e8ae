"""The compose file cannot run here (no Docker engine), so check what can be checked: every service command
names a module that exists and runs, the health checks call real commands, and the EQA_* variables set are
exactly ones the code reads (and the code reads no EQA_* variable outside eqa/settings.py)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from eqa.dataflow import SERVICES
from eqa.settings import env_names

REPO = Path(__file__).resolve().parents[2]
COMPOSE = yaml.safe_load((REPO / "docker-compose.yml").read_text())
EQA_SERVICES = set(SERVICES)


def _module_exists(module: str) -> bool:
    path = REPO / Path(*module.split("."))
    return (path / "__main__.py").is_file()


def test_every_service_has_a_container_and_a_runnable_module():
    services = COMPOSE["services"]
    assert {"zenoh", "redis"} <= set(services)
    assert set(services) >= EQA_SERVICES
    for name in EQA_SERVICES:
        cmd = services[name]["command"]
        assert cmd[:2] == ["python", "-m"], name
        assert _module_exists(cmd[2]), f"{name}: module {cmd[2]} has no __main__.py"
        out = subprocess.run([sys.executable, "-m", cmd[2], "--help"], capture_output=True, text=True, timeout=240,
                             cwd=REPO)
        assert out.returncode == 0 and "EQA_" in out.stdout, f"{cmd[2]} --help failed: {out.stderr[-500:]}"
        assert "healthcheck" in services[name], name


def test_scorer_scales_with_replicas_and_points_at_the_router():
    scorer = COMPOSE["services"]["vlm_scorer"]
    assert scorer["deploy"]["replicas"] >= 2
    assert scorer["environment"]["EQA_ZENOH_CONNECT"] == "tcp/zenoh:7447"
    assert "7447" in " ".join(COMPOSE["services"]["zenoh"]["command"])


def test_environment_variables_are_the_ones_the_code_reads():
    known = env_names()
    for name in EQA_SERVICES:
        env = COMPOSE["services"][name]["environment"]
        unknown = {k for k in env if k.startswith("EQA_")} - known
        assert not unknown, f"{name} sets variables no code reads: {unknown}"
        for required in ("EQA_ZENOH_CONNECT", "EQA_REDIS_URL", "EQA_DATA_DIR"):
            assert required in env, f"{name} lacks {required}"
    dockerfile = (REPO / "Dockerfile").read_text()
    assert set(re.findall(r"\b(EQA_[A-Z_]+)=", dockerfile)) <= known


def test_code_reads_eqa_variables_only_through_settings():
    pattern = re.compile(r"(?:os\.environ(?:\.get)?\s*[\[(]|os\.getenv\s*\()\s*[\"'](EQA_[A-Z_]+)")
    offenders = []
    for path in [*REPO.glob("eqa/**/*.py"), *REPO.glob("services/**/*.py"), *REPO.glob("gateway/**/*.py")]:
        if path.name == "settings.py":
            continue
        offenders += [f"{path.relative_to(REPO)}: {m}" for m in pattern.findall(path.read_text())]
    assert not offenders, offenders


def test_health_command_exists_for_the_checks():
    out = subprocess.run([sys.executable, "-m", "eqa_app", "health", "--help"], capture_output=True, text=True,
                         timeout=60, cwd=REPO)
    assert out.returncode == 0, out.stderr


class _Override(yaml.SafeLoader):
    """Reads podman-compose's ``!override`` / ``!reset`` tags (plain values here)."""


_Override.add_constructor("!override", lambda loader, node: (
    loader.construct_sequence(node) if isinstance(node, yaml.SequenceNode) else loader.construct_mapping(node)))
_Override.add_constructor("!reset", lambda loader, node: None)


def test_podman_override_changes_only_what_cannot_be_pulled_here():
    """docker-compose.podman.yml swaps the two registry images for local ones and the published
    ports; the services, replicas, health checks and variables stay docker-compose.yml's."""
    override = yaml.load((REPO / "docker-compose.podman.yml").read_text(), Loader=_Override)
    services = override["services"]
    assert set(services) == {"zenoh", "redis", "vlm_scorer", "gateway"}
    assert services["vlm_scorer"] == {"deploy": {"mode": "replicated"}}  # replicas stay the main file's
    assert set(services["gateway"]) == {"ports"}
    assert all(p.startswith("127.0.0.1:") for p in services["gateway"]["ports"])
    router = services["zenoh"]["command"]
    assert router[:4] == ["python", "-m", "eqa_app", "router"] and "tcp/0.0.0.0:7447" in router
    assert _module_exists("eqa_app")
    assert set(services["zenoh"]["environment"]) <= env_names()
    assert services["redis"]["command"][0] == "redis-server"


def test_compose_file_assumes_nothing_of_this_machine():
    text = (REPO / "docker-compose.yml").read_text()
    assert "localhost/" not in text and "/opt/" not in text and "podman" not in text.lower()
    assert COMPOSE["services"]["zenoh"]["image"].startswith("eclipse/zenoh:")
    assert COMPOSE["services"]["redis"]["image"].startswith("redis:")
    dockerfile = (REPO / "Dockerfile").read_text()
    assert re.search(r"^ARG BASE=python:3\.11-slim$", dockerfile, re.M)
    assert "/opt/" not in dockerfile.replace("/opt/venv", "")


def test_the_monitoring_profile_scrapes_every_service():
    """Prometheus runs only in the ``monitoring`` profile, with deploy/prometheus.yml, and that file scrapes
    every service on the port compose gives it (the services' EQA_METRICS_PORT, the gateway's API port)."""
    prom = COMPOSE["services"]["prometheus"]
    assert prom["profiles"] == ["monitoring"] and prom["image"].startswith("prom/prometheus:v")
    mounted = {v.split(":")[0]: v.split(":")[1] for v in prom["volumes"] if v.startswith("./")}
    assert mounted == {"./deploy/prometheus.yml": "/etc/prometheus/prometheus.yml",
                       "./deploy/prometheus-rules.yml": "/etc/prometheus/prometheus-rules.yml"}
    assert "--config.file=/etc/prometheus/prometheus.yml" in prom["command"]
    config = yaml.safe_load((REPO / "deploy" / "prometheus.yml").read_text())
    jobs = {job["job_name"]: job for job in config["scrape_configs"]}
    assert set(jobs) == EQA_SERVICES
    for name in EQA_SERVICES - {"gateway"}:
        env = COMPOSE["services"][name]["environment"]
        assert env["EQA_METRICS_HOST"] == "0.0.0.0", name
        (sd,) = jobs[name]["dns_sd_configs"]
        assert sd["names"] == [name] and sd["type"] == "A" and str(sd["port"]) == env["EQA_METRICS_PORT"], name
    gateway = COMPOSE["services"]["gateway"]["environment"]
    (static,) = jobs["gateway"]["static_configs"]
    assert static["targets"] == [f"gateway:{gateway['EQA_GATEWAY_PORT']}"]
    assert jobs["gateway"]["metrics_path"] == "/metrics" and "EQA_METRICS_TOKEN" in gateway


def test_the_scrape_config_passes_promtool(tmp_path: Path):
    """Prometheus' own checker (``promtool``, Debian package ``prometheus``) accepts deploy/prometheus.yml."""
    from support.promtool import SKIP_REASON
    from support.promtool import promtool as find_promtool

    promtool = find_promtool()
    if promtool is None:
        pytest.skip(SKIP_REASON)
    text = (REPO / "deploy" / "prometheus.yml").read_text()
    token = tmp_path / "metrics_token"
    token.write_text("a-metrics-token\n")
    config = tmp_path / "prometheus.yml"
    config.write_text(text.replace("/etc/prometheus/secrets/metrics_token", str(token)).replace(
        "/etc/prometheus/prometheus-rules.yml", str(REPO / "deploy" / "prometheus-rules.yml")))
    out = subprocess.run([promtool, "check", "config", str(config)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "SUCCESS: 10 rules found" in out.stdout, out.stdout  # the rule file was read and its queries parsed
    # the queries docs/metrics.md shows parse too (as recording rules)
    queries = re.findall(r"```promql\n(.*?)```", (REPO / "docs" / "metrics.md").read_text(), re.S)
    assert len(queries) >= 8
    rules = [{"record": f"eqa:doc_query_{i}", "expr": q.strip()} for i, q in enumerate(queries)]
    doc_rules = tmp_path / "doc-queries.yml"
    doc_rules.write_text(yaml.safe_dump({"groups": [{"name": "docs", "rules": rules}]}))
    out = subprocess.run([promtool, "check", "rules", str(doc_rules)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stdout + out.stderr

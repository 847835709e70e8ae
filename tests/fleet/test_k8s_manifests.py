"""The Kubernetes base (deploy/k8s) checked statically: no cluster here (``make kube-smoke`` plays it under
podman; docs/deployment.md). The kustomization lists exactly the manifest files; every Deployment has
replicas, probes, resources and the project's image, runs a module that exists, sets only settings the code
reads, with values Settings accepts; every Service selects pods that exist on ports they declare; the settings
that name other services (router, Redis, ports) point at those Services."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
import tomllib
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import pytest
import yaml

from eqa.dataflow import SERVICES
from eqa.settings import Settings, env_names

REPO = Path(__file__).resolve().parents[2]
BASE = REPO / "deploy" / "k8s"
IMAGE = "eqa:latest"


def _smoke() -> Any:
    spec = importlib.util.spec_from_file_location("kube_smoke", REPO / "scripts" / "kube_smoke.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


SMOKE = _smoke()
DOCS = SMOKE.render(BASE)
DEPLOYMENTS = {d["metadata"]["name"]: d for d in DOCS if d["kind"] == "Deployment"}
SERVICES_K8S = {d["metadata"]["name"]: d for d in DOCS if d["kind"] == "Service"}
CONFIGMAPS = {d["metadata"]["name"]: d for d in DOCS if d["kind"] == "ConfigMap"}
CLAIMS = {d["metadata"]["name"]: d for d in DOCS if d["kind"] == "PersistentVolumeClaim"}
COMPOSE = yaml.safe_load((REPO / "docker-compose.yml").read_text())


def _container(name: str) -> dict:
    (c,) = SMOKE.containers(DEPLOYMENTS[name])
    return c


def _env(c: dict) -> dict[str, str]:
    """A container's environment as the kubelet builds it: envFrom ConfigMaps, then env (which wins)."""
    env: dict[str, str] = {}
    for source in c.get("envFrom", []):
        env.update(CONFIGMAPS[source["configMapRef"]["name"]]["data"])
    env.update({e["name"]: e["value"] for e in c.get("env", [])})
    return env


def _service_of(c: dict) -> str | None:
    """The EQA service name a container runs (``python -m services.<name>`` or ``python -m gateway``)."""
    cmd = c["command"]
    if cmd[:2] != ["python", "-m"]:
        return None
    return cmd[2].removeprefix("services.")


def _eqa_cli(*args: str) -> subprocess.CompletedProcess[str]:
    """The ``eqa`` command the image installs (pyproject's [project.scripts]), run from this tree."""
    target = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]["eqa"]
    module, func = target.split(":")
    code = f"import sys; from {module} import {func}; sys.exit({func}({list(args)!r}))"
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=REPO)


def test_the_kustomization_lists_exactly_the_manifest_files():
    listed = {p.name for p in SMOKE.resources(BASE)}
    present = {p.name for p in BASE.iterdir() if p.suffix in (".yaml", ".yml")} - {"kustomization.yaml"}
    assert listed == present


def test_the_renderer_refuses_what_it_would_not_apply(tmp_path: Path):
    (tmp_path / "a.yaml").write_text("apiVersion: v1\nkind: ConfigMap\nmetadata: {name: a}\n")
    kust = tmp_path / "kustomization.yaml"
    kust.write_text("apiVersion: kustomize.config.k8s.io/v1beta1\nkind: Kustomization\nresources: [a.yaml]\n")
    assert [d["metadata"]["name"] for d in SMOKE.render(tmp_path)] == ["a"]
    for extra in ("namePrefix: x-\n", "images: [{name: eqa, newTag: v2}]\n", "patches: []\n"):
        kust.write_text(kust.read_text().split("resources")[0] + "resources: [a.yaml]\n" + extra)
        with pytest.raises(ValueError, match="does not apply"):
            SMOKE.render(tmp_path)
    for bad in ("b.yaml", "../a.yaml", "https://example.org/x.yaml"):
        kust.write_text(f"apiVersion: kustomize.config.k8s.io/v1beta1\nkind: Kustomization\nresources: [{bad!r}]\n")
        with pytest.raises(ValueError, match="not a file"):
            SMOKE.render(tmp_path)


def test_images_are_set_as_kustomize_images_would():
    docs = SMOKE.set_images(DOCS, {"eqa": "registry.example/eqa", "redis": "localhost/eqa-redis:7"})
    images = {c["image"] for d in docs for c in SMOKE.containers(d)}
    assert images == {"registry.example/eqa:latest", "localhost/eqa-redis:7"}
    assert {c["image"] for d in DOCS for c in SMOKE.containers(d)} == {IMAGE, "redis:7-alpine"}  # a copy


def test_every_fleet_service_has_a_deployment_and_the_scorer_its_own():
    ran = {_service_of(_container(n)) for n in DEPLOYMENTS}
    assert ran >= set(SERVICES), f"no Deployment runs {set(SERVICES) - ran}"
    assert {"zenoh", "redis"} <= set(DEPLOYMENTS)
    scorer = DEPLOYMENTS["vlm-scorer"]
    assert [_service_of(c) for c in SMOKE.containers(scorer)] == ["vlm_scorer"]
    assert scorer["spec"]["replicas"] >= 2


def test_every_deployment_has_replicas_labels_probes_resources_and_the_image():
    for name, d in DEPLOYMENTS.items():
        assert isinstance(d["spec"].get("replicas"), int) and d["spec"]["replicas"] >= 1, name
        selector = d["spec"]["selector"]["matchLabels"]
        assert selector.items() <= SMOKE.pod_labels(d).items(), f"{name}: selector does not match its pods"
        assert selector == {"app.kubernetes.io/name": "eqa", "app.kubernetes.io/component": name}
        # a crashed process is restarted in its pod (the only policy a Deployment allows; podman honours others)
        assert d["spec"]["template"]["spec"].get("restartPolicy", "Always") == "Always", name
        for c in SMOKE.containers(d):
            for probe in ("readinessProbe", "livenessProbe"):
                assert probe in c, f"{name}: no {probe}"
                p = c[probe]
                kinds = {"exec", "httpGet", "tcpSocket"} & set(p)
                assert len(kinds) == 1, f"{name} {probe}: {p}"
                port = (p.get("httpGet") or p.get("tcpSocket") or {}).get("port")
                if port is not None:
                    SMOKE.container_port(c, port)  # a declared port
            res = c["resources"]
            assert {"cpu", "memory"} <= set(res["requests"]) and "memory" in res["limits"], name
            if name != "redis":
                assert c["image"] == IMAGE, f"{name}: {c['image']}"
            for mount in c.get("volumeMounts", []):
                (vol,) = [v for v in d["spec"]["template"]["spec"]["volumes"] if v["name"] == mount["name"]]
                assert vol["persistentVolumeClaim"]["claimName"] in CLAIMS, f"{name}: {vol}"


def test_commands_and_probes_run_what_exists():
    for name in DEPLOYMENTS:
        c = _container(name)
        service = _service_of(c)
        if service is None:
            continue
        module = c["command"][2]
        assert (REPO / Path(*module.split(".")) / "__main__.py").is_file(), f"{name}: no module {module}"
        ready, live = c["readinessProbe"], c["livenessProbe"]
        if service == "gateway":
            assert ready["httpGet"]["path"] == "/v1/ready" and live["httpGet"]["path"] == "/v1/health"
        else:
            assert ready["exec"]["command"] == ["eqa", "health", service], name
            assert live["httpGet"]["path"] == "/metrics"
            assert SMOKE.container_port(c, live["httpGet"]["port"]) == int(_env(c)["EQA_METRICS_PORT"])
    from gateway.routers.health import router

    assert {"/v1/ready", "/v1/health"} <= {r.path for r in router.routes}
    assert _container("zenoh")["command"][:2] == ["eqa", "router"]
    for sub in ("health", "router"):
        out = _eqa_cli(sub, "--help")
        assert out.returncode == 0, out.stderr[-500:]


def test_settings_are_the_ones_the_code_reads_and_parse(monkeypatch: pytest.MonkeyPatch):
    known = env_names()
    for cm in CONFIGMAPS.values():
        assert set(cm["data"]) <= known, f"{cm['metadata']['name']}: {set(cm['data']) - known}"
    for name in DEPLOYMENTS:
        c = _container(name)
        if _service_of(c) is None and name != "zenoh":
            continue
        env = _env(c)
        assert {k for k in env if k.startswith("EQA_")} <= known, f"{name}: {set(env) - known}"
        for k in [k for k in os.environ if k.startswith("EQA_")]:
            monkeypatch.delenv(k)
        for k, v in env.items():
            monkeypatch.setenv(k, v)
        Settings()  # raises on a value the code would refuse


def test_the_settings_point_at_the_services():
    def service_port(name: str) -> int:
        return int(SERVICES_K8S[name]["spec"]["ports"][0]["port"])

    for name in DEPLOYMENTS:
        c = _container(name)
        if _service_of(c) is None:
            continue
        env = _env(c)
        router = urlsplit("//" + env["EQA_ZENOH_CONNECT"].split("/", 1)[1])
        assert (router.hostname, router.port) == ("zenoh", service_port("zenoh")), name
        redis = urlsplit(env["EQA_REDIS_URL"])
        assert (redis.hostname, redis.port) == ("redis", service_port("redis")), name
    gw = _container("gateway")
    http = SERVICES_K8S["gateway"]["spec"]["ports"][0]
    assert SMOKE.container_port(gw, http["targetPort"]) == int(_env(gw)["EQA_GATEWAY_PORT"])
    assert _env(gw)["EQA_GATEWAY_HOST"] == "0.0.0.0"


def test_every_service_selects_existing_pods_on_declared_ports():
    for name, svc in SERVICES_K8S.items():
        selected = [d for d in DEPLOYMENTS.values() if svc in SMOKE.services_of(d, DOCS)]
        assert len(selected) == 1, f"Service {name} selects {[d['metadata']['name'] for d in selected]}"
        (c,) = SMOKE.containers(selected[0])
        for port in svc["spec"]["ports"]:
            SMOKE.container_port(c, port["targetPort"])


def test_per_service_settings_match_the_compose_file():
    """A service configured as in docker-compose.yml (secrets excepted: an overlay's Secret)."""
    secrets = {"EQA_API_TOKENS", "EQA_METRICS_TOKEN"}
    shared = set(COMPOSE["x-eqa-env"])
    for name in DEPLOYMENTS:
        c = _container(name)
        service = _service_of(c)
        if service is None:
            continue
        compose_env = {k: str(v) for k, v in COMPOSE["services"][service]["environment"].items()
                       if k not in shared and k not in secrets}
        own = {e["name"]: e["value"] for e in c.get("env", [])}
        assert own == compose_env, f"{name}: {own} vs compose {compose_env}"


@pytest.mark.parametrize("version", ["1.29.0", "1.37.0"])
def test_every_resource_is_valid_against_the_kubernetes_schemas(version: str):
    """The API's own OpenAPI schemas (kubernetes-validate), strict: an unknown or misplaced field is an error."""
    import kubernetes_validate

    for doc in DOCS:
        kubernetes_validate.validate(doc, version, strict=True)


def test_kustomize_renders_what_the_smoke_plays():
    """Where kubectl is installed (its built-in kustomize), `kubectl kustomize deploy/k8s` gives exactly the
    documents of the smoke's renderer (kustomize orders them by kind)."""
    import shutil

    kubectl = shutil.which("kubectl")
    if kubectl is None:
        pytest.skip("kubectl is not installed: the renderer is not compared with kustomize on this machine")
    out = subprocess.run([kubectl, "kustomize", str(BASE)], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-1000:]
    theirs = {(d["kind"], d["metadata"]["name"]): d for d in yaml.safe_load_all(out.stdout) if d}
    ours = {(d["kind"], d["metadata"]["name"]): d for d in DOCS}
    assert theirs == ours

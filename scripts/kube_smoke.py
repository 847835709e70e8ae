"""Smoke run of the Kubernetes manifests (deploy/k8s) under ``podman kube play`` (``make kube-smoke``).

There is no Kubernetes cluster here, nor kustomize or kubectl: the base is rendered by :func:`render`, which
reads exactly the ``resources`` of deploy/k8s/kustomization.yaml (and refuses any other kustomize field, so
that it can never silently skip a transformation), then played with podman, which runs Deployments (one pod
per replica), ConfigMaps (``envFrom``), PersistentVolumeClaims (named volumes), resources and restart
policies, but not Services and not readiness probes. So the smoke stands in for what a cluster does
beyond that, and only for that:

* **Service DNS**: every Deployment is played on its own, on one podman network, with each Service that
  selects its pods' labels as a DNS alias of those pods (``--network eqa-kube:alias=<service>``): ``zenoh`` and
  ``redis`` resolve to their pods as a ClusterIP name would, to every replica's address when there are several.
* **Probes**: podman turns a liveness probe into a health check it runs only on systemd timers (none here) and
  with ``curl``/``nc`` for HTTP/TCP probes (not in the image), and ignores readiness. The smoke runs every
  container's readiness and liveness probes itself as a kubelet does: ``exec`` inside the container with
  ``podman exec`` (argument vector, no shell), ``httpGet`` and ``tcpSocket`` against the pod's address.
* **Ports**: podman 4.3 publishes every ``containerPort`` on the host as if it had a ``hostPort``, so the
  played copy of a Deployment has no ``ports`` (nor probes: above); nothing else of the base is changed but
  the images (:data:`SMOKE_IMAGES`, what an overlay's ``images:`` would set). ``--render`` prints the rendered base with
  those images (ports and probes still in).
* **The gateway Service**: requests go to the address of the gateway pod once its readiness passes (what the
  Service's endpoints would hold), on the Service's target port.

Then one question (the demo's) through the gateway; at step 2 the first mapper pod's process is killed with
SIGKILL from the host and must be restarted by the pod's restart policy (``Always``, a Deployment's), pass its
probes again, and the episode must end ``stopped``. Everything is torn down at the end (pods, the volumes of
the PVCs, the network), also on failure. Exit 0 only if all of it happened.

Needs podman with ``localhost/eqa:latest`` and ``localhost/eqa-redis:7`` (``scripts/containers.sh setup`` and
``build``; ``make kube-smoke`` does both) and root.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

import yaml

REPO = Path(__file__).resolve().parents[1]
BASE = REPO / "deploy" / "k8s"
SUDO = [] if os.geteuid() == 0 else ["sudo"]
NETWORK = "eqa-kube"
# What an overlay of this machine sets with kustomize's `images:` (no registry here: the images are local).
SMOKE_IMAGES = {"eqa": "localhost/eqa", "redis": "localhost/eqa-redis:7"}
KUSTOMIZATION_FIELDS = {"apiVersion", "kind", "resources"}
# The demo's scene and question (``eqa ask`` without arguments): a 100 m2 house, the box in the kitchen.
QUESTION = {
    "question": "Is the box in the kitchen closed?", "choices": ["Yes", "No"], "scene": "gen-00151",
    "strategy": "semantic", "stop_rule": "cp", "eps": 0.2, "seed": 0, "max_steps": 30,
}
Doc = dict[str, Any]


class SmokeError(Exception):
    pass


def log(msg: str) -> None:
    print(f"[kube-smoke {time.strftime('%H:%M:%S')}] {msg}", flush=True)


# ---------------------------------------------------------------- rendering (pure: the manifests test uses it)

def resources(base: Path = BASE) -> list[Path]:
    """The files kustomization.yaml lists, in its order; only plain local files of ``base`` (no other field,
    directory, remote base or generator: this renderer would not apply them)."""
    kust = yaml.safe_load((base / "kustomization.yaml").read_text())
    if kust.get("kind") != "Kustomization":
        raise ValueError(f"{base}/kustomization.yaml is not a Kustomization")
    extra = set(kust) - KUSTOMIZATION_FIELDS
    if extra:
        raise ValueError(f"kustomization fields this renderer does not apply: {sorted(extra)}")
    files = []
    for entry in kust.get("resources") or []:
        path = (base / entry).resolve()
        if "://" in entry or path.parent != base.resolve() or not path.is_file():
            raise ValueError(f"resource {entry!r} is not a file in {base}")
        files.append(path)
    if len(set(files)) != len(files):
        raise ValueError("a resource is listed twice")
    return files


def set_images(docs: list[Doc], images: dict[str, str]) -> list[Doc]:
    """kustomize's ``images:`` (``name`` -> ``newName[:newTag]``): a container image ``name[:tag]`` whose name
    is a key becomes the value, keeping the tag unless the value has one."""
    out = copy.deepcopy(docs)
    for doc in out:
        for c in containers(doc):
            image = c["image"]
            name, tag = (image.rsplit(":", 1) if ":" in image.rsplit("/", 1)[-1] else (image, ""))
            if name in images:
                new = images[name]
                c["image"] = new if ":" in new.rsplit("/", 1)[-1] or not tag else f"{new}:{tag}"
    return out


def render(base: Path = BASE, images: dict[str, str] | None = None) -> list[Doc]:
    """Every document of every listed resource, in order (``kustomize build`` of this base without overlays)."""
    docs: list[Doc] = []
    for path in resources(base):
        docs.extend(d for d in yaml.safe_load_all(path.read_text()) if d)
    return set_images(docs, images) if images else docs


def containers(doc: Doc) -> list[Doc]:
    if doc.get("kind") != "Deployment":
        return []
    return doc["spec"]["template"]["spec"]["containers"]


def pod_labels(deployment: Doc) -> dict[str, str]:
    return deployment["spec"]["template"]["metadata"]["labels"]


def services_of(deployment: Doc, docs: list[Doc]) -> list[Doc]:
    """The Services whose selector matches the Deployment's pods."""
    labels = pod_labels(deployment)
    return [d for d in docs if d.get("kind") == "Service"
            and d["spec"]["selector"].items() <= labels.items()]


def container_port(container: Doc, port: int | str) -> int:
    """A probe's or Service's port: a number, or the name of one of the container's ports."""
    if isinstance(port, int):
        return port
    for p in container.get("ports", []):
        if p.get("name") == port:
            return int(p["containerPort"])
    raise ValueError(f"container {container['name']} has no port named {port!r}")


# ---------------------------------------------------------------- podman

def podman(*args: str, check: bool = True, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    out = subprocess.run([*SUDO, "podman", *args], capture_output=True, text=True, timeout=timeout)
    if check and out.returncode != 0:
        raise SmokeError(f"podman {' '.join(args)} failed ({out.returncode}): {out.stderr[-1500:]}")
    return out


def inspect(name: str) -> Doc:
    return json.loads(podman("inspect", name).stdout)[0]


def pod_ip(pod: str) -> str:
    infra = json.loads(podman("pod", "inspect", pod).stdout)
    infra = infra[0] if isinstance(infra, list) else infra
    nets = inspect(infra["InfraContainerID"])["NetworkSettings"]["Networks"]
    return nets[NETWORK]["IPAddress"]


def pods_of(deployment: Doc) -> list[str]:
    """podman names a Deployment's pods ``<name>-pod-<i>``, one per replica."""
    return [f"{deployment['metadata']['name']}-pod-{i}" for i in range(int(deployment["spec"].get("replicas", 1)))]


def teardown(docs: list[Doc], workdir: Path) -> None:
    for f in sorted(workdir.glob("*.yaml")):
        podman("kube", "down", str(f), check=False, timeout=300)
    for d in docs:  # pods of an earlier run whose files are gone
        if d.get("kind") == "Deployment":
            for pod in pods_of(d):
                podman("pod", "rm", "-f", pod, check=False, timeout=120)
    for d in docs:
        if d.get("kind") == "PersistentVolumeClaim":
            podman("volume", "rm", "-f", d["metadata"]["name"], check=False)
    podman("network", "rm", "-f", NETWORK, check=False)


def for_podman(deployment: Doc) -> Doc:
    """The Deployment as podman 4.3 is given it: without the containers' ``ports``, which it would publish on
    the host as if each had a ``hostPort`` (two scorer replicas would collide, Redis would take the host's
    6379), and without probes, which it would turn into health checks of its own (``curl``/``nc``, not in the
    image, on systemd timers, absent here): the smoke runs the base's probes itself, against the base's ports."""
    out = copy.deepcopy(deployment)
    for c in containers(out):
        for key in ("ports", "readinessProbe", "livenessProbe", "startupProbe"):
            c.pop(key, None)
    return out


def play(docs: list[Doc], workdir: Path) -> list[Doc]:
    """The claims first, then each Deployment on its own with the ConfigMaps and its Services' names as DNS
    aliases on the network. Returns the Deployments played (as in the base)."""
    podman("network", "create", NETWORK)
    maps = [d for d in docs if d.get("kind") == "ConfigMap"]
    claims = [d for d in docs if d.get("kind") == "PersistentVolumeClaim"]
    supported = {"ConfigMap", "PersistentVolumeClaim", "Deployment", "Service"}
    unknown = {d.get("kind") for d in docs} - supported
    if unknown:
        raise SmokeError(f"kinds the smoke cannot play: {sorted(unknown)}")
    if claims:
        f = workdir / "00-claims.yaml"
        f.write_text(yaml.safe_dump_all(claims, sort_keys=False))
        podman("kube", "play", "--network", NETWORK, str(f))  # else podman makes a default kube network
    played = []
    for i, d in enumerate([d for d in docs if d.get("kind") == "Deployment"], start=1):
        name = d["metadata"]["name"]
        f = workdir / f"{i:02d}-{name}.yaml"
        f.write_text(yaml.safe_dump_all([*maps, for_podman(d)], sort_keys=False))
        aliases = [s["metadata"]["name"] for s in services_of(d, docs)]
        net = NETWORK + (":" + ",".join(f"alias={a}" for a in aliases) if aliases else "")
        podman("kube", "play", "--network", net, str(f), timeout=600)
        log(f"played {name}: {len(pods_of(d))} pod(s){', DNS ' + ', '.join(aliases) if aliases else ''}")
        played.append(d)
    return played


# ---------------------------------------------------------------- probes, as a kubelet runs them

def http_get(url: str, timeout: float) -> tuple[int, str]:
    try:
        with urllib.request.urlopen(url, timeout=timeout) as r:
            return r.status, r.read(2000).decode(errors="replace")
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read(2000).decode(errors="replace")
    except (urllib.error.URLError, OSError) as exc:
        return 0, str(exc)


def run_probe(probe: Doc, pod: str, container: Doc) -> tuple[bool, str]:
    """One run of a Kubernetes probe against a running pod: (passed, output)."""
    timeout = float(probe.get("timeoutSeconds", 1))
    if "exec" in probe:
        ctr = f"{pod}-{container['name']}"
        try:
            out = podman("exec", ctr, *probe["exec"]["command"], check=False, timeout=timeout + 30)
        except subprocess.TimeoutExpired:
            return False, f"exec timed out after {timeout + 30} s"
        return out.returncode == 0, (out.stdout + out.stderr).strip()[-300:]
    if "httpGet" in probe:
        g = probe["httpGet"]
        code, text = http_get(f"http://{pod_ip(pod)}:{container_port(container, g['port'])}{g.get('path', '/')}",
                              timeout)
        return 200 <= code < 400, f"{code} {text[:200]}"
    if "tcpSocket" in probe:
        try:
            with socket.create_connection((pod_ip(pod), container_port(container, probe["tcpSocket"]["port"])),
                                          timeout=timeout):
                return True, "connected"
        except OSError as exc:
            return False, str(exc)
    raise SmokeError(f"{pod}: a probe of a kind the smoke does not run: {probe}")


def wait_probes(targets: list[tuple[str, Doc]], kind: str, deadline: float) -> dict[str, float]:
    """Run ``kind`` (readinessProbe, livenessProbe) of every (pod, container) until each has passed once."""
    t0 = time.monotonic()
    passed: dict[str, float] = {}
    last: dict[str, str] = {}
    while len(passed) < len(targets):
        for pod, c in targets:
            if pod in passed:
                continue
            ok, out = run_probe(c[kind], pod, c)
            if ok:
                passed[pod] = round(time.monotonic() - t0, 1)
                log(f"{kind} passes: {pod} after {passed[pod]} s")
            else:
                last[pod] = out
        if len(passed) < len(targets):
            if time.monotonic() > deadline:
                missing = sorted({p for p, _ in targets} - set(passed))
                raise SmokeError(f"{kind} not passing in time: {missing}; last output: "
                                 f"{ {p: last.get(p, '') for p in missing} }")
            time.sleep(2)
    return passed


# ---------------------------------------------------------------- the run

def gateway_request(method: str, url: str, body: Doc | None = None) -> tuple[int, str]:
    data = json.dumps(body).encode() if body is not None else None
    req = urllib.request.Request(url, data=data, method=method, headers={"Content-Type": "application/json"})
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            return r.status, r.read().decode()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read().decode(errors="replace")
    except (urllib.error.URLError, OSError) as exc:
        return 0, str(exc)


def memory_mb() -> dict[str, float]:
    out = podman("stats", "--no-stream", "--format", "json", check=False, timeout=120)
    try:
        rows = json.loads(out.stdout or "[]")
    except json.JSONDecodeError:
        return {}
    mem: dict[str, float] = {}
    for r in rows:
        used = str(r.get("mem_usage", "")).split("/")[0].strip()
        num, unit = "".join(ch for ch in used if ch.isdigit() or ch == "."), used.lstrip("0123456789.").strip()
        scale = {"B": 1e-6, "kB": 1e-3, "KB": 1e-3, "MB": 1.0, "MiB": 1.048576, "GB": 1e3, "GiB": 1073.741824}
        if num and unit in scale and not r.get("name", "").endswith("-infra"):
            mem[r["name"]] = round(float(num) * scale[unit], 1)
    return mem


def run(args: argparse.Namespace, docs: list[Doc], workdir: Path) -> Doc:
    figures: Doc = {}
    t0 = time.monotonic()
    deployments = play(docs, workdir)
    figures["play_s"] = round(time.monotonic() - t0, 1)
    targets = [(pod, c) for d in deployments for pod in pods_of(d) for c in containers(d)]
    running = {c["Names"][0] for c in json.loads(podman("ps", "--format", "json").stdout or "[]")}
    absent = [f"{p}-{c['name']}" for p, c in targets if f"{p}-{c['name']}" not in running]
    if absent:
        raise SmokeError(f"containers not running after play: {absent}")
    scorers = [p for p, _ in targets if p.startswith("vlm-scorer-pod-")]
    log(f"{len(targets)} pods running {figures['play_s']} s after the first play ({len(scorers)} scorer replicas)")
    if len(scorers) < 2:
        raise SmokeError(f"expected 2 scorer replicas, got {scorers}")
    deadline = time.monotonic() + args.probe_timeout
    wait_probes(targets, "readinessProbe", deadline)
    figures["ready_s"] = round(time.monotonic() - t0, 1)
    wait_probes(targets, "livenessProbe", deadline)
    log(f"every readiness and liveness probe passes, {figures['ready_s']} s after the first play")

    gateway = next(d for d in deployments if d["metadata"]["name"] == "gateway")
    service = services_of(gateway, docs)[0]
    port = container_port(containers(gateway)[0], service["spec"]["ports"][0]["targetPort"])
    url = f"http://{pod_ip(pods_of(gateway)[0])}:{port}"
    log(f"gateway Service {service['metadata']['name']} -> endpoint {url}")
    t_ask = time.monotonic()
    code, text = gateway_request("POST", f"{url}/v1/questions", QUESTION)
    if code >= 400 or code == 0:
        raise SmokeError(f"POST /v1/questions answered {code}: {text[:500]}")
    eid = json.loads(text)["episode_id"]
    log(f"episode {eid} submitted: {QUESTION['question']}")
    mapper = next(d for d in deployments if d["metadata"]["name"] == args.kill)
    victim_pod, victim_ctr = pods_of(mapper)[0], containers(mapper)[0]
    victim = f"{victim_pod}-{victim_ctr['name']}"
    killed: tuple[float, int] | None = None
    deadline = time.monotonic() + args.episode_timeout
    while True:
        code, text = gateway_request("GET", f"{url}/v1/episodes/{eid}")
        if code != 200:
            raise SmokeError(f"GET /v1/episodes/{eid} answered {code}: {text[:500]}")
        status = json.loads(text)
        if killed is None and status.get("step", -1) >= args.kill_after_step:
            figures["memory_mb"] = memory_mb()
            st = inspect(victim)
            log(f"step {status['step']}: killing {victim} (host pid {st['State']['Pid']}) with SIGKILL")
            subprocess.run([*SUDO, "kill", "-9", str(st["State"]["Pid"])], check=True)
            killed = (time.monotonic(), int(st.get("RestartCount", 0)))
        if killed is not None and "restart_s" not in figures:
            st = inspect(victim)
            if int(st.get("RestartCount", 0)) > killed[1] and st["State"].get("Running"):
                figures["restart_s"] = round(time.monotonic() - killed[0], 1)
                log(f"{victim} restarted by the pod's restart policy in {figures['restart_s']} s "
                    f"(restart count {st['RestartCount']})")
        if status["state"] in ("stopped", "failed", "cancelled"):
            break
        if time.monotonic() > deadline:
            raise SmokeError(f"episode not finished in {args.episode_timeout} s: {status}")
        time.sleep(1)
    figures["episode_s"] = round(time.monotonic() - t_ask, 1)
    figures["episode"] = {k: status.get(k) for k in ("state", "steps", "answer", "answer_text", "stop_reason")}
    log(f"episode finished: {figures['episode']} in {figures['episode_s']} s")
    if killed is None:
        raise SmokeError(f"the episode ended before step {args.kill_after_step}: nothing was killed")
    if "restart_s" not in figures:
        st = inspect(victim)
        if not (int(st.get("RestartCount", 0)) > killed[1] and st["State"].get("Running")):
            raise SmokeError(f"{victim} was not restarted: {st['State']}, restart count {st.get('RestartCount')}")
        figures["restart_s"] = "before the episode ended"
    if status["state"] != "stopped":
        raise SmokeError(f"the episode did not finish normally: {status['state']} ({status.get('stop_reason')})")
    deadline = time.monotonic() + args.probe_timeout
    for kind in ("readinessProbe", "livenessProbe"):
        wait_probes([(victim_pod, victim_ctr)], kind, deadline)
    return figures


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--kill", default="mapper", help="Deployment whose first pod's process is killed mid-episode")
    p.add_argument("--kill-after-step", type=int, default=2, help="kill once the episode reached this step")
    p.add_argument("--probe-timeout", type=float, default=900.0, help="seconds for every probe to pass")
    p.add_argument("--episode-timeout", type=float, default=1200.0, help="seconds for the episode to finish")
    p.add_argument("--keep", action="store_true", help="leave the pods running (no teardown) for a look")
    p.add_argument("--render", action="store_true",
                   help="print the rendered manifests with this machine's images (what is played) and exit")
    args = p.parse_args()
    docs = render(BASE, SMOKE_IMAGES)
    if args.render:
        print(yaml.safe_dump_all(docs, sort_keys=False), end="")
        return 0
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # a killed run still tears down
    workdir = Path(tempfile.mkdtemp(prefix="eqa-kube-smoke-"))
    t0 = time.monotonic()
    ok = False
    log("clean slate: earlier pods, volumes and network removed")
    teardown(docs, workdir)
    try:
        figures = run(args, docs, workdir)
        ok = True
    except SmokeError as exc:
        log(f"FAILED: {exc}")
        ours = {f"{pod}-{c['name']}" for d in docs if d.get("kind") == "Deployment" for pod in pods_of(d)
                for c in containers(d)}
        for row in json.loads(podman("ps", "-a", "--format", "json", check=False).stdout or "[]"):
            name = row["Names"][0]
            if name not in ours:
                continue
            log(f"--- {name}: {row.get('State')} ({row.get('Status')}); last log lines:")
            print(podman("logs", "--tail", "15", name, check=False).stdout, flush=True)
    finally:
        if not args.keep:
            t_down = time.monotonic()
            teardown(docs, workdir)
            log(f"torn down in {time.monotonic() - t_down:.0f} s")
    if ok:
        figures["total_s"] = round(time.monotonic() - t0, 1)
        log(f"PASSED: {json.dumps(figures)}")
        return 0
    return 1


if __name__ == "__main__":
    sys.exit(main())

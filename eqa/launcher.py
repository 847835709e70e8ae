"""Start the fleet as separate processes, wait until all are alive, keep them alive, stop them cleanly.

The launcher opens its own Zenoh session in router mode on a loopback port (free, or ``EQA_ZENOH_LISTEN``)
and hands every child ``EQA_ZENOH_CONNECT`` to it; the children are peers (multicast scouting off) that find
each other through the router's gossip and then talk directly, so the fleet keeps working even while the
launcher's session is busy. Each child is ``python -m services.<name>`` (or ``python -m gateway``) with its
own ``EQA_INSTANCE``; output goes to ``{data_dir}/logs/<instance>.log``.

A supervisor thread restarts a child that exits unexpectedly (with backoff, at most ``max_restarts`` times);
the services restore their per-episode state from the store, so the episode goes on.

One host's share of a fleet (``join``): the launcher's router also connects to an existing router
(``eqa up --join tls/10.0.0.1:7447``) and the children are Zenoh *clients* of it, so all of this host's traffic
goes through its router (no peer-to-peer links across hosts). With ``EQA_ZENOH_TLS_DIR`` (``eqa certs``) the
router listens on ``tls/`` with the ``router`` certificate and each child gets its own role's certificate; with
``EQA_ZENOH_USERS_FILE`` each child authenticates as its role with the password listed there; with
``EQA_ZENOH_ACL`` the launcher's router enforces the stream-ownership list on its children (``eqa.security``).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from eqa import dataflow, keys, metrics
from eqa.bus import Bus
from eqa.settings import Settings

log = logging.getLogger(__name__)

PIPELINE = dataflow.PIPELINE
SUPERVISE_S = 0.1  # how often the supervisor looks for exited children (a poll() each)
STEADY_S = 10.0  # a child that ran this long before it exited restarts with the shortest backoff
ALL_SERVICES = dataflow.SERVICES


class LaunchError(RuntimeError):
    pass


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def module_of(service: str) -> str:
    """The ``python -m`` module that runs a service."""
    return "gateway" if service == "gateway" else f"services.{service}"


@dataclass
class Child:
    service: str
    instance: str
    env: dict[str, str]
    log_path: Path
    proc: subprocess.Popen[bytes] | None = None
    restarts: int = 0
    streak: int = 0  # restarts in a row, each after less than STEADY_S of running (the backoff grows with it)
    started_at: float = 0.0
    history: list[str] = field(default_factory=list)

    @property
    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None


class Fleet:
    """The services of one deployment as local processes. Use as a context manager."""

    def __init__(
        self,
        settings: Settings,
        services: tuple[str, ...] | list[str] = PIPELINE,
        scorers: int = 1,
        extra_env: dict[str, str] | None = None,
        restart: bool = True,
        max_restarts: int = 5,
        join: list[str] | None = None,
        instances: dict[str, int] | None = None,
    ) -> None:
        unknown = set(services) - set(ALL_SERVICES) - set(dataflow.STANDS_IN)
        if unknown:
            raise LaunchError(f"unknown services {sorted(unknown)}; known: {', '.join(ALL_SERVICES)}")
        if scorers < 1 and "vlm_scorer" in services:
            raise LaunchError("--scorers must be at least 1")
        self.settings = settings
        self.services = tuple(services)
        self.scorers = scorers
        self.extra_env = dict(extra_env or {})
        self.restart_enabled = restart
        self.max_restarts = max_restarts
        self.join = list(join or [])
        self.instances = dict(instances or {})  # service -> processes (robots shared among them: eqa.sharding)
        if any(n < 1 for n in self.instances.values()):
            raise LaunchError("every service needs at least 1 instance")
        self.secured = settings.zenoh_tls_dir is not None or settings.zenoh_users_file is not None
        self.children: list[Child] = []
        self._hub: Bus | None = None
        self._alive: set[tuple[str, str]] = set()
        self._alive_changed = threading.Condition()
        self._stop = threading.Event()
        self._supervisor: threading.Thread | None = None
        self.endpoint = ""
        self.run_id = f"{os.getpid()}-{int(time.time())}"

    # ---- setup --------------------------------------------------------------------------------------------
    def _hub_settings(self) -> Settings:
        # The children connect to the router's first endpoint, so it needs a concrete port: ":0" (any port)
        # is resolved to a free one here.
        proto = "tls" if self.settings.zenoh_tls_dir is not None else "tcp"
        listen = [
            f"{e.rsplit(':', 1)[0]}:{free_port()}" if e.endswith(":0") else e for e in self.settings.zenoh_listen
        ] or [f"{proto}/127.0.0.1:{free_port()}"]
        update: dict[str, object] = {
            "zenoh_mode": "router", "zenoh_listen": listen, "zenoh_connect": self.join, "instance": "launcher",
        }
        update.update(self._role_security("router"))
        return self.settings.model_copy(update=update)

    def _role_security(self, role: str) -> dict[str, object]:
        """TLS certificate and user/password of one role, from EQA_ZENOH_TLS_DIR and EQA_ZENOH_USERS_FILE."""
        out: dict[str, object] = {}
        tls_dir = self.settings.zenoh_tls_dir
        if tls_dir is not None:
            cert, key, ca = tls_dir / f"{role}.pem", tls_dir / f"{role}.key", tls_dir / "ca.pem"
            for path in (cert, key, ca):
                if not path.is_file():
                    raise LaunchError(f"{path} is missing: make the fleet's certificates with `eqa certs {tls_dir}`")
            out.update(zenoh_tls_ca=ca, zenoh_tls_cert=cert, zenoh_tls_key=key)
        if self.settings.zenoh_users_file is not None:
            out.update(zenoh_user=role, zenoh_password=_password_of(self.settings.zenoh_users_file, role))
        return out

    def _child_env(self, service: str, instance: str) -> dict[str, str]:
        env = {k: v for k, v in os.environ.items() if not k.startswith("EQA_")}
        env.update(self.settings.env())
        client = bool(self.join) or self.secured  # all traffic through this host's router
        env.update({f"EQA_{k.upper()}": str(v) for k, v in self._role_security(service).items()})
        env.pop("EQA_ZENOH_USERS_FILE", None)  # the router checks passwords, the children only present theirs
        env.update(
            {
                "EQA_INSTANCE": instance,
                "EQA_ZENOH_MODE": "client" if client else "peer",
                "EQA_ZENOH_LISTEN": "" if client else "tcp/127.0.0.1:0",
                "EQA_ZENOH_ACL": "false",
                "EQA_ZENOH_CONNECT": self.endpoint,
                "EQA_DATA_DIR": str(Path(self.settings.data_dir).resolve()),
                "EQA_PARENT_PID": str(os.getpid()),  # the child exits if this launcher dies (no orphans)
                "PYTHONUNBUFFERED": "1",
                "RERUN_TELEMETRY_ENABLED": "false",
            }
        )
        if service == "vlm_scorer":
            env["EQA_SCORER_REPLICA"] = instance
        env.update(self.extra_env)
        return env

    def _plan(self) -> None:
        logs = Path(self.settings.data_dir) / "logs"
        logs.mkdir(parents=True, exist_ok=True)
        for service in self.services:
            count = self.scorers if service == "vlm_scorer" else self.instances.get(service, 1)
            for i in range(count):
                instance = f"{service.replace('_', '-')}-{i}-{self.run_id}"
                self.children.append(
                    Child(service, instance, self._child_env(service, instance), logs / f"{service}-{i}.log")
                )
        metrics_ports(self.settings.metrics_port, self.children)
        if self.settings.metrics_port:
            write_targets(Path(self.settings.data_dir) / METRICS_TARGETS, self.settings, self.children)

    # ---- lifecycle ----------------------------------------------------------------------------------------
    def start(self, timeout: float = 90.0) -> Fleet:
        metrics.serve(self.settings, "launcher")
        hub_settings = self._hub_settings()
        self.endpoint = hub_settings.zenoh_listen[0].replace("0.0.0.0", "127.0.0.1")
        self._hub = Bus(hub_settings, "launcher", "launcher").open()
        self._hub.watch_alive(keys.ALIVE_ANY, self._on_alive)
        self._plan()
        for child in self.children:
            self._spawn(child)
        try:
            self.wait_alive(timeout)
        except LaunchError:
            self.stop()
            raise
        self._supervisor = threading.Thread(target=self._supervise, name="fleet-supervisor", daemon=True)
        self._supervisor.start()
        return self

    def _on_alive(self, service: str, instance: str, up: bool) -> None:
        with self._alive_changed:
            if up:
                self._alive.add((service, instance))
            else:
                self._alive.discard((service, instance))
            self._alive_changed.notify_all()

    def _spawn(self, child: Child) -> None:
        out = open(child.log_path, "ab")  # noqa: SIM115 - handed to the child, closed with it
        child.proc = subprocess.Popen(
            [sys.executable, "-m", module_of(child.service)],
            env=child.env,
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        out.close()
        child.started_at = time.monotonic()
        port = int(child.env.get("EQA_METRICS_PORT", "0"))
        log.info("started %s (pid %d), log %s%s", child.instance, child.proc.pid, child.log_path,
                 f", metrics on port {port}" if port else "")

    def missing(self) -> list[Child]:
        with self._alive_changed:
            return [c for c in self.children if (c.service, c.instance) not in self._alive]

    def wait_alive(self, timeout: float = 90.0, children: list[Child] | None = None) -> None:
        """Block until every child (or the given ones) holds its liveliness token."""
        deadline = time.monotonic() + timeout
        wanted = children or self.children
        with self._alive_changed:
            while True:
                missing = [c for c in wanted if (c.service, c.instance) not in self._alive]
                if not missing:
                    return
                dead = [c for c in missing if c.proc is not None and c.proc.poll() is not None]
                if dead:
                    c = dead[0]
                    raise LaunchError(
                        f"{c.service} exited with code {c.proc.returncode if c.proc else '?'} before it was up; "
                        f"its log: {c.log_path}\n{tail(c.log_path)}"
                    )
                left = deadline - time.monotonic()
                if left <= 0:
                    names = ", ".join(c.instance for c in missing)
                    raise LaunchError(f"not alive after {timeout:.0f} s: {names}; logs in {missing[0].log_path.parent}")
                self._alive_changed.wait(min(left, 0.5))

    def _supervise(self) -> None:
        while not self._stop.wait(SUPERVISE_S):
            for child in self.children:
                if self._stop.is_set() or child.proc is None or child.proc.poll() is None:
                    continue
                code = child.proc.returncode
                child.history.append(f"exited with {code}")
                if not self.restart_enabled or child.restarts >= self.max_restarts:
                    log.error("%s exited with %s; not restarting (restarts: %d)", child.instance, code, child.restarts)
                    child.proc = None
                    continue
                child.restarts += 1
                metrics.inc(metrics.CHILD_RESTARTS, child.service)
                # a crash loop backs off; a child that ran steadily before it died is back at once
                child.streak = child.streak + 1 if time.monotonic() - child.started_at < STEADY_S else 1
                delay = min(0.2 * 2 ** (child.streak - 1), 5.0)
                log.warning("%s exited with %s; restarting in %.1f s", child.instance, code, delay)
                time.sleep(delay)
                if not self._stop.is_set():
                    self._spawn(child)

    def child(self, service: str, index: int = 0) -> Child:
        matches = [c for c in self.children if c.service == service]
        if index >= len(matches):
            raise LaunchError(f"no {service} #{index} in this fleet")
        return matches[index]

    def kill(self, service: str, index: int = 0, sig: int = signal.SIGKILL) -> Child:
        """Kill one child (tests: the supervisor restarts it when restarts are on)."""
        child = self.child(service, index)
        if child.proc is not None and child.proc.poll() is None:
            os.killpg(child.proc.pid, sig)
            child.proc.wait(timeout=10)
        return child

    def stop(self, timeout: float = 10.0) -> None:
        self._stop.set()
        if self._supervisor is not None:
            self._supervisor.join(timeout=5)
        procs = [c.proc for c in self.children if c.proc is not None and c.proc.poll() is None]
        for p in procs:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGTERM)
        deadline = time.monotonic() + timeout
        for p in procs:
            try:
                p.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.warning("pid %d did not stop in %.0f s; killing", p.pid, timeout)
                os.killpg(p.pid, signal.SIGKILL)
                p.wait(timeout=5)
        if self._hub is not None:
            self._hub.close()
            self._hub = None
        metrics.stop_serving(self.settings.metrics_port)

    def __enter__(self) -> Fleet:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def hub(self) -> Bus:
        if self._hub is None:
            raise LaunchError("fleet is not started")
        return self._hub

    def client_settings(self, role: str = "operator") -> Settings:
        """Settings for another peer (a test, the CLI) joining this fleet (as ``role`` when it is secured)."""
        if self.join or self.secured:
            update: dict[str, object] = {"zenoh_mode": "client", "zenoh_listen": [], "zenoh_connect": [self.endpoint],
                                         "zenoh_acl": False, "zenoh_users_file": None}
            update.update(self._role_security(role))
            return self.settings.model_copy(update=update)
        return self.settings.model_copy(
            update={"zenoh_mode": "peer", "zenoh_listen": ["tcp/127.0.0.1:0"], "zenoh_connect": [self.endpoint]}
        )


def metrics_ports(base: int, children: list[Child]) -> None:
    """With ``EQA_METRICS_PORT`` set (the launcher serves on it), child ``k`` of the plan serves its metrics on
    ``base + 1 + k`` (``EQA_METRICS_PORT`` of its environment; the gateway serves /metrics on its own port). A
    fixed plan gives a restarted child the same port: one scrape target per process."""
    k = 0
    for child in children:
        if base and child.service != "gateway":
            k += 1
            if base + k > 65535:
                raise LaunchError(f"EQA_METRICS_PORT={base} leaves no port for child {k}: use a lower port")
            child.env["EQA_METRICS_PORT"] = str(base + k)
        else:
            child.env["EQA_METRICS_PORT"] = "0"


METRICS_TARGETS = "metrics-targets.json"


def write_targets(path: Path, settings: Settings, children: list[Child]) -> None:
    """The fleet's scrape targets as a Prometheus ``file_sd_configs`` file: the launcher, each child with a
    metrics port, the gateway's API port (job = service)."""
    host = "127.0.0.1" if settings.metrics_host in ("0.0.0.0", "::", "") else settings.metrics_host
    groups = [{"targets": [f"{host}:{settings.metrics_port}"], "labels": {"job": "launcher"}}]
    for child in children:
        if child.service == "gateway":
            target = f"{settings.gateway_host if settings.gateway_host != '0.0.0.0' else '127.0.0.1'}:" \
                     f"{settings.gateway_port}"
        else:
            target = f"{host}:{child.env['EQA_METRICS_PORT']}"
        groups.append({"targets": [target], "labels": {"job": child.service, "eqa_instance": child.instance}})
    path.write_text(json.dumps(groups, indent=1))


def _password_of(users_file: Path, user: str) -> str:
    """The password of ``user`` in a Zenoh ``user:password`` dictionary file."""
    for line in Path(users_file).read_text().splitlines():
        name, sep, password = line.partition(":")
        if sep and name.strip() == user:
            return password.strip()
    raise LaunchError(f"{users_file} has no password for {user!r}: add a line '{user}:<password>'")


def tail(path: Path, lines: int = 20) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return ""

"""Start the fleet as separate processes, wait until all are alive, keep them alive, stop them cleanly.

The launcher opens its own Zenoh session in router mode on a loopback port (free, or ``EQA_ZENOH_LISTEN``)
and hands every child ``EQA_ZENOH_CONNECT`` to it; the children are peers (multicast scouting off) that find
each other through the router's gossip and then talk directly, so the fleet keeps working even while the
launcher's session is busy. Each child is ``python -m services.<name>`` (or ``python -m gateway``) with its
own ``EQA_INSTANCE``; output goes to ``{data_dir}/logs/<instance>.log``.

A supervisor thread restarts a child that exits unexpectedly (with backoff, at most ``max_restarts`` times);
the services restore their per-episode state from the store, so the episode goes on. With ``EQA_STANDBY`` (the
default) the launcher keeps one warm standby per service (:mod:`eqa.standby`: imports done, off the bus): a
child that dies is replaced by its service's standby once its pid is reaped and its liveliness token gone,
without a new process's seconds of imports, and a new standby is started once the promoted one is up. The
gateway has no standby (its entry point is not :func:`eqa.service.main`).

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

from eqa import dataflow, keys, metrics, standby
from eqa.bus import Bus
from eqa.settings import Settings

log = logging.getLogger(__name__)

PIPELINE = dataflow.PIPELINE
SUPERVISE_S = 0.1  # how often the supervisor looks for exited children (a poll() each)
# a child that held its liveliness token this long before it exited restarts with the shortest backoff; one that
# died before it was up (or right after) is in a crash loop and backs off
STEADY_S = 2.0
ALL_SERVICES = dataflow.SERVICES
TOKEN_GONE_S = 3.0  # a dead child's liveliness token must be gone before its standby takes its name (bounded)
STANDBY_AFTER_S = 10.0  # a new standby starts once the promoted one is up, or this long after the promotion
STANDBY_FAILURES_MAX = 3  # standbys of one service that died before being needed; then it gets no more


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
    streak: int = 0  # restarts in a row, each after less than STEADY_S up (the backoff grows with it)
    started_at: float = 0.0
    up_at: float | None = None  # when this process's liveliness token appeared
    history: list[str] = field(default_factory=list)

    @property
    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None


@dataclass
class Standby:
    """A warm standby of one service (:mod:`eqa.standby`): imported, off the bus, waiting on its stdin."""

    service: str
    env: dict[str, str]
    log_path: Path
    proc: subprocess.Popen[bytes]
    started_at: float
    ready: threading.Event = field(default_factory=threading.Event)
    ready_after_s: float | None = None  # from the spawn to its "ready"

    @property
    def alive(self) -> bool:
        return self.proc.poll() is None


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
        standby: bool | None = None,
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
        # one warm standby per service that runs eqa.service.main (EQA_STANDBY; only when restarts are on)
        self.standby_enabled = (settings.standby if standby is None else standby) and restart
        self.standbys: dict[str, Standby] = {}
        self._standby_due: dict[str, float] = {}  # service -> when to start its next standby
        self._standby_wait_for: dict[str, Child] = {}  # service -> the promoted child whose token starts it early
        self._standby_failures: dict[str, int] = {}
        self.promotions = 0
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
        if self.standby_enabled:
            # after the fleet is up: the standbys' imports do not slow the first start down
            now = time.monotonic()
            for service in dict.fromkeys(c.service for c in self.children if c.service != "gateway"):
                self._standby_due[service] = now
        self._supervisor = threading.Thread(target=self._supervise, name="fleet-supervisor", daemon=True)
        self._supervisor.start()
        return self

    def _on_alive(self, service: str, instance: str, up: bool) -> None:
        with self._alive_changed:
            if up:
                self._alive.add((service, instance))
                for child in self.children:
                    if child.instance == instance and child.service == service and child.up_at is None:
                        child.up_at = time.monotonic()
            else:
                self._alive.discard((service, instance))
            self._alive_changed.notify_all()

    def _spawn(self, child: Child) -> None:
        with self._alive_changed:
            child.up_at = None  # set by its token's arrival (_on_alive)
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

    def _is_up(self, child: Child) -> bool:
        """``child``'s process runs and has declared its liveliness token since it was started (call with
        ``_alive_changed`` held). The token alone is not enough: a killed process's token stays visible until
        the bus notices its session is gone, and a standby promoted in its place declares the same token."""
        return ((child.service, child.instance) in self._alive and child.up_at is not None
                and child.proc is not None and child.proc.poll() is None)

    def missing(self) -> list[Child]:
        with self._alive_changed:
            return [c for c in self.children if not self._is_up(c)]

    def wait_alive(self, timeout: float = 90.0, children: list[Child] | None = None) -> None:
        """Block until every child (or the given ones) is up (:meth:`_is_up`)."""
        deadline = time.monotonic() + timeout
        wanted = children or self.children
        with self._alive_changed:
            while True:
                missing = [c for c in wanted if not self._is_up(c)]
                if not missing:
                    return
                # a dead child the supervisor is about to replace (a restart, or its standby once the dead
                # process's token is gone) is waited for; one it will not replace ends the wait
                dead = [c for c in missing if (c.proc is None or c.proc.poll() is not None) and not self._replaces(c)]
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

    def _replaces(self, child: Child) -> bool:
        """True when the supervisor will start a process in place of ``child``'s dead one."""
        return (child.proc is not None and self.restart_enabled and child.restarts < self.max_restarts
                and not self._stop.is_set() and self._supervisor_running())

    def _supervisor_running(self) -> bool:
        return self._supervisor is not None and self._supervisor.is_alive()

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
                steady = child.up_at is not None and time.monotonic() - child.up_at >= STEADY_S
                child.streak = 1 if steady else child.streak + 1
                delay = min(0.2 * 2 ** (child.streak - 1), 5.0)
                spare = self.standbys.get(child.service)
                if spare is not None and spare.alive:
                    if child.streak > 1:
                        log.warning("%s exited with %s; promoting its standby in %.1f s", child.instance, code,
                                    delay)
                        time.sleep(delay)
                    if not self._stop.is_set() and self._promote(child, spare):
                        continue
                log.warning("%s exited with %s; restarting in %.1f s", child.instance, code, delay)
                time.sleep(delay)
                if not self._stop.is_set():
                    self._spawn(child)
            if self.standby_enabled and not self._stop.is_set():
                self._keep_standbys()

    # ---- warm standbys (eqa.standby) ------------------------------------------------------------------------
    def _spawn_standby(self, service: str) -> None:
        env = self._child_env(service, f"{service.replace('_', '-')}-standby-{self.run_id}")
        env["EQA_METRICS_PORT"] = "0"  # it serves the replaced instance's port once promoted
        log_path = Path(self.settings.data_dir) / "logs" / f"{service}-standby.log"
        read_fd, write_fd = os.pipe()
        out = open(log_path, "ab")  # noqa: SIM115 - handed to the child, closed with it
        try:
            proc = subprocess.Popen(
                [sys.executable, "-m", module_of(service), "--standby", str(write_fd)],
                env=env, stdin=subprocess.PIPE, stdout=out, stderr=subprocess.STDOUT, pass_fds=(write_fd,),
                start_new_session=True,
            )
        finally:
            out.close()
            os.close(write_fd)
        spare = Standby(service, env, log_path, proc, time.monotonic())
        self.standbys[service] = spare
        threading.Thread(target=self._await_ready, args=(spare, read_fd), name=f"standby-{service}",
                         daemon=True).start()
        log.info("started a standby of %s (pid %d, off the bus until promoted), log %s", service, proc.pid, log_path)

    def _await_ready(self, spare: Standby, read_fd: int) -> None:
        with os.fdopen(read_fd, "rb") as pipe:
            line = pipe.readline(64)
        if line == standby.READY:
            spare.ready_after_s = time.monotonic() - spare.started_at
            spare.ready.set()
            metrics.gauge_set(metrics.STANDBY_READY, 1.0, spare.service)
            log.info("standby of %s (pid %d) is ready after %.1f s", spare.service, spare.proc.pid,
                     spare.ready_after_s)

    def _promote(self, child: Child, spare: Standby) -> bool:
        """Hand ``child``'s place to its service's standby: only once the dead process's liveliness token is gone
        (its pid is already reaped), so no two processes ever hold one instance's name. False: the standby
        died meanwhile (the caller restarts the child the ordinary way)."""
        deadline = time.monotonic() + TOKEN_GONE_S
        with self._alive_changed:
            while (child.service, child.instance) in self._alive and time.monotonic() < deadline:
                self._alive_changed.wait(deadline - time.monotonic())
            if (child.service, child.instance) in self._alive:
                log.warning("%s: its liveliness token is still there %.0f s after its exit; promoting anyway (the "
                            "process is gone)", child.instance, TOKEN_GONE_S)
        env = {k: v for k, v in child.env.items() if spare.env.get(k) != v}
        unset = [k for k in spare.env if k not in child.env]
        line = standby.Promotion(env=env, unset=unset, log_path=child.log_path.resolve()).encode()
        del self.standbys[child.service]
        metrics.gauge_set(metrics.STANDBY_READY, 0.0, child.service)
        # the child is the standby's from here: its token, declared as soon as the line is read, marks it up
        with self._alive_changed:
            child.proc = spare.proc
            child.started_at = time.monotonic()
            child.up_at = None
        stdin = spare.proc.stdin
        try:
            if stdin is None:
                raise BrokenPipeError("no pipe")
            stdin.write(line)
            stdin.flush()
            stdin.close()
        except OSError as exc:
            log.warning("the standby of %s (pid %d) could not be promoted (%s); restarting %s instead",
                        child.service, spare.proc.pid, exc, child.instance)
            _end(spare.proc)
            self._standby_due[child.service] = time.monotonic()
            return False
        child.history.append(f"standby pid {spare.proc.pid} promoted")
        self.promotions += 1
        metrics.inc(metrics.STANDBY_PROMOTIONS, child.service)
        log.warning("%s is gone; its standby (pid %d, %s) takes its place", child.instance, spare.proc.pid,
                    "warm" if spare.ready.is_set() else "still warming up")
        self._standby_due[child.service] = time.monotonic() + STANDBY_AFTER_S
        self._standby_wait_for[child.service] = child
        return True

    def _keep_standbys(self) -> None:
        """Replace standbys that died, start the ones that are due (one per service)."""
        now = time.monotonic()
        for service, spare in list(self.standbys.items()):
            if spare.alive:
                continue
            del self.standbys[service]
            metrics.gauge_set(metrics.STANDBY_READY, 0.0, service)
            failures = self._standby_failures[service] = self._standby_failures.get(service, 0) + 1
            if failures >= STANDBY_FAILURES_MAX:
                log.error("the standby of %s exited with %s (%d times); no more standbys for it, log %s", service,
                          spare.proc.returncode, failures, spare.log_path)
                continue
            log.warning("the standby of %s exited with %s; starting another, log %s", service,
                        spare.proc.returncode, spare.log_path)
            self._standby_due[service] = now + min(0.2 * 2 ** failures, 5.0)
        for service, due in list(self._standby_due.items()):
            promoted = self._standby_wait_for.get(service)
            with self._alive_changed:
                up = promoted is not None and self._is_up(promoted)
            if now < due and not up:
                continue  # the promoted standby first has the cores to itself while it joins the bus
            del self._standby_due[service]
            self._standby_wait_for.pop(service, None)
            if service not in self.standbys and self._standby_failures.get(service, 0) < STANDBY_FAILURES_MAX:
                self._spawn_standby(service)

    def wait_standbys(self, timeout: float = 90.0) -> None:
        """Block until every service that gets a standby has a ready one (tests, benches)."""
        if not self.standby_enabled:
            return
        services = [s for s in dict.fromkeys(c.service for c in self.children if c.service != "gateway")
                    if self._standby_failures.get(s, 0) < STANDBY_FAILURES_MAX]
        deadline = time.monotonic() + timeout
        while True:
            pending = [s for s in services if s not in self.standbys or not self.standbys[s].ready.is_set()]
            if not pending:
                return
            if time.monotonic() >= deadline:
                raise LaunchError(f"no ready standby after {timeout:.0f} s for: {', '.join(pending)}")
            time.sleep(0.05)

    def status(self) -> list[dict[str, object]]:
        """One row per process: service, instance, pid, role (``active`` or ``standby``), alive, ready."""
        with self._alive_changed:
            alive = set(self._alive)
        rows: list[dict[str, object]] = [
            {"service": c.service, "instance": c.instance, "pid": c.proc.pid if c.proc is not None else None,
             "role": "active", "alive": (c.service, c.instance) in alive, "restarts": c.restarts}
            for c in self.children
        ]
        rows += [{"service": s.service, "instance": None, "pid": s.proc.pid, "role": "standby", "alive": s.alive,
                  "ready": s.ready.is_set()} for s in list(self.standbys.values())]
        return rows

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
        for spare in list(self.standbys.values()):
            if spare.proc.stdin is not None:
                with contextlib.suppress(OSError):
                    spare.proc.stdin.close()  # end of file: the standby exits
        procs = [c.proc for c in self.children if c.proc is not None and c.proc.poll() is None]
        procs += [s.proc for s in self.standbys.values() if s.alive]
        self.standbys.clear()
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


def _end(proc: subprocess.Popen[bytes]) -> None:
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGKILL)
    with contextlib.suppress(subprocess.TimeoutExpired):
        proc.wait(timeout=5)


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

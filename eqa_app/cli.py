"""``eqa``: the command line of the system.

    eqa ask ["QUESTION" --choice A --choice B ... --scene S]   run one question end to end and print the answer
    eqa task ["Move the X from the Y to the Z" --scene S]      run one HELIOS task and print each phase
    eqa up [--scorers N]                                      run the fleet until Ctrl-C
    eqa health SERVICE...                                     exit 0 when each service has a live instance
    eqa export EPISODE_ID --mcap                              the episode as MCAP (Foxglove, ros2 bag, Rerun)
    eqa sim ...  eqa calibrate ...  eqa bench ...  eqa gateway   (see each --help)

Every command is configured by ``EQA_*`` environment variables (eqa/settings.py); flags override them.
Bad input gives a one-line error and exit code 2.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import signal
import sys
import threading
from pathlib import Path
from typing import NoReturn

from eqa.bus import BusError
from eqa.settings import Settings

log = logging.getLogger(__name__)

# Modules that add sub-commands with ``register(subparsers)``.
_SUBCOMMAND_MODULES = (
    "eqa_app.ask",
    "eqa_app.task",
    "services.sim.cli",
    "services.vlm_scorer.cli",
    "eqa_app.calibrate",
    "eqa_app.bench_cli",
    "eqa_app.fleet_cli",
    "eqa_app.export",
)


class UsageError(Exception):
    """Bad input from the user: printed as one line, exit code 2."""


def load_settings() -> Settings:
    try:
        return Settings()
    except Exception as exc:
        raise UsageError(f"invalid EQA_* settings: {exc}") from exc


def check_scorer(settings: Settings) -> None:
    """Refuse to start a fleet whose scorer replicas could only answer errors (a missing model directory, no
    endpoint): :class:`UsageError` saying what to set."""
    from services.vlm_scorer.backends import BackendUnavailable, check_settings

    try:
        check_settings(settings)
    except BackendUnavailable as exc:
        raise UsageError(str(exc)) from None
    if settings.scorer_backend == "remote":
        check_remote(settings)


def check_remote(settings: Settings) -> None:
    """``eqa scorer check`` on the configured endpoint: :class:`UsageError` with its findings when
    the remote scorer could not use it; else one line saying the mode and the latency of a step."""
    from services.vlm_scorer.backends.remote import probe_endpoint

    report = probe_endpoint(settings.remote_base_url or "", settings.remote_model, settings.remote_api_key,
                            settings.remote_timeout_s, settings.remote_mode, settings.remote_samples,
                            settings.remote_sample_temperature)
    if not report.usable:
        raise UsageError("the remote scorer cannot use this endpoint:\n  " + "\n  ".join(report.lines()))
    latency = f", one step {report.step_latency_s * 1000:.0f} ms" if report.step_latency_s is not None else ""
    print(f"remote scorer: {report.base_url} model {report.model}, mode {report.mode}{latency} "
          f"({report.calls_per_step} HTTP calls)", file=sys.stderr, flush=True)


def cmd_up(args: argparse.Namespace) -> int:
    from eqa.dataflow import STATEFUL
    from eqa.launcher import ALL_SERVICES, PIPELINE, Fleet, LaunchError
    from eqa.service import setup_logging

    settings = load_settings()
    check_scorer(settings)
    setup_logging(settings.log_level, "eqa-up", settings.log_format, settings.instance)
    services = list(PIPELINE if args.no_gateway else ALL_SERVICES)
    if args.services:
        services = [s.strip() for s in args.services.split(",") if s.strip()]
    if args.port is not None:
        settings = settings.model_copy(update={"gateway_port": args.port})
    try:
        instances = {s: args.instances for s in STATEFUL}
        fleet = Fleet(settings, services=services, scorers=args.scorers, join=args.join, instances=instances)
    except LaunchError as exc:
        raise UsageError(str(exc)) from None
    try:
        fleet.start(timeout=args.timeout)
    except LaunchError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(f"fleet up: {len(fleet.children)} processes, zenoh router at {fleet.endpoint}", flush=True)
    print(f"join it from another shell (eqa health, more scorer replicas): EQA_ZENOH_CONNECT={fleet.endpoint}",
          flush=True)
    if "gateway" in services:
        base = f"http://{settings.gateway_host}:{settings.gateway_port}"
        print(f"web console: {base}/ (ask, watch, fleet); API docs: {base}/docs", flush=True)
    print(f"logs: {settings.data_dir / 'logs'}; Ctrl-C stops", flush=True)
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    try:
        done.wait()
    except KeyboardInterrupt:
        pass
    finally:
        fleet.stop()
    return 0


def cmd_health(args: argparse.Namespace) -> int:
    from eqa.health import check

    settings = load_settings()
    missing = check(settings, args.services, timeout=args.timeout)
    if missing:
        hint = (f" (looked via {', '.join(settings.zenoh_connect) or 'multicast scouting'}; for a fleet started "
                "by `eqa up` set EQA_ZENOH_CONNECT to the endpoint it printed)")
        print(f"not alive: {', '.join(missing)}{hint}", file=sys.stderr)
        return 1
    print("alive: " + ", ".join(args.services))
    return 0


class OneLineParser(argparse.ArgumentParser):
    """Bad arguments give one line on stderr (no usage dump) and exit code 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="eqa",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    up = sub.add_parser(
        "up", help="start every service as its own process and keep them running",
        description="Start the sim, mapper, scorer replicas, planner, stopper and the gateway, each its own process "
        "over Zenoh, restart any that dies (a restarted service continues its episodes from the store), and run "
        "until Ctrl-C. The web console and the API are on the gateway's port. Configured by EQA_* variables "
        "(docs/configuration.md); --services and --join spread a fleet over hosts (docs/deployment.md).")
    up.add_argument("--scorers", type=int, default=1, help="number of scorer replicas (default 1)")
    up.add_argument("--no-gateway", action="store_true", help="run the pipeline services only")
    up.add_argument("--port", type=int, default=None, help="gateway port (default EQA_GATEWAY_PORT=8080)")
    up.add_argument("--timeout", type=float, default=90.0, help="seconds to wait until all are alive")
    up.add_argument("--instances", type=int, default=1,
                    help="processes of each stateful service (sim, mapper, planner, stopper); they share the "
                    "robots (default 1)")
    up.add_argument("--services", default=None,
                    help="comma-separated services to run on this host (default: all; e.g. mapper,planner)")
    up.add_argument("--join", action="append", default=None, metavar="ENDPOINT",
                    help="join an existing fleet: this host's router connects to ENDPOINT (e.g. "
                    "tls/10.0.0.1:7447; repeatable) and runs only --services (docs/deployment.md, Scaling out)")
    up.set_defaults(func=cmd_up)

    health = sub.add_parser(
        "health", help="check that services hold a liveliness token (compose health checks)",
        description="Exit 0 when every named service has a live instance on the bus (its liveliness token), 1 "
        "otherwise, naming the ones missing; the compose file's health checks run it.")
    health.add_argument("services", nargs="+", help="service names, e.g. sim mapper")
    health.add_argument("--timeout", type=float, default=5.0,
                        help="seconds to wait for every named service (default 5)")
    health.set_defaults(func=cmd_health)

    for name in _SUBCOMMAND_MODULES:
        importlib.import_module(name).register(sub)
    from gateway import cli as gateway_cli

    gateway_cli.register(sub, scene_area=_floor_area)  # the gateway gets the sim's scene library from here
    return parser


def _floor_area(scene: str, scenes_dir: Path, hm3d_dir: Path | None) -> float:
    from services.sim.library import floor_area  # imported on first use: `eqa --help` stays quick

    return floor_area(scene, scenes_dir, hm3d_dir)


def _terminate(signum: int, _frame: object) -> None:
    # SIGTERM (and SIGINT where a background start ignored it) unwinds like Ctrl-C, so that fleets started by
    # a command are stopped by their context managers instead of being orphaned.
    raise KeyboardInterrupt


def main(argv: list[str] | None = None) -> int:
    signal.signal(signal.SIGTERM, _terminate)
    signal.signal(signal.SIGINT, _terminate)
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except UsageError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except BusError as exc:  # nothing to connect to, or the fleet refused this node's credentials
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130

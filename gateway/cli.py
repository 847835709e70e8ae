"""Command line of the gateway: ``python -m gateway`` / ``eqa gateway`` runs the server (``eqa ask --url``
in :mod:`eqa_app.ask` is the client)."""

from __future__ import annotations

import argparse
import functools
import logging
import sys
from typing import Any

from eqa.settings import Settings
from gateway.manager import SceneArea

log = logging.getLogger(__name__)


def uvicorn_options(settings: Settings) -> dict[str, Any]:
    """How uvicorn serves the gateway (``python -m gateway`` and the tests' servers alike).

    ``proxy_headers`` off: uvicorn would otherwise take the client address from ``X-Forwarded-For`` of any
    peer on 127.0.0.1 (its ``forwarded_allow_ips`` default), so a local client could pick its address; the
    app reads the header itself, only from ``EQA_TRUSTED_PROXIES`` (:func:`gateway.auth.client_ip`).
    Idle keep-alive connections close after ``EQA_GATEWAY_KEEP_ALIVE_S``; slow bodies are the app's
    (:class:`gateway.limits.BodyLimit`). On SIGTERM, requests in flight get ``EQA_GATEWAY_SHUTDOWN_GRACE_S``,
    then are cancelled: event streams only end when their episode does."""
    return {
        "host": settings.gateway_host,
        "port": settings.gateway_port,
        "proxy_headers": False,
        "server_header": False,
        "timeout_keep_alive": settings.gateway_keep_alive_s,
        "timeout_graceful_shutdown": settings.gateway_shutdown_grace_s,
        "access_log": False,
    }


def serve(args: argparse.Namespace, scene_area: SceneArea | None = None) -> int:
    import uvicorn

    from eqa.service import setup_logging
    from gateway.app import create_app

    try:
        settings = Settings()
    except Exception as exc:
        print(f"error: invalid EQA_* settings: {exc}", file=sys.stderr)
        return 2
    if args.host:
        settings = settings.model_copy(update={"gateway_host": args.host})
    if args.port is not None:
        if not 0 <= args.port <= 65535:
            print(f"error: port {args.port} out of range", file=sys.stderr)
            return 2
        settings = settings.model_copy(update={"gateway_port": args.port})
    setup_logging(args.log_level or settings.log_level, "gateway", settings.log_format, settings.instance)
    # JSON logs: uvicorn's loggers go through the root handler (its own config would print them as text)
    log_config = None if settings.log_format == "json" else uvicorn.config.LOGGING_CONFIG
    uvicorn.run(
        create_app(settings, scene_area),
        log_level=(args.log_level or settings.log_level).lower(),
        log_config=log_config,
        **uvicorn_options(settings),
    )
    return 0


def _add_serve_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--host", default=None, help="override EQA_GATEWAY_HOST")
    p.add_argument("--port", type=int, default=None, help="override EQA_GATEWAY_PORT")
    p.add_argument("--log-level", default=None, help="override EQA_LOG_LEVEL")


def register(subparsers: argparse._SubParsersAction, scene_area: SceneArea | None = None) -> None:
    p = subparsers.add_parser("gateway", help="run the HTTP gateway (configured by EQA_* variables)")
    _add_serve_args(p)
    p.set_defaults(func=functools.partial(serve, scene_area=scene_area))


def main(argv: list[str] | None = None, scene_area: SceneArea | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m gateway",
        description=(
            "Run the EQA HTTP gateway. Configured by EQA_* environment variables (see eqa/settings.py); "
            "runs until SIGTERM/SIGINT."
        ),
    )
    _add_serve_args(parser)
    return serve(parser.parse_args(argv), scene_area)

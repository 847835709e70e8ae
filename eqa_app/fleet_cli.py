"""``eqa router`` and ``eqa certs``: the parts of a fleet across machines (docs/deployment.md, "Scaling out").

    eqa certs DIR --host 10.0.0.1 --host zenoh   a private CA, one certificate per role, a users file
    eqa router                                   a Zenoh router configured by EQA_* (TLS, users, ACL)
    eqa router --print-config                    the same configuration as a zenohd JSON5 file
"""

from __future__ import annotations

import argparse
import secrets
import signal
import threading
from pathlib import Path
from typing import Any

from eqa import security


def cmd_certs(args: argparse.Namespace) -> int:
    out = Path(args.dir)
    hosts = tuple(dict.fromkeys(["localhost", "127.0.0.1", *args.host]))
    made = security.make_fleet_certs(out, roles=security.ROLES, hosts=hosts, days=args.days)
    users = out / "users.txt"
    if not users.exists():
        users.write_text("".join(f"{role}:{secrets.token_urlsafe(18)}\n" for role in security.ROLES))
        users.chmod(0o600)
    print(f"CA and {len(made)} certificates ({', '.join(made)}) in {out}, valid for {', '.join(hosts)}")
    print(f"passwords: {users} (keep it and the *.key files out of git and images)")
    print(f"a host's share: EQA_ZENOH_TLS_DIR={out.resolve()} EQA_ZENOH_USERS_FILE={users.resolve()} "
          "EQA_ZENOH_ACL=true eqa up --join tls/<router>:7447 --services ...")
    return 0


def cmd_router(args: argparse.Namespace) -> int:
    from eqa.bus import Bus
    from eqa.service import setup_logging
    from eqa_app.cli import UsageError, load_settings

    settings = load_settings()
    update: dict[str, Any] = {"zenoh_mode": "router"}
    if args.listen:
        update["zenoh_listen"] = args.listen
    if args.connect is not None:
        update["zenoh_connect"] = args.connect
    settings = settings.model_copy(update=update)
    if not settings.zenoh_listen:
        raise UsageError("a router needs an endpoint to listen on: --listen tls/0.0.0.0:7447 (or EQA_ZENOH_LISTEN)")
    try:
        if args.print_config:
            print(security.router_config_json5(settings))
            return 0
        security.check(settings)
    except security.SecurityConfigError as exc:
        raise UsageError(str(exc)) from None
    setup_logging(settings.log_level, "eqa-router", settings.log_format, settings.instance)
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    with Bus(settings, "router", settings.instance):
        extra = (" (mTLS)" if security.tls_on(settings) else "") + (" with the ACL" if settings.zenoh_acl else "")
        print(f"router listening on {', '.join(settings.zenoh_listen)}{extra}", flush=True)
        done.wait()  # SIGTERM; Ctrl-C unwinds through eqa's main
    return 0


def register(sub: Any) -> None:
    certs = sub.add_parser("certs", help="make a private CA, one certificate per role and a users file")
    certs.add_argument("dir", help="output directory (keep it out of git)")
    certs.add_argument("--host", action="append", default=[],
                       help="a host name or IP address routers are reached at (repeatable)")
    certs.add_argument("--days", type=int, default=365, help="validity (default 365)")
    certs.set_defaults(func=cmd_certs)

    router = sub.add_parser("router", help="run a Zenoh router with the fleet's security settings")
    router.add_argument("--listen", action="append", default=None, help="endpoint, e.g. tls/0.0.0.0:7447")
    router.add_argument("--connect", action="append", default=None, help="another router to connect to")
    router.add_argument("--print-config", action="store_true", help="print a zenohd JSON5 config and exit")
    router.set_defaults(func=cmd_router)

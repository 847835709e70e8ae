"""The bus secured with Zenoh's own means: TLS with mutual authentication, user/password authentication and an
access-control list that lets only the owner of a stream publish on it.

Everything here is Zenoh configuration built from :class:`eqa.settings.Settings`; nothing in the services
changes. Off by default (the loopback peer fleet of ``eqa up`` needs none of it).

* **TLS** (``EQA_ZENOH_TLS_CA``, ``EQA_ZENOH_TLS_CERT``, ``EQA_ZENOH_TLS_KEY``): every link is ``tls/``
  (other protocols are refused), both ends present a certificate signed by the fleet's CA (mTLS), and the
  certificate's common name is the node's *role*: a service name (``stopper``, ``gateway``, ...),
  ``router`` or ``operator`` (read-only tools: ``eqa health``).
* **User/password** (``EQA_ZENOH_USER`` / ``EQA_ZENOH_PASSWORD`` on the connecting side,
  ``EQA_ZENOH_USERS_FILE`` with ``user:password`` lines on the accepting side): the user name is the role too.
* **Access control** (``EQA_ZENOH_ACL=true``, on the routers): :func:`acl_config` denies by default and
  allows each role exactly what its service does (:data:`STREAM_OWNERS`): the stopper alone puts
  ``EpisodeEnd``, the gateway alone ``EpisodeStart``/``EpisodeCancel``, a scorer replica alone answers score
  queries, every role holds liveliness tokens only under its own service name. With TLS the subject is the
  certificate's common name (user/password then is a second gate at connection time); without TLS it is the
  user name, which only the accepting end of a link learns: so a fleet of several routers needs TLS.

Zenoh enforces the list on the node that holds it, on the messages that come in over its links. So a secured
fleet is routers (``EQA_ZENOH_MODE=router``, ACL on) with services connected to them as clients
(``EQA_ZENOH_MODE=client``): every message of a service passes its router's ingress check, and services do
not listen, so nobody can reach them around the router. :func:`make_fleet_certs` writes a private CA and
one certificate per role with ``openssl`` (for tests and a first deployment; keys never go into git).
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path
from typing import Any

from eqa import keys
from eqa.settings import BusSettings

# Who alone may publish each stream of a robot (every stream of ``eqa.messages.STREAM_TYPES`` has one owner).
STREAM_OWNERS: dict[tuple[str, str], str] = {
    keys.EPISODE_START: "gateway",
    keys.EPISODE_CANCEL: "gateway",
    keys.EPISODE_END: "stopper",
    keys.SIM_FRAME: "sim",
    keys.SIM_ERROR: "sim",
    keys.MAPPER_MAP: "mapper",
    keys.MAPPER_SCORES: "mapper",
    keys.MAPPER_ERROR: "mapper",
    keys.STOPPER_DECISION: "stopper",
    keys.PLANNER_GOAL: "planner",
}
# Roles that query the scorer pool (the mapper scores views; the CLI's scorer check runs as operator).
SCORER_CLIENTS = ("mapper", "operator")
ROUTER = "router"
OPERATOR = "operator"
ROLES = (*keys.SERVICES, ROUTER, OPERATOR)

ALL_MESSAGES = (
    "put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
    "liveliness_token", "declare_liveliness_subscriber", "liveliness_query",
)
_ALL_KEYS = f"{keys.ROOT}/**"
_SCORER_KEYS = keys.SCORER_ANY


class SecurityConfigError(ValueError):
    """Security settings that cannot work together; the message says what to set."""


def tls_on(settings: BusSettings) -> bool:
    return settings.zenoh_tls_ca is not None


def check(settings: BusSettings) -> None:
    """Refuse incomplete or contradictory security settings with a message that says what to set."""
    cert, key, ca = settings.zenoh_tls_cert, settings.zenoh_tls_key, settings.zenoh_tls_ca
    if (cert is None) != (key is None):
        raise SecurityConfigError("set both EQA_ZENOH_TLS_CERT and EQA_ZENOH_TLS_KEY (this node's certificate and key)")
    if cert is not None and ca is None:
        raise SecurityConfigError(
            "EQA_ZENOH_TLS_CERT needs EQA_ZENOH_TLS_CA (the CA that signed the fleet's certificates)"
        )
    if ca is not None:
        if cert is None:
            raise SecurityConfigError(
                "TLS is mutual: with EQA_ZENOH_TLS_CA set, also set EQA_ZENOH_TLS_CERT and EQA_ZENOH_TLS_KEY "
                "(`eqa certs DIR` makes a CA and one certificate per role)"
            )
        for what, path in (("EQA_ZENOH_TLS_CA", ca), ("EQA_ZENOH_TLS_CERT", cert), ("EQA_ZENOH_TLS_KEY", key)):
            if path is not None and not Path(path).is_file():
                raise SecurityConfigError(f"{what}={path}: no such file")
        plain = [e for e in (*settings.zenoh_listen, *settings.zenoh_connect) if not e.startswith("tls/")]
        if plain:
            raise SecurityConfigError(
                f"with TLS on, every endpoint must be tls/...: {', '.join(plain)} (EQA_ZENOH_LISTEN/EQA_ZENOH_CONNECT)"
            )
    if (settings.zenoh_user is None) != (settings.zenoh_password is None):
        raise SecurityConfigError("set both EQA_ZENOH_USER and EQA_ZENOH_PASSWORD, or neither")
    if settings.zenoh_users_file is not None and not Path(settings.zenoh_users_file).is_file():
        raise SecurityConfigError(f"EQA_ZENOH_USERS_FILE={settings.zenoh_users_file}: no such file")
    if settings.zenoh_acl and ca is None and settings.zenoh_users_file is None:
        raise SecurityConfigError(
            "EQA_ZENOH_ACL needs a way to tell roles apart: TLS (EQA_ZENOH_TLS_CA, ...) and/or "
            "EQA_ZENOH_USERS_FILE"
        )


def _rule(rule_id: str, messages: tuple[str, ...], key_exprs: list[str], flow: str = "ingress") -> dict[str, Any]:
    return {"id": rule_id, "permission": "allow", "flows": [flow], "messages": list(messages), "key_exprs": key_exprs}


def role_grants(role: str) -> list[tuple[tuple[str, ...], list[str]]]:
    """What one role may send into a router: ``(message kinds, key expressions)`` pairs. Pure."""
    if role not in ROLES:
        raise ValueError(f"unknown role {role!r}; known: {', '.join(ROLES)}")
    if role == ROUTER:  # another router forwards what its own list let in
        return [(ALL_MESSAGES, [_ALL_KEYS])]
    grants: list[tuple[tuple[str, ...], list[str]]] = [
        (("declare_subscriber",), [_ALL_KEYS]),
        (("declare_liveliness_subscriber", "liveliness_query"), [keys.ALIVE_ANY]),
    ]
    if role != OPERATOR:
        grants.append((("liveliness_token",), [keys.alive_service(role)]))
    owned = [keys.any_robot(pair) for pair, owner in STREAM_OWNERS.items() if owner == role]
    if owned:
        grants.append((("put",), owned))
    if role == "vlm_scorer":
        grants.append((("declare_queryable", "reply"), [_SCORER_KEYS]))
    if role in SCORER_CLIENTS:
        grants.append((("query",), [_SCORER_KEYS]))
    return grants


def acl_config(by_cert: bool, by_user: bool, roles: tuple[str, ...] = ROLES) -> dict[str, Any]:
    """Zenoh's ``access_control`` section: deny by default, allow each role its :func:`role_grants` on the way
    in, and anything on the way out to an identified role (it was checked on the way in). Pure."""
    if not (by_cert or by_user):
        raise SecurityConfigError("the ACL needs certificates and/or user names to identify roles")
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for role in roles:
        subject: dict[str, Any] = {"id": f"role-{role}"}
        if by_cert:
            subject["cert_common_names"] = [role]
        if by_user:
            subject["usernames"] = [role]
        subjects.append(subject)
        ids = []
        for i, (messages, key_exprs) in enumerate(role_grants(role)):
            rule_id = f"{role}-in-{i}"
            rules.append(_rule(rule_id, messages, key_exprs))
            ids.append(rule_id)
        policies.append({"rules": ids, "subjects": [subject["id"]]})
    rules.append(_rule("out-to-fleet", ALL_MESSAGES, [_ALL_KEYS], flow="egress"))
    policies.append({"rules": ["out-to-fleet"], "subjects": [s["id"] for s in subjects]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


def security_sections(settings: BusSettings) -> dict[str, Any]:
    """The Zenoh configuration entries (path -> value) that the security settings add. Empty when all are off."""
    check(settings)
    out: dict[str, Any] = {}
    if tls_on(settings):
        cert, key = str(settings.zenoh_tls_cert), str(settings.zenoh_tls_key)
        out["transport/link/protocols"] = ["tls"]
        out["transport/link/tls"] = {
            "root_ca_certificate": str(settings.zenoh_tls_ca),
            "enable_mtls": True,
            "listen_certificate": cert,
            "listen_private_key": key,
            "connect_certificate": cert,
            "connect_private_key": key,
            "verify_name_on_connect": True,
        }
    usrpwd: dict[str, Any] = {}
    if settings.zenoh_user is not None:
        usrpwd["user"] = settings.zenoh_user
        usrpwd["password"] = settings.zenoh_password
    if settings.zenoh_users_file is not None:
        usrpwd["dictionary_file"] = str(settings.zenoh_users_file)
    if usrpwd:
        out["transport/auth/usrpwd"] = usrpwd
    if settings.zenoh_acl:
        # With TLS the subject is the certificate's common name alone: a node that opened a link knows the
        # other end's certificate but not its user name (user/password authenticates the opener only), so
        # requiring both would deny everything a router forwards to the router it connected to.
        by_cert = tls_on(settings)
        out["access_control"] = acl_config(by_cert, not by_cert and settings.zenoh_users_file is not None)
    return out


def apply(conf: Any, settings: BusSettings) -> None:
    """Insert :func:`security_sections` into a ``zenoh.Config``."""
    for path, value in security_sections(settings).items():
        conf.insert_json5(path, json.dumps(value))


def router_config_json5(settings: BusSettings) -> str:
    """A whole configuration file for ``zenohd -c`` (the compose file's router) from these settings."""
    doc: dict[str, Any] = {
        "mode": "router",
        "listen": {"endpoints": list(settings.zenoh_listen)},
        "connect": {"endpoints": list(settings.zenoh_connect)},
        "scouting": {"multicast": {"enabled": bool(settings.zenoh_multicast)}},
    }
    for path, value in security_sections(settings).items():
        node = doc
        *parents, leaf = path.split("/")
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = value
    return json.dumps(doc, indent=2)


# ---- certificates (tests, a first deployment) ------------------------------------------------------------


def _openssl(*args: str, cwd: Path) -> None:
    exe = shutil.which("openssl")
    if exe is None:
        raise RuntimeError("openssl is not installed: apt-get install openssl (or bring your own certificates)")
    proc = subprocess.run([exe, *args], cwd=cwd, capture_output=True, text=True, timeout=60)
    if proc.returncode != 0:
        raise RuntimeError(f"openssl {args[0]} failed: {proc.stderr.strip()[-500:]}")


def make_fleet_certs(
    out_dir: Path, roles: tuple[str, ...] = ROLES, hosts: tuple[str, ...] = ("localhost", "127.0.0.1"), days: int = 30
) -> dict[str, tuple[Path, Path]]:
    """Write ``ca.pem``/``ca.key`` and ``<role>.pem``/``<role>.key`` for each role (P-256 keys, CN = role,
    the given host names and IP addresses as subject alternative names so that routers can be verified).
    Returns ``role -> (certificate, key)``."""
    import ipaddress

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ec = ("-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes")
    if not (out / "ca.pem").exists():
        _openssl("req", "-x509", *ec, "-keyout", "ca.key", "-out", "ca.pem", "-days", str(days),
                 "-subj", "/CN=eqa-fleet-ca", "-addext", "basicConstraints=critical,CA:TRUE",
                 "-addext", "keyUsage=critical,keyCertSign,cRLSign", cwd=out)
    sans = []
    for h in hosts:
        try:
            ipaddress.ip_address(h)
            sans.append(f"IP:{h}")
        except ValueError:
            sans.append(f"DNS:{h}")
    made: dict[str, tuple[Path, Path]] = {}
    for role in roles:
        keys.check_id(role, "role")
        ext = out / f"{role}.ext"
        ext.write_text(
            "basicConstraints=CA:FALSE\nkeyUsage=critical,digitalSignature\n"
            f"extendedKeyUsage=serverAuth,clientAuth\nsubjectAltName={','.join(sans)}\n"
        )
        _openssl("req", *ec, "-keyout", f"{role}.key", "-out", f"{role}.csr", "-subj", f"/CN={role}", cwd=out)
        _openssl("x509", "-req", "-in", f"{role}.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial",
                 "-out", f"{role}.pem", "-days", str(days), "-extfile", ext.name, cwd=out)
        (out / f"{role}.csr").unlink()
        ext.unlink()
        (out / f"{role}.key").chmod(0o600)
        made[role] = (out / f"{role}.pem", out / f"{role}.key")
    (out / "ca.key").chmod(0o600)
    return made

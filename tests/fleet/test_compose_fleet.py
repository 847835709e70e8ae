"""docker-compose.fleet.yml (a fleet over several hosts) cannot run here (no container engine), so its settings
are run instead: every EQA_* variable is one the code reads, every service presents its own role's certificate
and user, and the router and a service configured exactly by the file's environment (certificates made by the
test, the router's host name pointed at loopback) connect over mTLS, and the router refuses a forged
EpisodeEnd."""

from __future__ import annotations

import re
import shutil
import threading
import time
from pathlib import Path

import pytest
import yaml

from eqa import keys, security
from eqa.bus import Bus
from eqa.launcher import free_port
from eqa.messages import EpisodeEnd
from eqa.settings import Settings, env_names

REPO = Path(__file__).resolve().parents[2]
FLEET = yaml.safe_load((REPO / "docker-compose.fleet.yml").read_text())
SERVICES = {"sim", "mapper", "vlm_scorer", "planner", "stopper", "gateway"}
_VAR = re.compile(r"\$\{([A-Z_]+)(?::[-?]([^}]*))?\}")


def _env(service: str, values: dict[str, str], pki: Path, port: int) -> dict[str, str]:
    out = {}
    for k, v in FLEET["services"][service]["environment"].items():
        v = _VAR.sub(lambda m: values.get(m.group(1), m.group(2) or ""), str(v))
        v = v.replace("/pki/", f"{pki}/").replace("tls/zenoh:7447", f"tls/127.0.0.1:{port}")
        out[k] = v
    return out


def _settings(env: dict[str, str], monkeypatch: pytest.MonkeyPatch, tmp: Path) -> Settings:
    with monkeypatch.context() as m:
        for k in list(__import__("os").environ):
            if k.startswith("EQA_"):
                m.delenv(k)
        for k, v in env.items():
            m.setenv(k, v)
        m.setenv("EQA_DATA_DIR", str(tmp))
        return Settings()


def test_every_variable_is_a_setting_and_every_service_is_its_own_role():
    known = env_names()
    assert {"zenoh", "redis"} | SERVICES <= set(FLEET["services"])
    for name in SERVICES | {"zenoh"}:
        env = FLEET["services"][name]["environment"]
        assert not {k for k in env if k.startswith("EQA_")} - known, name
    for name in SERVICES:
        env = FLEET["services"][name]["environment"]
        assert env["EQA_ZENOH_TLS_CERT"] == f"/pki/{name}.pem" and env["EQA_ZENOH_USER"] == name
        assert env["EQA_ZENOH_MODE"] == "client" and env["EQA_SHARD"] == "true"
        cmd = FLEET["services"][name]["command"]
        assert (REPO / Path(*cmd[2].split("."))).joinpath("__main__.py").is_file()
    router = FLEET["services"]["zenoh"]
    assert router["environment"]["EQA_ZENOH_ACL"] == "true" and "router" in router["command"]
    assert "core" in router["profiles"] and "workers" in FLEET["services"]["mapper"]["profiles"]


@pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl is needed to make test certificates")
def test_the_files_settings_connect_and_the_router_refuses_a_forgery(tmp_path: Path,
                                                                    monkeypatch: pytest.MonkeyPatch):
    pki = tmp_path / "pki"
    security.make_fleet_certs(pki, days=1)
    pw = {r: f"pw-{r}" for r in security.ROLES}
    (pki / "users.txt").write_text("".join(f"{r}:{p}\n" for r, p in pw.items()))
    values = {f"EQA_PW_{r.upper()}": p for r, p in pw.items()}
    port = free_port()
    r_env = _env("zenoh", values, pki, port)
    r_set = _settings(r_env, monkeypatch, tmp_path)
    listen = FLEET["services"]["zenoh"]["command"][-1].replace("0.0.0.0:7447", f"127.0.0.1:{port}")
    r_set = r_set.model_copy(update={"zenoh_mode": "router", "zenoh_listen": [listen]})
    got: list[str] = []
    done = threading.Event()
    def on_end(_k: str, m: EpisodeEnd) -> None:
        got.append(m.reason)
        if m.reason == "real":
            done.set()

    def role(name: str) -> Settings:
        return _settings(_env(name, values, pki, port), monkeypatch, tmp_path)

    with Bus(r_set, "router", "router"), Bus(role("gateway"), "gateway", "gw") as gw, \
            Bus(role("stopper"), "stopper", "st") as st, Bus(role("planner"), "planner", "pl") as pl:
        gw.subscribe(keys.any_robot(keys.EPISODE_END), EpisodeEnd, on_end)
        time.sleep(0.5)
        forged = EpisodeEnd(episode_id="e", robot="robot0", state="stopped", reason="forged", answer="B")
        pl.publish(keys.stream("robot0", keys.EPISODE_END), forged)
        st.publish(keys.stream("robot0", keys.EPISODE_END), forged.model_copy(update={"reason": "real"}))
        assert done.wait(5.0)
        time.sleep(0.3)
    assert got == ["real"]

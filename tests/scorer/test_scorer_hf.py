"""The hf backend on a tiny random Qwen2-VL that the test builds, saves and loads like a user's model."""

from __future__ import annotations

import numpy as np
import pytest
from support.scorer import frame_request

from eqa.messages import NOT_LISTED_CHOICE, Question
from services.vlm_scorer import prompts
from services.vlm_scorer.backends.base import BackendUnavailable, BadRequest
from services.vlm_scorer.backends.hf import HFBackend
from services.vlm_scorer.tiny import build_tiny_qwen2vl
from services.vlm_scorer.visual_prompt import annotate


@pytest.fixture(scope="module")
def backend(tmp_path_factory: pytest.TempPathFactory) -> HFBackend:
    path = build_tiny_qwen2vl(tmp_path_factory.mktemp("tiny") / "qwen2vl")
    return HFBackend(path)


def test_probabilities_sum_to_one_over_candidates(backend):
    req = frame_request(h=56, w=84)
    req.prompt_points.append(req.prompt_points[0].model_copy(update={"label": "C", "u": 40.0}))
    s = backend.score(req)
    assert len(s.answer_probs) == 4 and abs(sum(s.answer_probs) - 1) < 1e-6
    assert len(s.lsv) == 3 and abs(sum(s.lsv) - 1) < 1e-6
    assert 0 < s.relevance < 1 and 0 < s.gsv < 1
    assert all(p > 0 for p in s.answer_probs)
    assert s.annotated is not None and not np.array_equal(s.annotated, req.rgb)


def test_batched_equals_unbatched(backend):
    req = frame_request(h=56, w=84)
    queries = prompts.step_queries(req.question, req.question.choices, len(req.prompt_points))
    assert [q.name for q in queries] == ["answer", "relevance", "gsv", "lsv"]
    ann = annotate(req.rgb, req.prompt_points)
    batched = backend.candidate_probs(req.rgb, ann, queries)
    for q, b in zip(queries, batched, strict=True):
        single = backend.candidate_probs(req.rgb, ann, [q])[0]
        assert set(single) == set(q.candidates)
        for c in q.candidates:
            assert b[c] == pytest.approx(single[c], abs=1e-5)
    # the annotated image matters: the LSV query on the plain image differs
    plain = backend.candidate_probs(req.rgb, None, [queries[-1]])[0]
    assert any(abs(plain[c] - batched[-1][c]) > 1e-7 for c in plain)


def test_candidate_tokens_are_found(backend):
    ids = [backend.token_id(c) for c in ["A", "B", "C", "D", "Yes", "No"]]
    assert len(set(ids)) == 6
    assert [backend.tokenizer.decode([i]) for i in ids] == ["A", "B", "C", "D", "Yes", "No"]


def test_choice_letter_that_is_not_a_single_token_is_a_clear_error(tmp_path):
    b = HFBackend(build_tiny_qwen2vl(tmp_path / "abcd_only", letters="ABCD"))
    q = Question(text="Which one?", choices=["w", "x", "y", "z", "v"], scene="s")
    with pytest.raises(BadRequest, match="candidate 'E' is not a single token"):
        b.score(frame_request(question=q, h=56, w=84))


def test_questions_without_choices_get_proposals_plus_not_listed(backend):
    s = backend.score(frame_request(question=Question(text="What color is the sofa?", scene="s"), h=56, w=84))
    assert s.proposed_choices[-1] == NOT_LISTED_CHOICE
    assert len(s.answer_probs) == len(s.proposed_choices) and abs(sum(s.answer_probs) - 1) < 1e-6


def test_not_a_model_directory(tmp_path):
    with pytest.raises(BackendUnavailable, match="does not exist"):
        HFBackend(tmp_path / "missing")
    (tmp_path / "llm").mkdir()
    (tmp_path / "llm" / "config.json").write_text('{"model_type": "gpt2"}')
    with pytest.raises(BackendUnavailable, match="not a supported vision-language model"):
        HFBackend(tmp_path / "llm")


def test_helios_value_prompt_reads_p_yes(backend):
    """HELIOS 3.1.2 on the hf backend: P(Yes) of "Seems like there is a (object) ahead. Answer Yes or No.",
    normalised over Yes / No, one per target."""
    from eqa.messages import ValueRequest
    from services.vlm_scorer.target_values import QUESTION, target_values

    rgb = frame_request(h=56, w=84).rgb
    values = target_values(backend, ValueRequest(episode_id="e", step=0, rgb=rgb, targets=["mug", "sofa"]))
    q = prompts.Query("value", QUESTION.format(target="mug"), prompts.YES_NO)
    direct = backend.candidate_probs(rgb, None, [q])[0]
    assert len(values) == 2 and all(0 < v < 1 for v in values)
    assert values[0] == pytest.approx(direct["Yes"] / (direct["Yes"] + direct["No"]), rel=1e-4)

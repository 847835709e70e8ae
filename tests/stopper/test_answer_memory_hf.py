"""Answer memory on the hf backend: one prompt with several images, through the real transformers
code path of a tiny random Qwen2-VL built offline (its probabilities are meaningless; the plumbing is real)."""

from __future__ import annotations

import numpy as np
import pytest

from eqa.messages import Question
from services.vlm_scorer import prompts
from services.vlm_scorer.backends.base import BadRequest
from services.vlm_scorer.backends.hf import HFBackend, qwen_chat_images
from services.vlm_scorer.tiny import build_tiny_qwen2vl

Q = Question(text="What colour is the sofa?", choices=["red", "blue", "green", "grey"], scene="s")


@pytest.fixture(scope="module")
def backend(tmp_path_factory: pytest.TempPathFactory) -> HFBackend:
    return HFBackend(build_tiny_qwen2vl(tmp_path_factory.mktemp("tiny") / "qwen2vl"))


def _img(seed: int, h: int = 56, w: int = 84) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, size=(h, w, 3), dtype=np.uint8)


def test_several_images_in_one_prompt(backend: HFBackend) -> None:
    a, b, c = _img(1), _img(2), _img(3, 84, 56)  # images of different sizes: each placeholder its own tokens
    p2 = backend.answer_from_views([a, b], Q, Q.choices)
    assert len(p2) == 4 and abs(sum(p2) - 1) < 1e-6 and all(v > 0 for v in p2)
    # every image reaches the model: changing the second view, or adding a third, changes the answer
    assert not np.allclose(p2, backend.answer_from_views([a, c], Q, Q.choices), atol=1e-7)
    p3 = backend.answer_from_views([a, b, c], Q, Q.choices)
    assert len(p3) == 4 and not np.allclose(p2, p3, atol=1e-7)
    # deterministic (no sampling)
    assert backend.answer_from_views([a, b], Q, Q.choices) == pytest.approx(p2, abs=1e-6)


def test_prompt_format_and_bounds(backend: HFBackend) -> None:
    chat = qwen_chat_images("x", 3)
    assert chat.count("<|vision_start|><|image_pad|><|vision_end|>") == 3 and "Picture 3: " in chat
    assert "3 images are views of the same scene" in prompts.memory_answer_prompt(Q, Q.choices, 3)
    with pytest.raises(ValueError):
        prompts.memory_answer_prompt(Q, Q.choices, prompts.MAX_MEMORY_VIEWS + 1)
    with pytest.raises(BadRequest, match=r"1\.\.16 images"):
        backend.answer_from_views([], Q, Q.choices)
    with pytest.raises(BadRequest, match="uint8"):
        backend.answer_from_views([np.zeros((56, 84, 3), np.float32)], Q, Q.choices)

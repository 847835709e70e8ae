"""The batch-wide Qwen2-VL inputs of services/vlm_scorer/backends/qwen_inputs.py against transformers' own code on
random inputs: M-RoPE positions equal ``Qwen2VLModel.get_rope_index``'s, the prepared attention mask equals the
library's causal mask, and pixel values equal the image processor's, value for value."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from services.vlm_scorer.backends.qwen_inputs import QwenPixels, causal_padding_bias, mrope_position_ids


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory):
    from transformers import AutoImageProcessor, AutoModelForImageTextToText

    from services.vlm_scorer.tiny import build_tiny_qwen2vl

    path = build_tiny_qwen2vl(tmp_path_factory.mktemp("tiny") / "qwen2vl")
    return (AutoModelForImageTextToText.from_pretrained(path, local_files_only=True).eval(),
            AutoImageProcessor.from_pretrained(path, local_files_only=True))


def _random_batch(rng: np.random.Generator, merge: int, left: bool) -> tuple[torch.Tensor, ...]:
    """Rows of text runs and images (0-3 per row, random grids), padded on the left or the right."""
    rows, types, grids = [], [], []
    for _ in range(int(rng.integers(1, 7))):
        ids: list[int] = []
        kinds: list[int] = []
        for _ in range(int(rng.integers(0, 4))):
            text = int(rng.integers(1, 9))
            ids += rng.integers(10, 50, text).tolist()
            kinds += [0] * text
            h, w = (int(rng.integers(1, 6)) * merge for _ in range(2))
            grids.append([1, h, w])
            ids += [7] * (h * w // merge**2)
            kinds += [1] * (h * w // merge**2)
        text = int(rng.integers(1, 9))
        ids += rng.integers(10, 50, text).tolist()
        kinds += [0] * text
        rows.append(ids)
        types.append(kinds)
    length = max(len(r) for r in rows) + int(rng.integers(0, 5))
    input_ids = torch.zeros((len(rows), length), dtype=torch.long)
    mm = torch.zeros((len(rows), length), dtype=torch.int32)
    mask = torch.zeros((len(rows), length), dtype=torch.long)
    for k, (r, t) in enumerate(zip(rows, types, strict=True)):
        at = slice(length - len(r), length) if left else slice(0, len(r))
        input_ids[k, at] = torch.tensor(r)
        mm[k, at] = torch.tensor(t, dtype=torch.int32)
        mask[k, at] = 1
    grid = torch.tensor(grids, dtype=torch.long) if grids else None
    return input_ids, mm, grid, mask


def test_rope_positions_equal_the_librarys(tiny) -> None:
    model, _ = tiny
    merge = model.config.vision_config.spatial_merge_size
    rng = np.random.default_rng(0)
    images = 0
    for trial in range(200):
        input_ids, mm, grid, mask = _random_batch(rng, merge, left=trial % 2 == 0)
        images += 0 if grid is None else len(grid)
        ref_pos, ref_delta = model.model.get_rope_index(input_ids, mm_token_type_ids=mm, image_grid_thw=grid,
                                                        attention_mask=mask)
        pos, delta = mrope_position_ids(input_ids, mm, grid, mask, merge)
        assert pos.dtype == ref_pos.dtype and pos.shape == ref_pos.shape
        assert torch.equal(pos, ref_pos), f"trial {trial}"
        assert torch.equal(delta, ref_delta), f"trial {trial}"
    assert images > 200  # the trials did exercise images, several per row


def test_rope_positions_refuse_a_run_that_does_not_fit_its_grid(tiny) -> None:
    input_ids = torch.tensor([[5, 7, 7, 7, 5]])
    mm = torch.tensor([[0, 1, 1, 1, 0]], dtype=torch.int32)
    with pytest.raises(ValueError, match="grid"):
        mrope_position_ids(input_ids, mm, torch.tensor([[1, 4, 4]]), torch.ones_like(input_ids), 2)


@pytest.mark.parametrize("sizes", [[(120, 160)], [(120, 160), (60, 80), (120, 160), (56, 56), (97, 203)],
                                   [(480, 640), (33, 21)]])
def test_pixel_values_equal_the_image_processors(tiny, sizes) -> None:
    from PIL import Image

    _, processor = tiny
    pixels = QwenPixels(processor)
    assert pixels.exact
    rng = np.random.default_rng(len(sizes))
    images = [rng.integers(0, 256, (h, w, 3), dtype=np.uint8) for h, w in sizes]
    images.append(np.zeros((sizes[0][0], sizes[0][1], 3), np.uint8))
    images.append(np.full((sizes[0][0], sizes[0][1], 3), 255, np.uint8))
    ref = processor(images=[Image.fromarray(i) for i in images], return_tensors="pt")
    got, grid = pixels(images)
    assert got.dtype == ref["pixel_values"].dtype and got.shape == ref["pixel_values"].shape
    assert torch.equal(got, ref["pixel_values"])  # bit for bit: float32 equality with no tolerance
    assert torch.equal(grid, ref["image_grid_thw"])
    for (h, w), g in zip([im.shape[:2] for im in images], ref["image_grid_thw"], strict=True):
        assert pixels.tokens(h, w) == int(g.prod()) // processor.merge_size**2


def test_pixel_value_table_covers_every_value_of_every_channel(tiny) -> None:
    """Every 8-bit value in every channel: an image holding all 256 x 3 of them."""
    from PIL import Image

    _, processor = tiny
    h, w = QwenPixels(processor).resized(56, 56)
    assert (h, w) == (56, 56)  # not resized, so every value reaches the table unchanged
    flat = np.zeros((h * w, 3), np.uint8)
    flat[:256] = np.arange(256, dtype=np.uint8)[:, None]
    flat[256:512] = np.arange(256, dtype=np.uint8)[::-1, None]
    image = flat.reshape(h, w, 3)
    ref = processor(images=[Image.fromarray(image)], return_tensors="pt")["pixel_values"]
    assert torch.equal(QwenPixels(processor)([image])[0], ref)


def test_causal_padding_bias_is_the_float_form_of_the_librarys_mask(tiny) -> None:
    """The prepared mask equals what torch's attention makes of transformers' boolean causal mask (0 where it
    is True, -inf where False), for left- and right-padded rows and rows without padding."""
    from transformers.masking_utils import create_causal_mask

    model, _ = tiny
    text = model.model.language_model
    rng = np.random.default_rng(1)
    for trial in range(40):
        batch, length = int(rng.integers(1, 6)), int(rng.integers(2, 40))
        mask = torch.zeros((batch, length), dtype=torch.long)
        for b in range(batch):
            n = int(rng.integers(1, length + 1))
            if trial % 2 == 0:
                mask[b, length - n:] = 1
            else:
                mask[b, :n] = 1
        mask[0] = 1  # one row without padding
        embeds = torch.zeros((batch, length, text.config.hidden_size))
        ref = create_causal_mask(config=text.config, inputs_embeds=embeds, attention_mask=mask, past_key_values=None,
                                 allow_is_causal_skip=False)
        assert ref.dtype == torch.bool
        expected = torch.zeros(ref.shape).masked_fill(~ref, float("-inf"))
        got = causal_padding_bias(mask, torch.float32)
        assert got.dtype == torch.float32
        assert torch.equal(got, expected), f"trial {trial}"

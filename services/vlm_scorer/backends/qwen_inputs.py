"""Qwen2-VL model inputs for a whole batch in array operations: the image processor's ``pixel_values`` and the
M-RoPE position ids.

transformers computes both row by row in Python: ``Qwen2VLModel.get_rope_index`` groups each row's tokens with
``itertools.groupby`` and builds every group's positions with a few small tensor operations, and the image
processor converts, rescales, normalises and patchifies one image at a time. On a small model those loops cost
about as much as the forward pass, and they grow with every row a replica merges. Here the same numbers come
from a few whole-batch operations:

* :func:`mrope_position_ids` gives exactly ``get_rope_index``'s positions and deltas (integers), for any left
  or right padding and any number of images per row;
* :class:`QwenPixels` gives exactly the image processor's ``pixel_values`` and ``image_grid_thw``: the resize
  is the library's (PIL, the processor's resample filter and ``smart_resize`` size), and the rescale and
  normalisation, which map each 8-bit value of a channel to one float32 through the same float operations,
  become a 256 x 3 table looked up once per pixel, followed by one patchify of all images of a size.

tests/scorer/test_qwen_inputs.py compares both with the library's functions on random inputs, value for value.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

IMAGE_TYPE = 1  # mm_token_type_ids: 0 text, 1 image, 2 video


def mrope_position_ids(input_ids: Any, mm_token_type_ids: Any, image_grid_thw: Any, attention_mask: Any,
                       spatial_merge_size: int) -> tuple[Any, Any]:
    """``(position_ids (3, B, L), mrope_position_deltas (B, 1))`` as ``Qwen2VLModel.get_rope_index`` computes
    them for text and image tokens (videos are not supported: ``ValueError``).

    The tokens a row attends to (``attention_mask``) are taken in order; a run of equal token types is a group
    (text, or one image whose grid is the next of ``image_grid_thw``, in row-major order). A text group of n
    tokens advances the position by n, an image group by ``max(h, w) / merge``; a text token's three positions
    are its group's start plus its index in the group, an image token's are the start plus its (t, h, w) in the
    merged grid. Masked positions stay 0."""
    import torch

    batch, length = input_ids.shape
    valid = attention_mask.bool() if attention_mask is not None else torch.ones(
        batch, length, dtype=torch.bool, device=input_ids.device)
    types = mm_token_type_ids.to(torch.long)[valid]  # the attended tokens, row-major
    if bool((types > IMAGE_TYPE).any()):
        raise ValueError("mrope_position_ids handles text and image tokens, not video")
    counts = valid.sum(1)
    row = torch.repeat_interleave(torch.arange(batch, device=input_ids.device), counts)
    n = types.numel()
    starts = torch.ones(n, dtype=torch.bool, device=input_ids.device)
    starts[1:] = (types[1:] != types[:-1]) | (row[1:] != row[:-1])
    group = torch.cumsum(starts, 0) - 1  # group index of every token
    first = torch.nonzero(starts).squeeze(1)  # flat index of every group's first token
    g_type = types[first]
    g_len = torch.diff(first, append=torch.tensor([n], device=first.device))
    g_row = row[first]
    is_image = g_type == IMAGE_TYPE
    n_images = int(is_image.sum())
    # a text group's grid is a single merged cell (never read for its positions; keeps the divisions defined)
    grids = torch.tensor([1, spatial_merge_size, spatial_merge_size], device=input_ids.device).repeat(first.numel(), 1)
    if n_images:
        if image_grid_thw is None or len(image_grid_thw) < n_images:
            raise ValueError(f"{n_images} image token runs but {0 if image_grid_thw is None else len(image_grid_thw)}"
                             " image grids")
        grids[is_image] = image_grid_thw[:n_images].to(torch.long).to(input_ids.device)
    llm_t = grids[:, 0]
    llm_h = grids[:, 1] // spatial_merge_size
    llm_w = grids[:, 2] // spatial_merge_size
    if bool((g_len[is_image] != (llm_t * llm_h * llm_w)[is_image]).any()):
        raise ValueError("an image's token run does not match its grid")
    advance = torch.where(is_image, torch.maximum(llm_h, llm_w), g_len)
    before = torch.cumsum(advance, 0) - advance  # advances of all earlier groups of the batch
    row_first = torch.zeros(batch, dtype=torch.long, device=input_ids.device)
    row_first.scatter_reduce_(0, g_row, before, reduce="amin", include_self=False)
    g_start = before - row_first[g_row]  # the group's start position in its row
    k = torch.arange(n, device=input_ids.device) - first[group]  # index of each token in its group
    start = g_start[group]
    h, w = llm_h[group], llm_w[group]
    image = is_image[group]
    pos = torch.stack([
        start + torch.where(image, k // (h * w), k),
        start + torch.where(image, (k // w) % h, k),
        start + torch.where(image, k % w, k),
    ])
    position_ids = torch.zeros((3, batch, length), dtype=input_ids.dtype, device=input_ids.device)
    position_ids[:, valid] = pos.to(input_ids.dtype)
    top = torch.zeros(batch, dtype=torch.long, device=input_ids.device)
    top.scatter_reduce_(0, row, pos.amax(0), reduce="amax", include_self=False)
    return position_ids, (top + 1 - counts).unsqueeze(1)


def causal_padding_bias(attention_mask: Any, dtype: Any) -> Any:
    """The additive 4D attention mask ``(B, 1, L, L)`` of a causal language model over padded rows: 0 where query
    ``q`` may attend to key ``k`` (``k <= q`` and ``attention_mask[b, k]``), -inf elsewhere.

    transformers builds this as a boolean mask (``masking_utils.create_causal_mask``) and torch's
    ``scaled_dot_product_attention`` turns a boolean mask into exactly this float one (0 / -inf) in every layer
    it is given to; building it once, as the sum of a causal and a padding term, is what saves that. The model
    takes it as its prepared mask (``attention_mask={"full_attention": ...}``)."""
    import torch

    length = attention_mask.shape[1]
    causal = torch.full((length, length), float("-inf"), dtype=dtype, device=attention_mask.device).triu(1)
    padding = torch.zeros(attention_mask.shape, dtype=dtype, device=attention_mask.device)
    padding.masked_fill_(attention_mask == 0, float("-inf"))
    return causal[None, None] + padding[:, None, None, :]


class QwenPixels:
    """``pixel_values`` and ``image_grid_thw`` of HxWx3 uint8 images, as the Qwen2-VL image processor
    (``Qwen2VLImageProcessorPil``) makes them, for all images of a call at once; another processor class is
    called as it is (:attr:`exact` is False then)."""

    def __init__(self, processor: Any) -> None:
        self.processor = processor
        self.exact = type(processor).__name__ == "Qwen2VLImageProcessorPil"
        self.patch = int(processor.patch_size)
        self.merge = int(processor.merge_size)
        self.temporal = int(processor.temporal_patch_size)
        self.resize = bool(processor.do_resize)
        self.resample = processor.resample
        size = processor.size
        self.min_pixels = int(size["shortest_edge"]) if self.resize else 0
        self.max_pixels = int(size["longest_edge"]) if self.resize else 0
        self.table = self._table(processor)
        self._sizes: dict[tuple[int, int], tuple[int, int]] = {}

    @staticmethod
    def _table(processor: Any) -> np.ndarray:
        """The float32 value of each 8-bit value in each channel after the processor's rescale and normalise
        (``image_transforms.rescale`` and ``normalize``, the same operations on the same dtypes), 256 x 3."""
        v: np.ndarray = np.repeat(np.arange(256, dtype=np.uint8)[:, None], 3, axis=1)
        if processor.do_rescale:
            v = (v.astype(np.float64) * processor.rescale_factor).astype(np.float32)
        if processor.do_normalize:
            if not np.issubdtype(v.dtype, np.floating):
                v = v.astype(np.float32)
            mean, std = processor.image_mean, processor.image_std
            mean = np.array(list(mean) if isinstance(mean, (list, tuple)) else [mean] * 3, dtype=v.dtype)
            std = np.array(list(std) if isinstance(std, (list, tuple)) else [std] * 3, dtype=v.dtype)
            v = (v - mean) / std
        return np.ascontiguousarray(v, dtype=np.float32)

    def resized(self, h: int, w: int) -> tuple[int, int]:
        """The height and width the processor resizes an ``h`` x ``w`` image to."""
        if not self.resize:
            return h, w
        got = self._sizes.get((h, w))
        if got is None:
            from transformers.models.qwen2_vl.image_processing_pil_qwen2_vl import smart_resize

            got = self._sizes[(h, w)] = tuple(smart_resize(h, w, factor=self.patch * self.merge,  # type: ignore[assignment]
                                                           min_pixels=self.min_pixels, max_pixels=self.max_pixels))
        return got

    def tokens(self, h: int, w: int) -> int:
        """How many ``<|image_pad|>`` tokens an ``h`` x ``w`` image takes."""
        rh, rw = self.resized(h, w)
        return (rh // self.patch) * (rw // self.patch) // (self.merge**2)

    def __call__(self, images: list[np.ndarray]) -> tuple[Any, Any]:
        """``(pixel_values, image_grid_thw)`` torch tensors of ``images``, concatenated in order."""
        import torch
        from PIL import Image

        if not self.exact:
            vis = self.processor(images=[Image.fromarray(i) for i in images], return_tensors="pt")
            return vis["pixel_values"], vis["image_grid_thw"]
        resized = []
        for im in images:
            rh, rw = self.resized(*im.shape[:2])
            if (rh, rw) == im.shape[:2] or not self.resize:
                resized.append(np.ascontiguousarray(im))
            else:
                pil = Image.fromarray(np.ascontiguousarray(im)).resize((rw, rh), resample=self.resample)
                resized.append(np.asarray(pil))
        by_size: dict[tuple[int, int], list[int]] = {}
        for k, im in enumerate(resized):
            by_size.setdefault(im.shape[:2], []).append(k)
        parts: list[np.ndarray] = [np.empty(0)] * len(images)
        grids = np.zeros((len(images), 3), dtype=np.int64)
        for (h, w), members in by_size.items():
            patches = self._patchify(np.stack([resized[k] for k in members]))
            if len(by_size) == 1:  # one size: already in order
                parts = [patches]
            per = (h // self.patch) * (w // self.patch)
            for j, k in enumerate(members):
                if len(by_size) > 1:
                    parts[k] = patches[j * per:(j + 1) * per]
                grids[k] = (1, h // self.patch, w // self.patch)
        return torch.from_numpy(np.concatenate(parts) if len(parts) > 1 else parts[0]), torch.from_numpy(grids)

    def _patchify(self, batch: np.ndarray) -> np.ndarray:
        """``Qwen2VLImageProcessorPil.patchify`` of each image of ``batch`` (N x H x W x 3 uint8) after the
        value table: rows of (channel, temporal copy, patch row, patch column), merge blocks in raster order.
        The 8-bit pixels are put in patch order first (a quarter of the bytes of the float values), then each
        channel's table is read straight into its place of the output and the temporal copy is one copy."""
        n, h, w, c = batch.shape
        p, m, t = self.patch, self.merge, self.temporal
        gh, gw = h // p, w // p
        # N, gh/m, m, p, gw/m, m, p, C  ->  N, gh/m, gw/m, m(h), m(w), C, p(h), p(w)
        pixels = np.ascontiguousarray(
            batch.reshape(n, gh // m, m, p, gw // m, m, p, c).transpose(0, 1, 4, 2, 5, 7, 3, 6))
        out = np.empty((n, gh // m, gw // m, m, m, c, t, p, p), dtype=np.float32)
        for ch in range(c):
            np.take(self.table[:, ch], pixels[:, :, :, :, :, ch], out=out[:, :, :, :, :, ch, 0])
        for k in range(1, t):
            out[:, :, :, :, :, :, k] = out[:, :, :, :, :, :, 0]
        return out.reshape(n * gh * gw, c * t * p * p)

"""Local transformers vision-language model (``scorer_backend=hf``), loaded from a directory.

Supported families (by ``config.model_type``): ``qwen2_vl`` and ``qwen2_5_vl`` (Qwen2-VL chat format).
The probabilities are read from the next-token logits at the end of the assistant prompt and normalised
over the candidate tokens (letters or Yes/No), i.e. a softmax restricted to the candidate logits. The
four prompts of a step run as one left-padded batch (:meth:`HFBackend.candidate_probs`); the steps of several
robots that a replica batches share forward passes (:meth:`HFBackend.candidate_probs_many`).

Inputs are built from the directory's tokenizer and image processor (``AutoTokenizer``,
``AutoImageProcessor``) rather than ``Qwen2VLProcessor``: the processor insists on a video processor that
needs torchvision, which cannot be installed beside torch 2.13.0 here. Building them ourselves is what the
processor does for images: expand ``<|image_pad|>`` to ``prod(image_grid_thw) / merge_size**2`` tokens and
mark those tokens in ``mm_token_type_ids`` (1 = image) for M-RoPE. Without torchvision
``AutoImageProcessor`` gives ``Qwen2VLImageProcessorPil``.

What transformers computes row by row in Python around the forward pass is computed for the whole batch in array
operations (:mod:`services.vlm_scorer.backends.qwen_inputs`, each equal to the library's, tested): the pixel
values, the M-RoPE positions (passed as ``position_ids``) and the float attention mask (passed as the prepared
mask). The forward pass itself is the library's, asked for the last position's logits only.
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path
from typing import Any

import numpy as np

from services.vlm_scorer import prompts
from services.vlm_scorer.backends.base import BackendUnavailable, BadRequest, ModelBackend, ProbeItem
from services.vlm_scorer.backends.qwen_inputs import QwenPixels, causal_padding_bias, mrope_position_ids

log = logging.getLogger(__name__)

QWEN_FAMILIES = {"qwen2_vl", "qwen2_5_vl"}
IMAGE_PAD = "<|image_pad|>"
# the vision tower's output per distinct image, their grids, and per image array (by id) its distinct image's index
Encoded = tuple[tuple[Any, ...], Any, dict[int, int]]
# queries are left-padded to a multiple of this many tokens, alone or batched with other robots' steps (see
# HFBackend.candidate_probs_many): the padding a row carries changes its logits in the last bits
PAD_MULTIPLE = 32


def qwen_chat(text: str, system: str = prompts.SYSTEM) -> str:
    """Qwen2-VL chat format with one image before the user text, ending where the answer starts."""
    return (
        f"<|im_start|>system\n{system}<|im_end|>\n"
        f"<|im_start|>user\n<|vision_start|>{IMAGE_PAD}<|vision_end|>{text}<|im_end|>\n"
        "<|im_start|>assistant\n"
    )


def qwen_chat_images(text: str, n_images: int, system: str = prompts.SYSTEM) -> str:
    """Qwen2-VL chat format with ``n_images`` images ("Picture k:" before each, as Qwen2-VL's template with
    ``add_vision_id``) before the user text, ending where the answer starts."""
    vision = "".join(f"Picture {k + 1}: <|vision_start|>{IMAGE_PAD}<|vision_end|>" for k in range(n_images))
    return (
        f"<|im_start|>system\n{system}<|im_end|>\n"
        f"<|im_start|>user\n{vision}{text}<|im_end|>\n"
        "<|im_start|>assistant\n"
    )


def single_token_id(tokenizer: object, text: str) -> int:
    """The id of ``text`` as one token; a clear error when the tokenizer splits it or cannot encode it."""
    ids = tokenizer.encode(text, add_special_tokens=False)  # type: ignore[attr-defined]
    if len(ids) != 1:
        pieces = tokenizer.convert_ids_to_tokens(ids) if ids else []  # type: ignore[attr-defined]
        raise BadRequest(
            f"candidate {text!r} is not a single token of this model's tokenizer (encodes to {pieces!r}); "
            "its probability cannot be read from the next-token distribution"
        )
    return int(ids[0])


def check_model_dir(path: str | Path | None) -> Path:
    """``path`` if it looks like a saved transformers model (cheap: no torch), else :class:`BackendUnavailable`
    saying what to set."""
    if path is None:
        raise BackendUnavailable("scorer_backend=hf needs a model directory: set EQA_HF_MODEL_PATH")
    p = Path(path)
    if not p.is_dir():
        raise BackendUnavailable(
            f"hf model directory {str(p)!r} does not exist (set EQA_HF_MODEL_PATH to a saved model)"
        )
    if not (p / "config.json").is_file():
        raise BackendUnavailable(f"{str(p)!r} has no config.json: not a transformers model directory")
    return p


class HFBackend(ModelBackend):
    name = "hf"

    def __init__(self, path: str | Path, device: str = "cpu") -> None:
        import torch
        from transformers import AutoConfig, AutoImageProcessor, AutoModelForImageTextToText, AutoTokenizer

        self.path = check_model_dir(path)
        try:
            config = AutoConfig.from_pretrained(self.path, local_files_only=True)
        except Exception as exc:
            raise BackendUnavailable(f"cannot read the model config in {str(self.path)!r}: {exc}") from exc
        model_type = getattr(config, "model_type", "?")
        if model_type not in QWEN_FAMILIES or getattr(config, "vision_config", None) is None:
            raise BackendUnavailable(
                f"{str(self.path)!r} holds a {model_type!r} model, not a supported vision-language model "
                f"(supported: {', '.join(sorted(QWEN_FAMILIES))})"
            )
        self.torch = torch
        self.device = torch.device(device)
        self.tokenizer = AutoTokenizer.from_pretrained(self.path, local_files_only=True)
        self.tokenizer.padding_side = "left"
        if self.tokenizer.pad_token_id is None:
            self.tokenizer.pad_token = self.tokenizer.eos_token
        self.image_processor = AutoImageProcessor.from_pretrained(self.path, local_files_only=True)
        self.pixels = QwenPixels(self.image_processor)
        self.net = AutoModelForImageTextToText.from_pretrained(self.path, local_files_only=True)
        self.net.to(self.device).eval()
        self.image_token_id = int(config.image_token_id)
        self.merge = int(getattr(self.image_processor, "merge_size", 2))
        self.model_name = f"{model_type}:{self.path.name}"
        self._lock = threading.Lock()
        self._token_cache: dict[str, int] = {}
        self._chat_cache: dict[str, tuple[list[int], int]] = {}
        self._row_cache: dict[tuple[str, int], np.ndarray] = {}
        self.image_pad_id = int(self.tokenizer.convert_tokens_to_ids(IMAGE_PAD))
        log.info("hf backend: %s (%s) on %s", self.path, model_type, self.device)

    def token_id(self, text: str) -> int:
        if text not in self._token_cache:
            self._token_cache[text] = single_token_id(self.tokenizer, text)
        return self._token_cache[text]

    # ---- inputs ---------------------------------------------------------------------------------------
    def _pixels(self, images: list[np.ndarray]) -> tuple[object, object, list[int]]:
        """``pixel_values`` and ``image_grid_thw`` of the distinct arrays of ``images`` (each processed once: a
        step's plain image serves three of its four prompts, and a merged batch holds several steps), and for
        each image the index of its distinct one."""
        slot: dict[int, int] = {}
        distinct: list[np.ndarray] = []
        for im in images:
            if id(im) not in slot:
                slot[id(im)] = len(distinct)
                distinct.append(im)
        pixels, grid = self.pixels(distinct)
        return pixels, grid, [slot[id(im)] for im in images]

    def _encode(self, images: list[np.ndarray]) -> Encoded:
        """The vision tower's output for the distinct arrays of ``images``, run once for all of them, with their
        grids and, per array (by ``id``), the index of its distinct image. An image's output depends on that
        image alone (attention within each image), so a merged batch encodes the images of all its forward
        passes in one call."""
        pixels, grid, order = self._pixels(images)
        with self._lock, self.torch.inference_mode():
            enc = self.net.model.get_image_features(pixels.to(self.device),  # type: ignore[attr-defined]
                                                    grid.to(self.device), return_dict=True)  # type: ignore[attr-defined]
        return tuple(enc.pooler_output), grid, {id(im): k for im, k in zip(images, order, strict=True)}

    def _per_row(self, pixels: object, grid: object, order: list[int]) -> object:
        """The rows' ``pixel_values`` from the distinct images' (the image processor works image by image, so
        repeating an image's patches is the same as processing it again)."""
        if order == list(range(len(order))):
            return pixels
        per_image = self.torch.split(pixels, [int(g.prod().item()) for g in grid])  # type: ignore[attr-defined]
        return self.torch.cat([per_image[k] for k in order])

    def _chat_ids(self, text: str) -> tuple[list[int], int]:
        """Token ids of the chat of ``text`` with one ``<|image_pad|>``, and where that token is. A replica sees
        the same few prompt texts over and over (four per question), so they are tokenized once: the tokenizer
        was a third of a step's time on the tiny model, and it is work per request that batching cannot share."""
        got = self._chat_cache.get(text)
        if got is None:
            ids = list(self.tokenizer(qwen_chat(text), add_special_tokens=False)["input_ids"])
            if ids.count(self.image_pad_id) != 1:
                raise BadRequest("the prompt text must not contain the image placeholder token")
            if len(self._chat_cache) >= 4096:
                self._chat_cache.clear()
            got = self._chat_cache[text] = (ids, ids.index(self.image_pad_id))
        return got

    def _row_ids(self, text: str, n_image_tokens: int) -> np.ndarray:
        """The ids of one row: the chat of ``text`` with its ``<|image_pad|>`` repeated ``n_image_tokens`` times
        (built once per prompt text and image size; see :meth:`_inputs`)."""
        key = (text, n_image_tokens)
        got = self._row_cache.get(key)
        if got is None:
            ids, at = self._chat_ids(text)
            if len(self._row_cache) >= 4096:
                self._row_cache.clear()
            got = self._row_cache[key] = np.array(ids[:at] + [self.image_pad_id] * n_image_tokens + ids[at + 1:],
                                                  dtype=np.int64)
        return got

    def _inputs(self, images: list[np.ndarray], texts: list[str], pad_multiple: int | None = None,
                encode_distinct: bool = False, encoded: Encoded | None = None) -> dict[str, object]:
        """The model's inputs for ``(image, text)`` rows, left-padded to the longest row (rounded up to a multiple
        of ``pad_multiple``). ``<|image_pad|>`` is a special token, which the tokenizer splits off before it
        encodes the text around it, so the chat with the image's ``n`` pad tokens encodes as the chat with one,
        that one repeated ``n`` times (tests/scorer/test_scorer_batching.py checks it against the tokenizer).

        ``encode_distinct``: the vision tower runs once per distinct image (its output for an image depends on
        that image alone: attention within each image), and every row gets its image's features
        (``mm_encoder_outputs``) instead of pixels; a step's four prompts share two images, so this halves the
        vision work per step, alone or merged. ``encoded``: :meth:`_encode` of a set of images that holds these."""
        torch = self.torch
        if encode_distinct:
            features, distinct_grid, slots = encoded if encoded is not None else self._encode(images)
            order = [slots[id(im)] for im in images]
        else:
            pixels, distinct_grid, order = self._pixels(images)
        grid = distinct_grid[order]  # type: ignore[index]
        tokens = (grid.prod(1) // (self.merge**2)).tolist()  # type: ignore[attr-defined]
        rows = [self._row_ids(text, n) for text, n in zip(texts, tokens, strict=True)]
        length = max(len(r) for r in rows)
        if pad_multiple:
            length = -(-length // pad_multiple) * pad_multiple
        ids_np = np.full((len(rows), length), int(self.tokenizer.pad_token_id), dtype=np.int64)
        mask_np = np.zeros((len(rows), length), dtype=np.int64)
        for k, r in enumerate(rows):
            ids_np[k, length - len(r):] = r
            mask_np[k, length - len(r):] = 1
        ids_t, mask = torch.from_numpy(ids_np), torch.from_numpy(mask_np)
        out: dict[str, object] = {
            "input_ids": ids_t.to(self.device),
            "attention_mask": mask.to(self.device),
            "mm_token_type_ids": (ids_t == self.image_token_id).to(torch.int32).to(self.device),
            "image_grid_thw": grid.to(self.device),  # type: ignore[attr-defined]
        }
        if not encode_distinct:
            out["pixel_values"] = self._per_row(pixels, distinct_grid, order).to(self.device)  # type: ignore[attr-defined]
            return out
        from transformers.modeling_outputs import BaseModelOutputWithPooling

        rows_features = tuple(features[k] for k in order)
        out["mm_encoder_outputs"] = {"image": BaseModelOutputWithPooling(pooler_output=rows_features)}
        return out

    def answer_from_views(self, images: list[np.ndarray], question: object, choices: list[str]) -> list[float]:
        """Answer memory: the answer distribution over ``choices`` from one prompt holding every
        image of ``images`` (the K most relevant views, :class:`services.mapper.answer_views.AnswerViews`);
        softmax of the next-token logits over the choice letters, as for one view."""
        from PIL import Image

        from eqa.messages import Question, letters

        if not isinstance(question, Question):
            raise BadRequest("answer_from_views needs a Question")
        if not 1 <= len(images) <= prompts.MAX_MEMORY_VIEWS:
            raise BadRequest(f"answer_from_views takes 1..{prompts.MAX_MEMORY_VIEWS} images, got {len(images)}")
        for im in images:
            if not isinstance(im, np.ndarray) or im.ndim != 3 or im.shape[2] != 3 or im.dtype != np.uint8:
                raise BadRequest("every view must be an HxWx3 uint8 image")
        cands = letters(len(choices))
        ids = [self.token_id(c) for c in cands]
        vis = self.image_processor(images=[Image.fromarray(i) for i in images], return_tensors="pt")
        grid = vis["image_grid_thw"]
        chat = qwen_chat_images(prompts.memory_answer_prompt(question, choices, len(images)), len(images))
        parts = chat.split(IMAGE_PAD)
        text = parts[0]
        for k, rest in enumerate(parts[1:]):  # each placeholder expands to its own image's token count
            text += IMAGE_PAD * (int(grid[k].prod().item()) // (self.merge**2)) + rest
        enc = self.tokenizer([text], return_tensors="pt", add_special_tokens=False)
        ids_t = enc["input_ids"]
        inputs = {
            "input_ids": ids_t.to(self.device),
            "attention_mask": enc["attention_mask"].to(self.device),
            "mm_token_type_ids": (ids_t == self.image_token_id).to(self.torch.int32).to(self.device),
            "pixel_values": vis["pixel_values"].to(self.device),
            "image_grid_thw": grid.to(self.device),
        }
        with self._lock, self.torch.inference_mode():
            logits = self.net(**inputs).logits[0, -1, :].float()
        return [float(v) for v in self.torch.softmax(logits[ids], dim=-1).cpu().numpy()]

    def candidate_probs(
        self, rgb: np.ndarray, annotated: np.ndarray | None, queries: list[prompts.Query]
    ) -> list[dict[str, float]]:
        """One forward pass over the batch; softmax of the last logits over each query's candidates."""
        return self.candidate_probs_many([ProbeItem(rgb, annotated, queries)])[0]

    def _forward(self, flat: list[tuple[np.ndarray, prompts.Query]], encoded: Encoded) -> list[dict[str, float]]:
        """One left-padded forward pass over ``(image, query)`` rows, padded to a multiple of
        :data:`PAD_MULTIPLE` tokens; softmax of the last logits over each query's candidates."""
        cand_ids = [[self.token_id(c) for c in q.candidates] for _, q in flat]
        inputs = self._inputs([im for im, _ in flat], [q.text for _, q in flat], pad_multiple=PAD_MULTIPLE,
                             encode_distinct=True, encoded=encoded)
        # the M-RoPE positions the model would compute itself (Qwen2VLModel.get_rope_index), for the whole batch
        # at once instead of row by row in Python
        inputs["position_ids"], _ = mrope_position_ids(inputs["input_ids"], inputs["mm_token_type_ids"],
                                                       inputs["image_grid_thw"], inputs["attention_mask"], self.merge)
        if not bool(inputs["attention_mask"].all()):  # type: ignore[attr-defined]
            # the float mask torch would make of the library's boolean one in every layer, made once (without
            # padding the library passes no mask at all, which is another attention path: left to it)
            inputs["attention_mask"] = {"full_attention": causal_padding_bias(inputs["attention_mask"], self.net.dtype)}
        with self._lock, self.torch.inference_mode():
            logits = self.net(**inputs, use_cache=False, logits_to_keep=1).logits[:, -1, :].float()
        out = []
        for row, (_, q), ids in zip(logits, flat, cand_ids, strict=True):
            p = self.torch.softmax(row[ids], dim=-1).cpu().numpy()
            out.append({c: float(v) for c, v in zip(q.candidates, p, strict=True)})
        return out

    def candidate_probs_many(self, items: list[ProbeItem]) -> list[list[dict[str, float]]]:
        """The queries of several items (the steps of several robots) in as few forward passes as keep every
        item's values exactly what it gets alone.

        A row's logits do not depend on the other rows of its batch, but they do depend on how much left
        padding it carries (the padded positions still enter the attention's reductions). So each item is
        padded as it would be alone -- its longest query, rounded up to a multiple of :data:`PAD_MULTIPLE`
        tokens -- and the items that share that length run as one batch: the rounding is what lets steps with
        questions of different lengths share a forward pass."""
        rows = [[(it.annotated if (q.annotated and it.annotated is not None) else it.rgb, q) for q in it.queries]
                for it in items]
        groups: dict[int, list[int]] = {}
        for i, item_rows in enumerate(rows):
            if item_rows:
                groups.setdefault(self._padded_length(item_rows), []).append(i)
        out: list[list[dict[str, float]]] = [[] for _ in items]
        if not groups:
            return out
        encoded = self._encode([im for item_rows in rows for im, _ in item_rows])
        for members in groups.values():
            probs = self._forward([r for i in members for r in rows[i]], encoded)
            k = 0
            for i in members:
                out[i] = probs[k : k + len(rows[i])]
                k += len(rows[i])
        return out

    def _padded_length(self, rows: list[tuple[np.ndarray, prompts.Query]]) -> int:
        """The token length an item's queries are padded to when they run alone (see _forward)."""
        longest = 0
        for im, q in rows:
            h, w = im.shape[:2]
            # <|image_pad|> is one special token: the chat with one of them, plus the image's other n - 1
            longest = max(longest, len(self._chat_ids(q.text)[0]) + self._image_tokens(h, w) - 1)
        return -(-longest // PAD_MULTIPLE) * PAD_MULTIPLE

    def _image_tokens(self, h: int, w: int) -> int:
        """How many ``<|image_pad|>`` tokens an ``h`` x ``w`` image takes (the image processor's grid)."""
        return self.pixels.tokens(h, w)

    def generate(self, rgb: np.ndarray, text: str, max_new_tokens: int = 48) -> str:
        inputs = self._inputs([rgb], [text])
        with self._lock, self.torch.inference_mode():
            out = self.net.generate(**inputs, max_new_tokens=max_new_tokens, do_sample=False)
        new = out[0, inputs["input_ids"].shape[1] :]  # type: ignore[union-attr]
        return str(self.tokenizer.decode(new, skip_special_tokens=True))

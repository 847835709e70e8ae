"""Build a tiny, randomly initialised Qwen2-VL model directory, offline (tests and bench).

The directory has what a real Qwen2-VL checkpoint has (``config.json``, weights, tokenizer files,
``preprocessor_config.json``), so :class:`services.vlm_scorer.backends.hf.HFBackend` loads it through exactly
the code path a user's downloaded model takes. The tokenizer is a byte-level BPE trained on a few strings of
the scorer's prompts; nothing is downloaded. The weights are random: the probabilities it gives are
meaningless, only their plumbing (candidate tokens, normalisation, batching) is real.

It also has a chat template in the Qwen2-VL format (``chat_template.jinja``, :data:`CHAT_TEMPLATE`: ChatML turns,
each image as ``<|vision_start|><|image_pad|><|vision_end|>``, a default system turn), so an OpenAI-compatible
server that renders chats with the checkpoint's own template (``transformers serve``) can serve it.
"""

from __future__ import annotations

from pathlib import Path

from services.vlm_scorer import prompts

SPECIAL_TOKENS = [
    "<|endoftext|>",
    "<|im_start|>",
    "<|im_end|>",
    "<|vision_start|>",
    "<|vision_end|>",
    "<|image_pad|>",
    "<|video_pad|>",
]


# The Qwen2-VL chat format: ChatML turns; an image part (OpenAI "image_url" or HF "image") becomes the vision
# placeholder the processor expands; a conversation without a system turn gets the default one.
CHAT_TEMPLATE = (
    "{% set image_count = namespace(value=0) %}"
    "{% for message in messages %}"
    "{% if loop.first and message['role'] != 'system' %}"
    "<|im_start|>system\nYou are a helpful assistant.<|im_end|>\n"
    "{% endif %}"
    "<|im_start|>{{ message['role'] }}\n"
    "{% if message['content'] is string %}"
    "{{ message['content'] }}<|im_end|>\n"
    "{% else %}"
    "{% for part in message['content'] %}"
    "{% if part['type'] in ('image', 'image_url') or 'image' in part or 'image_url' in part %}"
    "{% set image_count.value = image_count.value + 1 %}"
    "{% if add_vision_id %}Picture {{ image_count.value }}: {% endif %}"
    "<|vision_start|><|image_pad|><|vision_end|>"
    "{% elif 'text' in part %}"
    "{{ part['text'] }}"
    "{% endif %}"
    "{% endfor %}"
    "<|im_end|>\n"
    "{% endif %}"
    "{% endfor %}"
    "{% if add_generation_prompt %}<|im_start|>assistant\n{% endif %}"
)


def _corpus() -> list[str]:
    texts = [
        prompts.SYSTEM,
        prompts.RELEVANCE.format(question="Is the lamp on?"),
        prompts.LSV.format(question="Where is the sofa?"),
        prompts.GSV.format(question="Where is the sofa?"),
        prompts.ANSWER_INSTRUCTION,
        prompts.PROPOSE.format(question="What color is the rug?", n=4),
        "Yes No Yes No user assistant system",
    ]
    return texts * 3


def build_tiny_qwen2vl(path: str | Path, letters: str | None = None, seed: int = 0) -> Path:
    """Write a tiny random Qwen2-VL (config + BPE tokenizer + image processor) to ``path`` and return it.

    ``letters``: if given, the tokenizer knows only the characters of its training strings plus these
    letters (no full byte alphabet), so other capital letters are *not* single tokens - used to test the
    error for a choice letter the tokenizer cannot produce. By default every byte is a token.
    """
    import torch
    from tokenizers import Tokenizer, decoders, models, pre_tokenizers, trainers
    from transformers import PreTrainedTokenizerFast, Qwen2VLConfig, Qwen2VLForConditionalGeneration
    from transformers.models.qwen2_vl.image_processing_pil_qwen2_vl import Qwen2VLImageProcessorPil

    out = Path(path)
    out.mkdir(parents=True, exist_ok=True)
    tok = Tokenizer(models.BPE())
    tok.pre_tokenizer = pre_tokenizers.ByteLevel(add_prefix_space=False)
    tok.decoder = decoders.ByteLevel()
    corpus = _corpus()
    if letters is None:
        alphabet = pre_tokenizers.ByteLevel.alphabet()
    else:
        corpus = [c.replace("A", "").replace("B", "").replace("C", "").replace("D", "") for c in corpus]
        corpus.append(" ".join(letters))
        alphabet = []
    trainer = trainers.BpeTrainer(vocab_size=400, special_tokens=SPECIAL_TOKENS, initial_alphabet=alphabet)
    tok.train_from_iterator(corpus, trainer)
    tokenizer = PreTrainedTokenizerFast(
        tokenizer_object=tok, eos_token="<|im_end|>", pad_token="<|endoftext|>", padding_side="left"
    )
    tokenizer.chat_template = CHAT_TEMPLATE
    tokenizer.save_pretrained(out)
    (out / "chat_template.jinja").write_text(CHAT_TEMPLATE)  # where a processor looks for it
    ids = {t: tokenizer.convert_tokens_to_ids(t) for t in SPECIAL_TOKENS}

    image_processor = Qwen2VLImageProcessorPil(
        min_pixels=28 * 28 * 4, max_pixels=28 * 28 * 16, patch_size=14, merge_size=2, temporal_patch_size=2
    )
    image_processor.save_pretrained(out)

    config = Qwen2VLConfig(
        text_config={
            "vocab_size": len(tokenizer),
            "hidden_size": 32,
            "intermediate_size": 64,
            "num_hidden_layers": 2,
            "num_attention_heads": 2,
            "num_key_value_heads": 1,
            "max_position_embeddings": 4096,
            "rope_parameters": {"rope_type": "default", "rope_theta": 10000.0, "mrope_section": [2, 3, 3]},
            "bos_token_id": ids["<|endoftext|>"],
            "eos_token_id": ids["<|im_end|>"],
            "pad_token_id": ids["<|endoftext|>"],
        },
        vision_config={
            "depth": 1,
            "embed_dim": 32,
            "hidden_size": 32,
            "mlp_ratio": 2,
            "num_heads": 2,
            "in_chans": 3,
            "patch_size": 14,
            "spatial_merge_size": 2,
            "temporal_patch_size": 2,
        },
        image_token_id=ids["<|image_pad|>"],
        video_token_id=ids["<|video_pad|>"],
        vision_start_token_id=ids["<|vision_start|>"],
        vision_end_token_id=ids["<|vision_end|>"],
    )
    torch.manual_seed(seed)
    model = Qwen2VLForConditionalGeneration(config).eval()
    model.save_pretrained(out)
    return out


# The tiny LLaVA's tokens: SentencePiece-style specials, the ChatML turn markers of CHAT_TEMPLATE and Pixtral's
# image tokens (llama.cpp's Pixtral projector needs [IMG_BREAK] and ends each image with [IMG_END]).
LLAVA_SPECIAL_TOKENS = ["<unk>", "<s>", "</s>", "<|im_start|>", "<|im_end|>", "[IMG]", "[IMG_BREAK]", "[IMG_END]"]
ANSWER_TOKENS = ("A", "B", "C", "D", "Yes", "No")  # what the scorer reads from a top-token list (remote backend)


def build_tiny_pixtral(path: str | Path, seed: int = 0) -> Path:
    """Write a tiny random LLaVA (transformers ``LlavaForConditionalGeneration``: a 3-layer Pixtral vision tower
    of width 32 on 64 px images, 16 px patches, and a 2-layer Llama of width 32) to ``path`` and return it.

    Its tokenizer is a byte-fallback BPE over SentencePiece-style words ("▁" marks a word start), trained on the
    scorer's prompts: llama.cpp's converter reads that kind (the Llama-2 tokenizer.json layout) without the check
    it applies to GPT-2-style BPE tokenizers, whose pre-tokenizer it recognises only by hashing its output on a
    fixed text against known models, so a tokenizer trained here would be refused. Every choice letter and
    Yes/No is one token (with a word-start mark: "▁A", "▁Yes"). The chat template is :data:`TEXT_CHAT_TEMPLATE`
    (llama-server turns each image part into a text marker before rendering). Pixtral rather than Qwen2-VL:
    its converter path keeps the Llama text model (and so this tokenizer), and it has a vision projector that
    llama.cpp converts (``--mmproj``); llama-server refuses image parts without one."""
    import torch
    from tokenizers import Tokenizer, decoders, models, pre_tokenizers, trainers
    from transformers import (
        LlamaConfig,
        LlavaConfig,
        LlavaForConditionalGeneration,
        PixtralVisionConfig,
        PreTrainedTokenizerFast,
    )
    from transformers.models.pixtral.image_processing_pil_pixtral import PixtralImageProcessorPil

    out = Path(path)
    out.mkdir(parents=True, exist_ok=True)
    tok = Tokenizer(models.BPE(unk_token="<unk>", byte_fallback=True, fuse_unk=True))
    tok.pre_tokenizer = pre_tokenizers.Metaspace(replacement="\u2581", prepend_scheme="first", split=True)
    tok.decoder = decoders.Sequence([decoders.Replace("\u2581", " "), decoders.ByteFallback(), decoders.Fuse(),
                                     decoders.Strip(" ", 1, 0)])
    byte_tokens = [f"<0x{i:02X}>" for i in range(256)]  # byte fallback: any text has tokens
    trainer = trainers.BpeTrainer(vocab_size=700, special_tokens=LLAVA_SPECIAL_TOKENS + byte_tokens)
    tok.train_from_iterator(_corpus() + [" ".join(ANSWER_TOKENS) + " A. B. C. D. Yes. No."] * 20, trainer)
    tokenizer = PreTrainedTokenizerFast(tokenizer_object=tok, bos_token="<s>", eos_token="<|im_end|>",
                                        unk_token="<unk>", pad_token="<unk>")
    tokenizer.chat_template = TEXT_CHAT_TEMPLATE
    tokenizer.save_pretrained(out)
    vocab = tokenizer.get_vocab()
    missing = [t for t in ANSWER_TOKENS if t not in vocab and "\u2581" + t not in vocab]
    if missing:
        raise RuntimeError(f"tiny tokenizer lacks the answer tokens {missing}")
    PixtralImageProcessorPil(size={"longest_edge": 64}, patch_size=16).save_pretrained(out)
    text = LlamaConfig(vocab_size=len(tokenizer), hidden_size=32, intermediate_size=64, num_hidden_layers=2,
                       num_attention_heads=2, num_key_value_heads=1, head_dim=16, max_position_embeddings=2048,
                       rms_norm_eps=1e-5, bos_token_id=vocab["<s>"], eos_token_id=vocab["<|im_end|>"])
    # 3 vision layers: the converter maps the projector's linear_1 / linear_2 by layer index, so it needs >= 3
    vision = PixtralVisionConfig(hidden_size=32, intermediate_size=64, num_hidden_layers=3, num_attention_heads=2,
                                 head_dim=16, image_size=64, patch_size=16, num_channels=3, hidden_act="gelu")
    config = LlavaConfig(vision_config=vision, text_config=text, image_token_index=vocab["[IMG]"],
                         projector_hidden_act="gelu", vision_feature_layer=-1,
                         vision_feature_select_strategy="full", multimodal_projector_bias=True)
    torch.manual_seed(seed)
    LlavaForConditionalGeneration(config).eval().save_pretrained(out)
    return out


def build_tiny_llama_gguf(path: str | Path, llama_cpp_dir: str | Path, seed: int = 0) -> tuple[Path, Path]:
    """The tiny LLaVA of :func:`build_tiny_pixtral` as llama.cpp files, converted by llama.cpp's own
    ``convert_hf_to_gguf.py`` from ``llama_cpp_dir`` (a llama.cpp source tree; its ``gguf-py`` is used), run with
    this interpreter (it needs torch, transformers, numpy, sentencepiece): ``path/model.gguf`` (the Llama, F32) and
    ``path/mmproj.gguf`` (the Pixtral projector) for ``llama-server -m model.gguf --mmproj mmproj.gguf``."""
    import subprocess
    import sys

    out = Path(path)
    hf = build_tiny_pixtral(out / "hf", seed=seed)
    convert = Path(llama_cpp_dir) / "convert_hf_to_gguf.py"
    if not convert.is_file():
        raise FileNotFoundError(f"{convert} is missing (is {llama_cpp_dir} a llama.cpp source tree?)")
    files = (out / "model.gguf", out / "mmproj.gguf")
    for target, src, extra in zip(files, (hf, _mmproj_input(hf, out / "hf-mmproj")), ([], ["--mmproj"]), strict=True):
        proc = subprocess.run([sys.executable, str(convert), str(src), "--outtype", "f32", "--outfile", str(target),
                               *extra], capture_output=True, text=True, check=False)
        if proc.returncode != 0 or not target.is_file():
            raise RuntimeError(f"convert_hf_to_gguf.py {' '.join(extra)} failed: {proc.stderr[-1500:]}")
    return files


def _mmproj_input(hf: Path, out: Path) -> Path:
    """The checkpoint the converter's ``--mmproj`` pass reads: the vision tower and projector, and the text
    model's token embedding under a name without ``language_model.``. llama.cpp's Pixtral projector needs the
    [IMG_BREAK] row of that embedding (``v.token_embd.img_break``; llama-server refuses the projector without
    it), and the converter's projector pass drops every tensor named ``language_model.`` before it looks for
    ``embed_tokens.weight``, and a LLaVA checkpoint keeps it as ``language_model.model.embed_tokens``."""
    import shutil

    from safetensors.torch import load_file, save_file

    out.mkdir(parents=True, exist_ok=True)
    for f in hf.iterdir():
        if f.suffix != ".safetensors":
            shutil.copy(f, out / f.name)
    tensors = load_file(hf / "model.safetensors")
    keep = {k: v for k, v in tensors.items() if "language_model." not in k and "lm_head" not in k}
    keep["embed_tokens.weight"] = next(v for k, v in tensors.items() if k.endswith("language_model.model.embed_tokens"
                                                                                     ".weight"))
    save_file(keep, out / "model.safetensors", metadata={"format": "pt"})
    return out


# The ChatML turns of CHAT_TEMPLATE for a text-only server (image parts are dropped; the text is kept).
TEXT_CHAT_TEMPLATE = (
    "{% for message in messages %}"
    "{% if loop.first and message['role'] != 'system' %}"
    "<|im_start|>system\nYou are a helpful assistant.<|im_end|>\n"
    "{% endif %}"
    "<|im_start|>{{ message['role'] }}\n"
    "{% if message['content'] is string %}{{ message['content'] }}"
    "{% else %}{% for part in message['content'] %}{% if 'text' in part %}{{ part['text'] }}{% endif %}"
    "{% endfor %}{% endif %}<|im_end|>\n"
    "{% endfor %}"
    "{% if add_generation_prompt %}<|im_start|>assistant\n{% endif %}"
)

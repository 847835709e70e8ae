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


def build_tiny_llama_gguf(path: str | Path, seed: int = 0) -> Path:
    """Write a tiny random Llama (transformers ``LlamaForCausalLM``, 2 layers of width 32) with the byte-level
    BPE tokenizer and ChatML template of :func:`build_tiny_qwen2vl` as one GGUF file (``gguf`` writer, F32), for
    llama.cpp's server: text only, no vision projector. Returns the file."""
    import json
    import tempfile

    import gguf
    import numpy as np
    import torch
    from transformers import LlamaConfig, LlamaForCausalLM, PreTrainedTokenizerFast

    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        tok_dir = Path(tmp) / "tok"
        tok_dir.mkdir()
        build_tiny_qwen2vl(tok_dir)
        tokenizer = PreTrainedTokenizerFast.from_pretrained(tok_dir)
        spec = json.loads((tok_dir / "tokenizer.json").read_text())
    vocab = len(tokenizer)
    ids = {t: tokenizer.convert_tokens_to_ids(t) for t in SPECIAL_TOKENS}
    cfg = LlamaConfig(vocab_size=vocab, hidden_size=32, intermediate_size=64, num_hidden_layers=2,
                      num_attention_heads=2, num_key_value_heads=1, max_position_embeddings=2048,
                      rms_norm_eps=1e-5, bos_token_id=ids["<|endoftext|>"], eos_token_id=ids["<|im_end|>"])
    torch.manual_seed(seed)
    sd = {k: v.detach().float().numpy() for k, v in LlamaForCausalLM(cfg).state_dict().items()}
    head_dim = cfg.hidden_size // cfg.num_attention_heads

    def permute(w: np.ndarray, heads: int) -> np.ndarray:  # HF's rotary layout -> GGML's (as convert_hf_to_gguf)
        return w.reshape(heads, 2, w.shape[0] // heads // 2, *w.shape[1:]).swapaxes(1, 2).reshape(w.shape)

    w = gguf.GGUFWriter(str(out), "llama")
    w.add_name("eqa-tiny-llama")
    w.add_context_length(cfg.max_position_embeddings)
    w.add_embedding_length(cfg.hidden_size)
    w.add_block_count(cfg.num_hidden_layers)
    w.add_feed_forward_length(cfg.intermediate_size)
    w.add_head_count(cfg.num_attention_heads)
    w.add_head_count_kv(cfg.num_key_value_heads)
    w.add_rope_dimension_count(head_dim)
    w.add_layer_norm_rms_eps(cfg.rms_norm_eps)
    w.add_file_type(gguf.LlamaFileType.ALL_F32)
    w.add_vocab_size(vocab)
    w.add_tokenizer_model("gpt2")
    w.add_tokenizer_pre("default")
    by_id = {i: t for t, i in tokenizer.get_vocab().items()}
    w.add_token_list([by_id[i] for i in range(vocab)])
    special = set(ids.values())
    w.add_token_types([gguf.TokenType.CONTROL if i in special else gguf.TokenType.NORMAL for i in range(vocab)])
    merges = spec["model"]["merges"]
    w.add_token_merges([m if isinstance(m, str) else " ".join(m) for m in merges])
    w.add_bos_token_id(ids["<|endoftext|>"])
    w.add_eos_token_id(ids["<|im_end|>"])
    w.add_pad_token_id(ids["<|endoftext|>"])
    w.add_add_bos_token(False)
    w.add_chat_template(TEXT_CHAT_TEMPLATE)
    names = {"model.embed_tokens.weight": "token_embd.weight", "model.norm.weight": "output_norm.weight",
             "lm_head.weight": "output.weight"}
    per_layer = {"input_layernorm": "attn_norm", "self_attn.q_proj": "attn_q", "self_attn.k_proj": "attn_k",
                 "self_attn.v_proj": "attn_v", "self_attn.o_proj": "attn_output",
                 "post_attention_layernorm": "ffn_norm", "mlp.gate_proj": "ffn_gate", "mlp.up_proj": "ffn_up",
                 "mlp.down_proj": "ffn_down"}
    for name, arr in sd.items():
        if name in names:
            w.add_tensor(names[name], arr)
            continue
        _, _, layer, *rest = name.split(".")
        part = ".".join(rest[:-1])
        if part == "self_attn.q_proj":
            arr = permute(arr, cfg.num_attention_heads)
        elif part == "self_attn.k_proj":
            arr = permute(arr, cfg.num_key_value_heads)
        w.add_tensor(f"blk.{layer}.{per_layer[part]}.weight", np.ascontiguousarray(arr, dtype=np.float32))
    w.write_header_to_file()
    w.write_kv_data_to_file()
    w.write_tensors_to_file()
    w.close()
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

"""The tiny random Llama as GGUF (services/vlm_scorer/tiny.py), read back with the ``gguf`` reader: what llama.cpp's
server needs to load it (architecture and shape keys, every tensor of each layer, the BPE vocabulary with its
merges and special tokens, the ChatML template)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def test_tiny_llama_gguf_has_what_llama_cpp_loads(tmp_path: Path) -> None:
    import gguf

    from services.vlm_scorer.tiny import SPECIAL_TOKENS, build_tiny_llama_gguf

    path = build_tiny_llama_gguf(tmp_path / "tiny.gguf")
    r = gguf.GGUFReader(str(path))

    def value(key: str) -> object:
        f = r.fields[key]
        if f.types[0] == gguf.GGUFValueType.ARRAY:
            return [f.parts[i].tobytes().decode() if f.types[-1] == gguf.GGUFValueType.STRING else f.parts[i][0]
                    for i in f.data]
        part = f.parts[f.data[0]]
        return part.tobytes().decode() if f.types[0] == gguf.GGUFValueType.STRING else part[0]

    assert value("general.architecture") == "llama" and value("llama.block_count") == 2
    assert value("llama.embedding_length") == 32 and value("llama.attention.head_count_kv") == 1
    names = {t.name for t in r.tensors}
    per_layer = ("attn_norm", "attn_q", "attn_k", "attn_v", "attn_output", "ffn_norm", "ffn_gate", "ffn_up",
                 "ffn_down")
    assert names == {"token_embd.weight", "output_norm.weight", "output.weight"} | {
        f"blk.{i}.{p}.weight" for i in range(2) for p in per_layer}
    assert all(t.tensor_type == gguf.GGMLQuantizationType.F32 and np.isfinite(t.data).all() for t in r.tensors)
    tokens = value("tokenizer.ggml.tokens")
    assert len(tokens) == len(set(tokens)) == value("llama.vocab_size")  # type: ignore[arg-type]
    assert r.get_tensor(0).data.shape == (len(tokens), 32)
    assert {"A", "B", "C", "D", "Yes", "No"} <= set(tokens) and set(SPECIAL_TOKENS) <= set(tokens)
    assert value("tokenizer.ggml.model") == "gpt2" and len(value("tokenizer.ggml.merges")) > 0  # type: ignore[arg-type]
    assert tokens[value("tokenizer.ggml.eos_token_id")] == "<|im_end|>"  # type: ignore[index]
    assert "<|im_start|>assistant" in str(value("tokenizer.chat_template"))

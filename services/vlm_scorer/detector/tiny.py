"""Build a tiny, randomly initialised OWL-ViT detector directory, offline (tests and bench).

The directory has what a real OWL-ViT checkpoint has (``config.json``, weights, tokenizer files,
``preprocessor_config.json``), so :class:`services.vlm_scorer.detector.hf.HFDetector` loads it through the
code path a downloaded model takes. The tokenizer is a byte-level BPE trained on a few class names; nothing
is downloaded. The weights are random: its boxes and scores are meaningless, only the plumbing is real.
"""

from __future__ import annotations

from pathlib import Path

SPECIAL = ["<|startoftext|>", "<|endoftext|>"]
UNUSED = "<unused>"  # id 0: OWL-ViT treats a query whose first token id is 0 as padding
WORDS = "a photo of mug table chair sofa bed counter sink towel lamp cup box vase plant cabinet shelf"


def build_tiny_owlvit(path: str | Path, seed: int = 0) -> Path:
    """Write a tiny random OWL-ViT (config + BPE tokenizer + image processor) to ``path`` and return it."""
    import torch
    from tokenizers import Tokenizer, decoders, models, pre_tokenizers, processors, trainers
    from transformers import OwlViTConfig, OwlViTForObjectDetection, PreTrainedTokenizerFast
    from transformers.models.owlvit.image_processing_pil_owlvit import OwlViTImageProcessorPil

    out = Path(path)
    out.mkdir(parents=True, exist_ok=True)
    tok = Tokenizer(models.BPE())
    tok.pre_tokenizer = pre_tokenizers.ByteLevel(add_prefix_space=False)
    tok.decoder = decoders.ByteLevel()
    trainer = trainers.BpeTrainer(
        vocab_size=300, special_tokens=[UNUSED, *SPECIAL], initial_alphabet=pre_tokenizers.ByteLevel.alphabet()
    )
    tok.train_from_iterator([WORDS] * 3, trainer)
    bos, eos = tok.token_to_id(SPECIAL[0]), tok.token_to_id(SPECIAL[1])
    tok.post_processor = processors.TemplateProcessing(
        single=f"{SPECIAL[0]} $A {SPECIAL[1]}", special_tokens=[(SPECIAL[0], bos), (SPECIAL[1], eos)]
    )
    tokenizer = PreTrainedTokenizerFast(
        tokenizer_object=tok, bos_token=SPECIAL[0], eos_token=SPECIAL[1], pad_token=SPECIAL[1]
    )
    tokenizer.save_pretrained(out)
    OwlViTImageProcessorPil(size={"height": 64, "width": 64}, crop_size={"height": 64, "width": 64}).save_pretrained(
        out
    )
    config = OwlViTConfig(
        text_config={
            "vocab_size": len(tokenizer),
            "hidden_size": 32,
            "intermediate_size": 64,
            "num_hidden_layers": 1,
            "num_attention_heads": 2,
            "max_position_embeddings": 16,
            "bos_token_id": bos,
            "eos_token_id": eos,
            "pad_token_id": eos,
        },
        vision_config={
            "hidden_size": 32,
            "intermediate_size": 64,
            "num_hidden_layers": 1,
            "num_attention_heads": 2,
            "image_size": 64,
            "patch_size": 16,
        },
        projection_dim=32,
    )
    torch.manual_seed(seed)
    OwlViTForObjectDetection(config).eval().save_pretrained(out)
    return out

"""Per-target value scores for HELIOS's layered value map (paper 3.1.2): the image-text score of each view
for the prompt "Seems like there is a (object) ahead", one layer per search target (pick and place location).

The paper scores this with BLIP-2's image-text matching; here it goes through the scorer pool's backend:

* a next-token model (``hf``, ``remote``): the prompt followed by "Answer Yes or No." and P(Yes) normalised
  over Yes / No, like the relevance and GSV queries (:class:`services.vlm_scorer.backends.base.ModelBackend`);
* the simulated perception model (``oracle``, not a VLM): P(Yes) from what the frame shows - a visible
  instance of the target raises it by its view quality (pixel share and distance, the same rule as the
  oracle's questions), the commonsense prior of the rooms in view for the target sets the base, plus noise
  seeded by (seed, episode, step, target).
"""

from __future__ import annotations

import zlib

import numpy as np

from eqa.messages import ValueRequest
from services.vlm_scorer import commonsense as cs
from services.vlm_scorer import prompts
from services.vlm_scorer.backends.base import Backend, BadRequest, ModelBackend, normalise
from services.vlm_scorer.backends.oracle import OracleBackend

PROMPT = "Seems like there is a {target} ahead."
QUESTION = PROMPT + " Answer Yes or No."


def validate_value_request(req: ValueRequest) -> None:
    rgb = req.rgb
    if not isinstance(rgb, np.ndarray) or rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise BadRequest(f"rgb must be an HxWx3 uint8 image, got {getattr(rgb, 'shape', None)}")
    if any(not t.strip() for t in req.targets):
        raise BadRequest("a value target is blank")
    h, w = rgb.shape[:2]
    if req.instances is not None and req.instances.shape != (h, w):
        raise BadRequest(f"instances has shape {req.instances.shape}, expected {(h, w)} like rgb")
    if req.depth is not None and req.depth.shape != (h, w):
        raise BadRequest(f"depth has shape {req.depth.shape}, expected {(h, w)} like rgb")


def target_values(backend: Backend, req: ValueRequest) -> list[float]:
    """P(Yes) of "Seems like there is a (target) ahead" for each target of ``req``."""
    validate_value_request(req)
    if isinstance(backend, OracleBackend):
        return [_oracle_value(backend, req, t) for t in req.targets]
    if isinstance(backend, ModelBackend):
        queries = [prompts.Query("value", QUESTION.format(target=t.strip()), prompts.YES_NO) for t in req.targets]
        raw = backend.candidate_probs(req.rgb, None, queries)
        return [normalise(r, prompts.YES_NO)[0] for r in raw]
    raise BadRequest(f"the {backend.name} backend cannot score value prompts")


def _oracle_value(backend: OracleBackend, req: ValueRequest, target: str) -> float:
    cat = cs.norm_category(target)
    h, w = req.rgb.shape[:2]
    best_q = 0.0
    rooms: set[str] = set()
    for lab in req.labels:
        if lab.room_kind:
            rooms.add(lab.room_kind)
        if cs.norm_category(lab.category) != cat and cs.norm_category(lab.category).split(" ")[-1] != cat:
            continue
        pixels, dist = lab.pixels, None
        if req.instances is not None:
            mask = req.instances == lab.id
            pixels = int(mask.sum())
            if req.depth is not None and pixels:
                d = req.depth[mask]
                d = d[np.isfinite(d) & (d > 0)]
                dist = float(np.median(d)) if d.size else None
        best_q = max(best_q, backend.view_quality(pixels / float(h * w), dist))
    prior = max((cs.prior(cat, rk) for rk in rooms), default=cs.UNKNOWN_PRIOR)
    rng = np.random.default_rng([req.seed, zlib.crc32(req.draw_key.encode()), req.step, zlib.crc32(cat.encode())])
    value = 0.1 + 0.4 * prior + 0.45 * best_q + rng.normal(0.0, 0.05)
    return float(np.clip(value, 0.01, 0.99))

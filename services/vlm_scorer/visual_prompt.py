"""Visual prompting (Explore-EQA section IV-C, Fig. 3): letters in circles drawn at the prompt points.

Each point ``p`` in ``P`` is drawn as a white disc with a black outline and its black letter, sized to the
image (radius ~ 4.5 % of the short side, at least 7 px) so the letters stay legible to a model at any
resolution. Points outside the image are clamped to its border (the letter stays visible).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from eqa.messages import PromptPoint


@lru_cache(maxsize=16)
def _font(size: int) -> ImageFont.ImageFont | ImageFont.FreeTypeFont:
    try:
        return ImageFont.load_default(size=size)
    except Exception:  # Pillow built without FreeType: the bitmap font
        return ImageFont.load_default()


def marker_radius(height: int, width: int) -> int:
    return max(7, round(0.045 * min(height, width)))


def annotate(rgb: np.ndarray, points: list[PromptPoint]) -> np.ndarray:
    """A copy of ``rgb`` (HxWx3 uint8) with each point's letter in a circle at its pixel ``(u, v)``."""
    img = Image.fromarray(np.ascontiguousarray(rgb))
    draw = ImageDraw.Draw(img)
    h, w = rgb.shape[:2]
    r = marker_radius(h, w)
    font = _font(max(8, int(r * 1.5)))
    for p in points:
        u = float(np.clip(p.u, r, w - 1 - r)) if w > 2 * r else w / 2
        v = float(np.clip(p.v, r, h - 1 - r)) if h > 2 * r else h / 2
        draw.ellipse(
            (u - r, v - r, u + r, v + r), fill=(255, 255, 255), outline=(0, 0, 0), width=max(1, r // 6)
        )
        if isinstance(font, ImageFont.FreeTypeFont):
            draw.text((u, v), p.label, fill=(0, 0, 0), font=font, anchor="mm")
        else:  # bitmap font: no anchors, centre by its box
            left, top, right, bottom = draw.textbbox((0, 0), p.label, font=font)
            draw.text((u - (right - left) / 2, v - (bottom - top) / 2), p.label, fill=(0, 0, 0), font=font)
    return np.asarray(img, dtype=np.uint8).copy()

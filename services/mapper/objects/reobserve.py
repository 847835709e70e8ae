"""The re-observation mask (HELIOS appendix 6.1, "Re-observing previously detected parts of the scene").

Render the layer's depth, keep the pixels whose measured depth lies within ``reobserve_depth_m`` (0.5 m) of
it, close small holes with a morphological closing, and update the Gaussians only through the rendering inside
this mask. A Gaussian behind an occluder is then left alone (the measured depth is the occluder's), while a
Gaussian in plain view whose object the detector does not report gets ``other`` evidence: not detecting an
object counts against it.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F  # noqa: N812


def dilate(mask: torch.Tensor, radius: int) -> torch.Tensor:
    """Binary dilation with a (2r+1)^2 square."""
    if radius <= 0:
        return mask
    x = mask[None, None].float()
    return F.max_pool2d(x, 2 * radius + 1, stride=1, padding=radius)[0, 0] > 0.5


def erode(mask: torch.Tensor, radius: int) -> torch.Tensor:
    """Binary erosion with a (2r+1)^2 square (pixels outside the image count as set: no border effect)."""
    if radius <= 0:
        return mask
    return ~dilate(~mask, radius)


def close(mask: torch.Tensor, radius: int) -> torch.Tensor:
    """Morphological closing (dilate then erode): fills holes narrower than 2r+1 pixels."""
    return erode(dilate(mask, radius), radius)


def reobservation_mask(
    measured: torch.Tensor, rendered: torch.Tensor, max_diff_m: float = 0.5, close_px: int = 2
) -> torch.Tensor:
    """Pixels where the layer is seen again: ``|measured - rendered| < max_diff_m`` where both are defined
    (> 0), closed with radius ``close_px``, and never where nothing was measured."""
    ok = (measured > 0) & (rendered > 0) & ((measured - rendered).abs() < max_diff_m)
    out = torch.zeros_like(ok)
    y0, y1, x0, x1 = bbox(ok, 2 * close_px)
    if y0 < y1:  # the closing only changes pixels within 2r of the set ones: work on that box
        out[y0:y1, x0:x1] = close(ok[y0:y1, x0:x1], close_px)
    return out & (measured > 0)


def bbox(mask: torch.Tensor, pad: int) -> tuple[int, int, int, int]:
    """``(y0, y1, x0, x1)`` of the set pixels grown by ``pad`` and clipped to the image; empty as (0, 0, 0, 0)."""
    rows, cols = torch.nonzero(mask.any(1)).squeeze(1), torch.nonzero(mask.any(0)).squeeze(1)
    if rows.numel() == 0:
        return 0, 0, 0, 0
    h, w = mask.shape
    return (max(int(rows[0]) - pad, 0), min(int(rows[-1]) + pad + 1, h),
            max(int(cols[0]) - pad, 0), min(int(cols[-1]) + pad + 1, w))

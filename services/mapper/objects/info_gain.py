"""Information gain (HELIOS Eq. 6), the optimistic information gain (Eq. 12) and Psi' (Eq. 11).

IG(theta_n, Y | P) = H(theta_n) - H(theta_n | P, Y)  (Eq. 6), H the Dirichlet entropy of Eq. 5, the
posterior found by applying the update of Eq. 3 to a copy.

Optimistic views (appendix "Expanded explanation of how we calculate information gain"): for an instance
o_i and class o, a copy of its Gaussians gets class probabilities one-hot on o; the layer (every Gaussian,
so that occlusion is kept; the others with their expected class probabilities) is rendered at each pose P
and the per-pixel argmax of the rendered class image is Y* (pixels the layer does not cover are ``other``).
A copy of the instance's concentrations is updated with Eq. 3 from Y* pose after pose; then

    IG_o(o_i | P, Y*) = sum_{n in o_i} H(theta_n) - H(theta_n | P, Y*)        (Eq. 12)
    Psi'_o(o_i) = S'_o - alpha_cs U'_o                                          (Eq. 11)

with S', U' the class score and uncertainty of the updated copy.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from services.mapper.objects import dirichlet, splat
from services.mapper.objects.config import ObjectLayerConfig
from services.mapper.objects.scores import class_scores


def information_gain(gamma_before: torch.Tensor, gamma_after: torch.Tensor) -> torch.Tensor:
    """Eq. 6 per Gaussian: H(before) - H(after).

    Adding evidence to a Gaussian's most likely class lowers the Dirichlet entropy (IG >= 0; tested), as
    does evidence in proportion to its current expectation. Evidence for a minority class can raise it (the
    belief moves towards the middle of the simplex), so the IG of a contradicting view can be negative."""
    return dirichlet.entropy(gamma_before) - dirichlet.entropy(gamma_after)


@dataclass
class Optimistic:
    ig: float  # Eq. 12, summed over the instance's Gaussians
    psi_prime: float  # Eq. 11
    s_prime: float
    u_prime: float
    pixels: int  # pixels of Y* showing the class (optimistic_each: inside the instance's box; 0: not visible)


def _seen_as(gamma: torch.Tensor, members: torch.Tensor, cls: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Eq. 11's optimistic assumption: render colours with the instance's Gaussians ``members`` one-hot at class
    ``cls`` (the others at their expected class probabilities), and each Gaussian's index within the instance
    (-1 outside it)."""
    colors = dirichlet.expectation(gamma).clone()
    onehot = torch.zeros(gamma.shape[1], device=gamma.device)
    onehot[cls] = 1.0
    colors[members] = onehot
    local = torch.full((gamma.shape[0],), -1, dtype=torch.long, device=gamma.device)
    local[members] = torch.arange(members.numel(), device=gamma.device)
    return colors, local


def _labels(r: splat.Splats, valid_acc: float) -> torch.Tensor:
    """Per pixel (flattened) the rendered class Y*: the argmax colour where enough opacity accumulated, else
    ``other`` (the last class)."""
    assert r.channels is not None
    other = r.channels.shape[-1] - 1
    return torch.where(r.acc >= valid_acc, r.channels.argmax(-1), torch.full_like(r.acc, other).long()).reshape(-1)


def optimistic_views(
    means: torch.Tensor,
    sigma: torch.Tensor,
    opacity: torch.Tensor,
    gamma: torch.Tensor,
    members: torch.Tensor,
    cls: int,
    poses: list[torch.Tensor],
    K: torch.Tensor,
    height: int,
    width: int,
    config: ObjectLayerConfig,
    pixel_weight: float,
) -> Optimistic:
    """Eq. 11 and 12 for the instance made of Gaussians ``members`` (indices) seen as class ``cls`` from the
    camera-to-world ``poses`` (intrinsics ``K`` at ``height x width``). ``pixel_weight``: Eq. 3's w at this
    resolution."""
    colors, local = _seen_as(gamma, members, cls)
    g0 = gamma[members].clone()
    g = g0.clone()
    shown = 0
    for pose in poses:
        r = splat.render(
            means, sigma, opacity, pose, K, height, width, colors=colors,
            max_radius_px=config.max_splat_radius_px, min_alpha=config.min_alpha, max_alpha=config.max_alpha,
            min_transmittance=config.min_transmittance, valid_acc=config.valid_acc,
        )
        y = _labels(r, config.valid_acc)
        shown += int((y == cls).sum())
        sel = local[r.gauss] >= 0
        g = dirichlet.update(g, local[r.gauss[sel]], r.kappa[sel], y[r.pixel[sel]], config.alpha_cpa, pixel_weight)
    ig = float(information_gain(g0, g).sum())
    s, u, psi = class_scores(g, config.alpha_cs)
    return Optimistic(ig, float(psi[cls]), float(s[cls]), float(u[cls]), shown)


def optimistic_each(
    means: torch.Tensor,
    sigma: torch.Tensor,
    opacity: torch.Tensor,
    gamma: torch.Tensor,
    members: torch.Tensor,
    cls: int,
    poses: list[torch.Tensor],
    K: torch.Tensor,
    height: int,
    width: int,
    config: ObjectLayerConfig,
    pixel_weight: float,
) -> list[Optimistic]:
    """:func:`optimistic_views` of each pose *alone* (Eq. 11, 12 of one gaze point each; the local search scores
    every gaze point this way), all poses in one vectorised render (:func:`splat.render_views`) restricted to the
    instance's box in each view -- the same numbers as one :func:`optimistic_views` call per pose (tested)."""
    if not poses:
        return []
    n_views = len(poses)
    n_classes = gamma.shape[1]
    m = int(members.numel())
    colors, local = _seen_as(gamma, members, cls)
    r = splat.render_views(
        means, sigma, opacity, torch.stack([p.to(means.device, torch.float32) for p in poses]), K, height, width,
        colors=colors, max_radius_px=config.max_splat_radius_px, min_alpha=config.min_alpha,
        max_alpha=config.max_alpha, min_transmittance=config.min_transmittance, valid_acc=config.valid_acc,
        roi_of=members,
    )
    y = _labels(r, config.valid_acc)
    hw = height * width
    shown = torch.zeros(n_views, dtype=torch.long, device=gamma.device).index_add_(
        0, torch.arange(n_views * hw, device=gamma.device) // hw, (y == cls).long())
    g0 = gamma[members].clone()
    sel = local[r.gauss] >= 0
    view = r.pixel[sel] // hw
    # one copy of the instance's concentrations per view, updated with that view's pairs only
    g = dirichlet.update(g0.repeat(n_views, 1), view * m + local[r.gauss[sel]], r.kappa[sel], y[r.pixel[sel]],
                         config.alpha_cpa, pixel_weight).view(n_views, m, n_classes)
    out = []
    for v in range(n_views):
        ig = float(information_gain(g0, g[v]).sum())
        s, u, psi = class_scores(g[v], config.alpha_cs)
        out.append(Optimistic(ig, float(psi[cls]), float(s[cls]), float(u[cls]), int(shown[v])))
    return out

"""Dirichlet class beliefs of the Gaussians (HELIOS Eq. 2-5, after Wilson et al. 2024 and Lin 2016).

Each Gaussian n has concentrations gamma_n (C,), one per class; the classes are the task's classes plus
``other`` (pixels no task-class detection covers), so *not* detecting an object where the layer expects it
is evidence against its class.
"""

from __future__ import annotations

import torch


def update(
    gamma: torch.Tensor,
    gauss: torch.Tensor,
    kappa: torch.Tensor,
    pixel_class: torch.Tensor,
    alpha_cpa: float,
    pixel_weight: float = 1.0,
) -> torch.Tensor:
    """Eq. 3 with the appendix's scaling: gamma_n^c += alpha_cpa * w * sum_i y_i^c kappa(p_i, x~_n).

    ``gauss``, ``kappa``: the contributing (Gaussian, pixel) pairs of a render (Eq. 1); ``pixel_class``: the
    class index y_i of each pair's pixel (one-hot y); ``w`` = ``pixel_weight`` (see
    ``ObjectLayerConfig.pixel_weight``). Returns a new tensor; ``gamma`` is not changed."""
    out = gamma.clone()
    flat = gauss * gamma.shape[1] + pixel_class
    add = torch.zeros(gamma.numel(), dtype=gamma.dtype, device=gamma.device)
    add.index_add_(0, flat, kappa.to(gamma.dtype) * float(alpha_cpa * pixel_weight))
    return out + add.view_as(gamma)


def expectation(gamma: torch.Tensor) -> torch.Tensor:
    """Eq. 4: E[theta_n^c] = gamma_n^c / sum_j gamma_n^j."""
    return gamma / gamma.sum(-1, keepdim=True)


def variance(gamma: torch.Tensor) -> torch.Tensor:
    """Eq. 4: Var[theta_n^c] = E[theta_n^c] (1 - E[theta_n^c]) / (1 + sum_j gamma_n^j)."""
    e = expectation(gamma)
    return e * (1.0 - e) / (1.0 + gamma.sum(-1, keepdim=True))


def entropy(gamma: torch.Tensor) -> torch.Tensor:
    """Eq. 5: H = log B(gamma) + (T - C) psi(T) - sum_c (gamma^c - 1) psi(gamma^c), T = sum_c gamma^c.

    (Differential entropy of the Dirichlet; log B(gamma) = sum_c lgamma(gamma^c) - lgamma(T).) Computed in
    float64; returns one value per row."""
    g = gamma.double()
    total = g.sum(-1)
    c = g.shape[-1]
    log_b = torch.lgamma(g).sum(-1) - torch.lgamma(total)
    return (log_b + (total - c) * torch.digamma(total) - ((g - 1.0) * torch.digamma(g)).sum(-1)).to(gamma.dtype)

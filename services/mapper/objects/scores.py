"""Per-instance class, class score, uncertainty and the uncertainty-weighted object score (HELIOS Eq. 7).

For an instance o_i (its Gaussians theta_n):

* class: mode over its Gaussians of argmax_c E[theta_n^c] (ties: the lower class index);
* S_c = mean_n E[theta_n^c];  U_c = mean_n sqrt(Var[theta_n^c])  (Eq. 4);
* Psi_c = S_c - alpha_cs U_c  (Eq. 7), the lower alpha_cs-sigma estimate; Psi_c <= S_c <= 1 and, since
  sqrt(Var) <= sqrt(E(1-E)) <= 1/2, Psi_c >= -alpha_cs / 2.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from services.mapper.objects import dirichlet


@dataclass
class InstanceScores:
    instance_id: int
    cls: int  # index into the layer's classes
    S: list[float]  # per class
    U: list[float]
    psi: list[float]
    centre: tuple[float, float, float]
    extent: tuple[float, float, float]
    n_gaussians: int


def class_scores(gamma: torch.Tensor, alpha_cs: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(S, U, Psi) per class (C,) for one instance's concentrations ``gamma`` (n, C) (Eq. 4, 7)."""
    s = dirichlet.expectation(gamma).mean(0)
    u = dirichlet.variance(gamma).sqrt().mean(0)
    return s, u, s - alpha_cs * u


def instance_class(gamma: torch.Tensor) -> int:
    """mode_n argmax_c E[theta_n^c] (ties broken towards the lower class index)."""
    votes = torch.bincount(dirichlet.expectation(gamma).argmax(1), minlength=gamma.shape[1])
    return int(votes.argmax())


def summarise(
    means: torch.Tensor, sigma: torch.Tensor, gamma: torch.Tensor, instance: torch.Tensor, alpha_cs: float
) -> list[InstanceScores]:
    """One :class:`InstanceScores` per instance label >= 0, in label order."""
    out: list[InstanceScores] = []
    labels = instance[instance >= 0]
    if labels.numel() == 0:
        return out
    uniq, inv = torch.unique(labels, return_inverse=True)
    sel = torch.nonzero(instance >= 0).squeeze(1)
    k, c = len(uniq), gamma.shape[1]
    e = dirichlet.expectation(gamma[sel]).double()
    sd = dirichlet.variance(gamma[sel]).sqrt().double()
    count = torch.bincount(inv, minlength=k).double()
    s = torch.zeros(k, c, dtype=torch.float64, device=gamma.device).index_add_(0, inv, e) / count[:, None]
    u = torch.zeros(k, c, dtype=torch.float64, device=gamma.device).index_add_(0, inv, sd) / count[:, None]
    votes = torch.zeros(k * c, dtype=torch.float64, device=gamma.device)
    votes.index_add_(0, inv * c + e.argmax(1), torch.ones_like(inv, dtype=torch.float64))
    cls = votes.view(k, c).argmax(1)
    m = means[sel].double()
    pad = sigma[sel].double()[:, None]
    big = torch.finfo(torch.float64).max
    lo = torch.full((k, 3), big, dtype=torch.float64, device=gamma.device)
    hi = torch.full((k, 3), -big, dtype=torch.float64, device=gamma.device)
    lo = lo.scatter_reduce(0, inv[:, None].expand(-1, 3), m - pad, "amin")
    hi = hi.scatter_reduce(0, inv[:, None].expand(-1, 3), m + pad, "amax")
    centre, extent = (lo + hi) / 2, hi - lo
    psi = s - alpha_cs * u
    for i in range(k):
        out.append(
            InstanceScores(
                int(uniq[i]),
                int(cls[i]),
                s[i].tolist(),
                u[i].tolist(),
                psi[i].tolist(),
                tuple(centre[i].tolist()),  # type: ignore[arg-type]
                tuple(extent[i].tolist()),  # type: ignore[arg-type]
                int(count[i]),
            )
        )
    return out

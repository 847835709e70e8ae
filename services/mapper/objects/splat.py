"""The alpha-blending splat renderer of the object layer (HELIOS Eq. 1, after 3DGS, Kerbl et al. 2023).

Each 3D Gaussian (mean mu, isotropic sigma, opacity alpha) is projected to a 2D Gaussian with the EWA
Jacobian of the pinhole projection (Sigma2D = J Sigma J^T + 0.3 I, as 3DGS), cut at 3 sigma (or
``max_radius_px``). For every pixel the overlapping splats are sorted by depth and blended front to back:

    alpha~_n(p) = min(max_alpha, alpha_n exp(-1/2 (p - mu~_n)^T Sigma2D_n^-1 (p - mu~_n)))
    kappa(p, x~_n) = alpha~_n(p) prod_{j<n} (1 - alpha~_j(p))                                  (Eq. 1)

Contributions with alpha~ < ``min_alpha`` are skipped and blending stops where the transmittance falls below
``min_transmittance`` (3DGS). No autograd: nothing is trained; the kappas themselves are the output the
Dirichlet update (Eq. 3) needs, alongside the rendered images Q(p) = sum_n c_n kappa(p, x~_n) for depth,
class expectation and uncertainty.

Implementation: all (Gaussian, pixel) pairs are listed at once (Gaussians grouped by radius so each group
expands its own square of offsets), sorted by (pixel, depth), and the exclusive product of (1 - alpha) per
pixel is an exclusive segmented cumulative sum of log(1 - alpha) in float64. Vectorised torch: the same code
on CPU and CUDA.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

EWA_DILATION = 0.3  # px^2 added to the 2D covariance (3DGS low-pass filter)
NEAR_M = 0.05


@dataclass
class Splats:
    """The output of one render at ``height x width``.

    ``gauss``, ``pixel``, ``kappa``: the contributing pairs (Gaussian index, flat pixel index, Eq. 1 weight).
    ``acc``: accumulated alpha sum_n kappa per pixel. ``depth``: kappa-weighted depth / acc where
    ``acc >= valid_acc``, else 0. ``channels``: sum_n c_n kappa per pixel for the given colours (H, W, K) or
    None.
    """

    height: int
    width: int
    gauss: torch.Tensor
    pixel: torch.Tensor
    kappa: torch.Tensor
    acc: torch.Tensor
    depth: torch.Tensor
    channels: torch.Tensor | None

    def image(self, values: torch.Tensor) -> torch.Tensor:
        """Q(p) = sum_n values_n kappa(p, x~_n) for per-Gaussian ``values`` (N,) or (N, K) -> (H, W[, K])."""
        hw = self.height * self.width
        if values.ndim == 1:
            out = torch.zeros(hw, dtype=values.dtype, device=values.device)
            out.index_add_(0, self.pixel, values[self.gauss] * self.kappa.to(values.dtype))
            return out.view(self.height, self.width)
        out = torch.zeros(hw, values.shape[1], dtype=values.dtype, device=values.device)
        out.index_add_(0, self.pixel, values[self.gauss] * self.kappa.to(values.dtype)[:, None])
        return out.view(self.height, self.width, values.shape[1])


def world_to_camera(camera_pose: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(R, t) of the world-to-camera transform of a 4x4 camera-to-world pose (OpenCV convention)."""
    r = camera_pose[:3, :3].T
    return r, -(r @ camera_pose[:3, 3])


def render(
    means: torch.Tensor,
    sigma: torch.Tensor,
    opacity: torch.Tensor,
    camera_pose: torch.Tensor,
    K: torch.Tensor,
    height: int,
    width: int,
    colors: torch.Tensor | None = None,
    max_radius_px: int = 8,
    min_alpha: float = 1.0 / 255.0,
    max_alpha: float = 0.99,
    min_transmittance: float = 1e-4,
    valid_acc: float = 0.5,
) -> Splats:
    """Render the Gaussians ``means`` (N,3) world, ``sigma`` (N,) m, ``opacity`` (N,) with Eq. 1 (see module)."""
    dev = means.device
    f32 = torch.float32
    hw = height * width
    empty_l = torch.zeros(0, dtype=torch.long, device=dev)
    acc = torch.zeros(hw, dtype=f32, device=dev)
    n = means.shape[0]
    if n == 0:
        ch = torch.zeros(height, width, colors.shape[1], dtype=f32, device=dev) if colors is not None else None
        z = torch.zeros(height, width, dtype=f32, device=dev)
        return Splats(height, width, empty_l, empty_l, torch.zeros(0, dtype=f32, device=dev), z.clone(), z, ch)
    R, t = world_to_camera(camera_pose.to(dev, f32))
    xc = means.to(f32) @ R.T + t
    z = xc[:, 2]
    fx, fy, cx, cy = (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
    zs = z.clamp(min=NEAR_M)
    u = fx * xc[:, 0] / zs + cx
    v = fy * xc[:, 1] / zs + cy
    j11, j22 = fx / zs, fy / zs
    j13, j23 = -fx * xc[:, 0] / zs**2, -fy * xc[:, 1] / zs**2
    s2 = sigma.to(f32) ** 2
    a = s2 * (j11**2 + j13**2) + EWA_DILATION
    b = s2 * (j13 * j23)
    c = s2 * (j22**2 + j23**2) + EWA_DILATION
    det = (a * c - b * b).clamp(min=1e-12)
    ia, ib, ic = c / det, -b / det, a / det
    lam = 0.5 * (a + c) + torch.sqrt((0.25 * (a - c) ** 2 + b * b).clamp(min=0))
    radius = torch.ceil(3.0 * torch.sqrt(lam)).clamp(max=max_radius_px).long()
    ok = (
        (z > NEAR_M)
        & (u + radius >= 0)
        & (u - radius <= width - 1)
        & (v + radius >= 0)
        & (v - radius <= height - 1)
        & torch.isfinite(u)
        & torch.isfinite(v)
    )
    idx = torch.nonzero(ok).squeeze(1)
    gs, ps, als = [], [], []
    ui, vi = torch.round(u).long(), torch.round(v).long()
    for r in torch.unique(radius[idx]).tolist():
        sel = idx[radius[idx] == r]
        off = torch.arange(-r, r + 1, device=dev)
        dy, dx = torch.meshgrid(off, off, indexing="ij")
        disc = dx * dx + dy * dy <= r * r + r  # the disc of radius r (the square's corners are past 3 sigma)
        dx, dy = dx[disc], dy[disc]
        px = ui[sel, None] + dx[None, :]
        py = vi[sel, None] + dy[None, :]
        ddx = px.to(f32) - u[sel, None]
        ddy = py.to(f32) - v[sel, None]
        power = -0.5 * (ia[sel, None] * ddx * ddx + 2 * ib[sel, None] * ddx * ddy + ic[sel, None] * ddy * ddy)
        alpha = (opacity.to(f32)[sel, None] * torch.exp(power)).clamp(max=max_alpha)
        keep = (alpha >= min_alpha) & (px >= 0) & (px < width) & (py >= 0) & (py < height)
        g = sel[:, None].expand_as(px)[keep]
        gs.append(g)
        ps.append((py * width + px)[keep])
        als.append(alpha[keep])
    gauss = torch.cat(gs) if gs else empty_l
    pixel = torch.cat(ps) if ps else empty_l
    alpha = torch.cat(als) if als else torch.zeros(0, dtype=f32, device=dev)
    # sort by (pixel, depth): the depth rank of each Gaussian breaks ties inside a pixel
    zrank = torch.empty(n, dtype=torch.long, device=dev)
    zrank[torch.argsort(z)] = torch.arange(n, device=dev)
    order = torch.argsort(pixel * n + zrank[gauss])
    gauss, pixel, alpha = gauss[order], pixel[order], alpha[order]
    # exclusive product of (1 - alpha) per pixel: exclusive segmented cumsum of log(1 - alpha)
    l1m = torch.log1p(-alpha.double())
    incl = torch.cumsum(l1m, 0)
    m = pixel.numel()
    if m:
        start = torch.ones(m, dtype=torch.bool, device=dev)
        start[1:] = pixel[1:] != pixel[:-1]
        seg_first = torch.cummax(torch.where(start, torch.arange(m, device=dev), torch.zeros_like(pixel)), 0)[0]
        base = incl[seg_first] - l1m[seg_first]
        trans = torch.exp(incl - l1m - base).to(f32)
    else:
        trans = torch.zeros(0, dtype=f32, device=dev)
    keep = trans >= min_transmittance
    gauss, pixel = gauss[keep], pixel[keep]
    kappa = alpha[keep] * trans[keep]
    acc.index_add_(0, pixel, kappa)
    dsum = torch.zeros(hw, dtype=f32, device=dev)
    dsum.index_add_(0, pixel, kappa * z[gauss])
    depth = torch.where(acc >= valid_acc, dsum / acc.clamp(min=1e-12), torch.zeros_like(acc))
    out = Splats(height, width, gauss, pixel, kappa, acc.view(height, width), depth.view(height, width), None)
    if colors is not None:
        out.channels = out.image(colors.to(dev, f32))
    return out

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
    return render_views(
        means, sigma, opacity, camera_pose[None], K, height, width, colors=colors, max_radius_px=max_radius_px,
        min_alpha=min_alpha, max_alpha=max_alpha, min_transmittance=min_transmittance, valid_acc=valid_acc,
    )


@dataclass
class _Projected:
    """Every Gaussian once per view (copy ``k`` = view ``view[k]``, Gaussian ``src[k]``): its camera depth ``z``,
    its centre ``(u, v)`` in pixels, the inverse ``(ia, ib, ic)`` of its EWA 2D covariance and its splat radius."""

    view: torch.Tensor
    src: torch.Tensor
    z: torch.Tensor
    u: torch.Tensor
    v: torch.Tensor
    ia: torch.Tensor
    ib: torch.Tensor
    ic: torch.Tensor
    radius: torch.Tensor


def _project(means: torch.Tensor, sigma: torch.Tensor, camera_poses: torch.Tensor, K: torch.Tensor,
             max_radius_px: int) -> _Projected:
    """The EWA projection (Zwicker et al. 2001, as in 3DGS) of every Gaussian into every view."""
    dev, f32 = means.device, torch.float32
    n_views, n_src = int(camera_poses.shape[0]), means.shape[0]
    Rs, ts = [], []
    for v in range(n_views):
        R, t = world_to_camera(camera_poses[v].to(dev, f32))
        Rs.append(R)
        ts.append(t)
    m32 = means.to(f32)
    xc = torch.cat([m32 @ R.T + t for R, t in zip(Rs, ts, strict=True)]) if n_views > 1 else m32 @ Rs[0].T + ts[0]
    view = torch.arange(n_views, device=dev).repeat_interleave(n_src)
    src = torch.arange(n_src, device=dev).repeat(n_views)
    z = xc[:, 2]
    fx, fy, cx, cy = (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
    zs = z.clamp(min=NEAR_M)
    u = fx * xc[:, 0] / zs + cx
    v_ = fy * xc[:, 1] / zs + cy
    j11, j22 = fx / zs, fy / zs
    j13, j23 = -fx * xc[:, 0] / zs**2, -fy * xc[:, 1] / zs**2
    s2 = sigma.to(f32).repeat(n_views) ** 2
    a = s2 * (j11**2 + j13**2) + EWA_DILATION
    b = s2 * (j13 * j23)
    c = s2 * (j22**2 + j23**2) + EWA_DILATION
    det = (a * c - b * b).clamp(min=1e-12)
    lam = 0.5 * (a + c) + torch.sqrt((0.25 * (a - c) ** 2 + b * b).clamp(min=0))
    radius = torch.ceil(3.0 * torch.sqrt(lam)).clamp(max=max_radius_px).long()
    return _Projected(view, src, z, u, v_, c / det, -b / det, a / det, radius)


def _boxes(p: _Projected, ok: torch.Tensor, n_views: int, height: int, width: int,
           roi_of: torch.Tensor | None) -> tuple[torch.Tensor, ...]:
    """Per view, the pixel box ``[x0, x1] x [y0, y1]`` rendered: the whole image, or with ``roi_of`` the bounding
    box of those Gaussians' splats (of the copies in front of the camera, ``ok``)."""
    dev, f32 = p.u.device, torch.float32
    x0 = torch.zeros(n_views, device=dev)
    y0 = torch.zeros(n_views, device=dev)
    x1 = torch.full((n_views,), float(width - 1), device=dev)
    y1 = torch.full((n_views,), float(height - 1), device=dev)
    if roi_of is not None:
        n_src = p.u.shape[0] // n_views
        mem = torch.zeros(n_src, dtype=torch.bool, device=dev)
        mem[roi_of.to(dev)] = True
        mem = mem.repeat(n_views) & ok
        big = torch.tensor(float("inf"), device=dev)
        rf = p.radius.to(f32)
        for lo, hi, val_lo, val_hi in ((x0, x1, p.u - rf, p.u + rf), (y0, y1, p.v - rf, p.v + rf)):
            lo_v = torch.full((n_views,), big.item(), device=dev).scatter_reduce(
                0, p.view[mem], val_lo[mem], "amin", include_self=True)
            hi_v = torch.full((n_views,), -big.item(), device=dev).scatter_reduce(
                0, p.view[mem], val_hi[mem], "amax", include_self=True)
            lo.copy_(torch.maximum(lo, torch.floor(lo_v)))
            hi.copy_(torch.minimum(hi, torch.ceil(hi_v)))
    return x0, y0, x1, y1


def _rasterize(p: _Projected, idx: torch.Tensor, opacity: torch.Tensor, n_views: int, hw: int, width: int,
               boxes: tuple[torch.Tensor, ...], min_alpha: float,
               max_alpha: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(copy, pixel, alpha) of every pixel of the copies ``idx`` where the splat's alpha (Eq. 1's
    ``o exp(-1/2 d^T Sigma^-1 d)``, at most ``max_alpha``) reaches ``min_alpha`` inside its view's box; the
    copies are drawn grouped by radius, each group over the disc of its radius."""
    dev, f32 = p.u.device, torch.float32
    x0, y0, x1, y1 = boxes
    empty_l = torch.zeros(0, dtype=torch.long, device=dev)
    gs, ps, als = [], [], []
    ui, vi = torch.round(p.u).long(), torch.round(p.v).long()
    for r in torch.unique(p.radius[idx]).tolist():
        sel = idx[p.radius[idx] == r]
        off = torch.arange(-r, r + 1, device=dev)
        dy, dx = torch.meshgrid(off, off, indexing="ij")
        disc = dx * dx + dy * dy <= r * r + r  # the disc of radius r (the square's corners are past 3 sigma)
        dx, dy = dx[disc], dy[disc]
        px = ui[sel, None] + dx[None, :]
        py = vi[sel, None] + dy[None, :]
        ddx = px.to(f32) - p.u[sel, None]
        ddy = py.to(f32) - p.v[sel, None]
        power = -0.5 * (p.ia[sel, None] * ddx * ddx + 2 * p.ib[sel, None] * ddx * ddy + p.ic[sel, None] * ddy * ddy)
        alpha = (opacity.to(f32).repeat(n_views)[sel, None] * torch.exp(power)).clamp(max=max_alpha)
        vw = p.view[sel, None]
        keep = (alpha >= min_alpha) & (px >= x0[vw]) & (px <= x1[vw]) & (py >= y0[vw]) & (py <= y1[vw])
        g = sel[:, None].expand_as(px)[keep]
        gs.append(g)
        ps.append((vw * hw + py * width + px)[keep])
        als.append(alpha[keep])
    gauss = torch.cat(gs) if gs else empty_l
    pixel = torch.cat(ps) if ps else empty_l
    alpha = torch.cat(als) if als else torch.zeros(0, dtype=f32, device=dev)
    return gauss, pixel, alpha


def _blend(z: torch.Tensor, gauss: torch.Tensor, pixel: torch.Tensor, alpha: torch.Tensor,
           min_transmittance: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Front-to-back alpha blending (Eq. 1): per pixel, the copies in depth order, each one's weight ``kappa``
    = its alpha times the transmittance of those in front of it; only copies whose transmittance reaches
    ``min_transmittance`` are kept. Returns (copy, pixel, kappa)."""
    dev, f32 = z.device, torch.float32
    n = z.shape[0]
    # sort by (pixel, depth): the depth rank of each Gaussian breaks ties inside a pixel
    zrank = torch.empty(n, dtype=torch.long, device=dev)
    zrank[torch.argsort(z, stable=True)] = torch.arange(n, device=dev)  # stable: equal depths in index order
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
    return gauss[keep], pixel[keep], alpha[keep] * trans[keep]


def render_views(
    means: torch.Tensor,
    sigma: torch.Tensor,
    opacity: torch.Tensor,
    camera_poses: torch.Tensor,
    K: torch.Tensor,
    height: int,
    width: int,
    colors: torch.Tensor | None = None,
    max_radius_px: int = 8,
    min_alpha: float = 1.0 / 255.0,
    max_alpha: float = 0.99,
    min_transmittance: float = 1e-4,
    valid_acc: float = 0.5,
    roi_of: torch.Tensor | None = None,
) -> Splats:
    """Eq. 1 from ``V`` camera poses ``camera_poses`` (V, 4, 4) in one vectorised pass: the views are stacked
    vertically, so the result is one :class:`Splats` of ``V * height`` x ``width`` (view ``v`` = rows
    ``v * height`` .. ``(v + 1) * height - 1``; ``gauss`` indexes ``means``). Each view is exactly the
    single-pose render.

    ``roi_of`` (indices into ``means``): only the pixels inside the bounding box of these Gaussians' splats are
    rendered in each view (the others are left empty and Gaussians whose splat misses the box are skipped).
    Inside the box nothing changes -- every splat covering one of its pixels is kept -- so everything a
    quantity about those Gaussians needs (their kappas, the blended image where they are) is the same as in
    the full render, at the cost of the box only (the optimistic views of one instance, Eq. 11/12)."""
    dev = means.device
    f32 = torch.float32
    n_views = int(camera_poses.shape[0])
    hw = height * width
    empty_l = torch.zeros(0, dtype=torch.long, device=dev)
    acc = torch.zeros(n_views * hw, dtype=f32, device=dev)
    n_src = means.shape[0]
    if n_src == 0 or n_views == 0:
        hh = n_views * height
        ch = torch.zeros(hh, width, colors.shape[1], dtype=f32, device=dev) if colors is not None else None
        z = torch.zeros(hh, width, dtype=f32, device=dev)
        return Splats(hh, width, empty_l, empty_l, torch.zeros(0, dtype=f32, device=dev), z.clone(), z, ch)
    p = _project(means, sigma, camera_poses, K, max_radius_px)
    ok = (p.z > NEAR_M) & torch.isfinite(p.u) & torch.isfinite(p.v)
    boxes = _boxes(p, ok, n_views, height, width, roi_of)
    x0, y0, x1, y1 = boxes
    view, radius = p.view, p.radius
    ok = (
        ok
        & (p.u + radius >= x0[view])
        & (p.u - radius <= x1[view])
        & (p.v + radius >= y0[view])
        & (p.v - radius <= y1[view])
    )
    idx = torch.nonzero(ok).squeeze(1)
    gauss, pixel, alpha = _rasterize(p, idx, opacity, n_views, hw, width, boxes, min_alpha, max_alpha)
    gauss, pixel, kappa = _blend(p.z, gauss, pixel, alpha, min_transmittance)
    acc.index_add_(0, pixel, kappa)
    dsum = torch.zeros(n_views * hw, dtype=f32, device=dev)
    dsum.index_add_(0, pixel, kappa * p.z[gauss])
    depth = torch.where(acc >= valid_acc, dsum / acc.clamp(min=1e-12), torch.zeros_like(acc))
    hh = n_views * height
    out = Splats(hh, width, p.src[gauss], pixel, kappa, acc.view(hh, width), depth.view(hh, width), None)
    if colors is not None:
        out.channels = out.image(colors.to(dev, f32))
    return out

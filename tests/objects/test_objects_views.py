"""The vectorised renders of the object layer: several camera poses in one pass and the render
restricted to one instance's box give exactly the single-pose, full-image numbers (Eq. 1, 11, 12)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from services.mapper.objects import splat
from services.mapper.objects.config import ObjectLayerConfig
from services.mapper.objects.layer import ObjectLayer, camera_from_gaze

W, H = 160, 120
F = W / 2 / math.tan(math.radians(60))
K = np.array([[F, 0, (W - 1) / 2], [0, F, (H - 1) / 2], [0, 0, 1.0]])
Kt = torch.tensor(K, dtype=torch.float32)


def _gaussians(seed: int = 0, n: int = 400) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 3, generator=g) * torch.tensor([2.0, 2.0, 1.0]) + torch.tensor([-1.0, -1.0, 2.0])
    means[: n // 4, 2] = 2.5  # a quarter at one depth: ties in the depth order
    sigma = 0.01 + 0.04 * torch.rand(n, generator=g)
    opacity = 0.3 + 0.6 * torch.rand(n, generator=g)
    return means, sigma, opacity


def _poses() -> list[torch.Tensor]:
    out = [torch.eye(4)]
    for yaw, x in ((0.15, -0.3), (-0.2, 0.4), (math.pi, 0.0)):  # the last looks away
        c, s = math.cos(yaw), math.sin(yaw)
        T = torch.eye(4)
        T[0, 0], T[0, 2], T[2, 0], T[2, 2] = c, s, -s, c
        T[0, 3] = x
        out.append(T)
    return out


def _same(a: dict[tuple[int, int], float], b: dict[tuple[int, int], float]) -> bool:
    """The same pairs with the same kappas up to float32 rounding (the blend's running sums differ in length)."""
    return a.keys() == b.keys() and all(abs(a[k] - b[k]) <= 1e-6 + 1e-5 * abs(b[k]) for k in a)


def _pairs(r: splat.Splats, lo: int, hi: int) -> dict[tuple[int, int], float]:
    sel = (r.pixel >= lo) & (r.pixel < hi)
    return {(int(g), int(p) - lo): float(k) for g, p, k in zip(r.gauss[sel], r.pixel[sel], r.kappa[sel], strict=True)}


def test_render_views_is_each_single_render() -> None:
    means, sigma, opacity = _gaussians()
    colors = torch.rand(len(means), 3, generator=torch.Generator().manual_seed(1))
    poses = _poses()
    rb = splat.render_views(means, sigma, opacity, torch.stack(poses), Kt, H, W, colors=colors)
    assert rb.height == len(poses) * H
    for v, pose in enumerate(poses):
        r1 = splat.render(means, sigma, opacity, pose, Kt, H, W, colors=colors)
        assert _same(_pairs(rb, v * H * W, (v + 1) * H * W), _pairs(r1, 0, H * W))
        assert torch.allclose(rb.depth[v * H:(v + 1) * H], r1.depth, atol=1e-5)
        assert torch.allclose(rb.channels[v * H:(v + 1) * H], r1.channels, atol=1e-6)
    assert float(rb.acc[3 * H:].sum()) == 0.0  # looking away


def test_render_restricted_to_a_box_keeps_everything_about_its_gaussians() -> None:
    means, sigma, opacity = _gaussians(seed=2)
    members = torch.arange(40, 70)
    poses = _poses()[:3]
    rb = splat.render_views(means, sigma, opacity, torch.stack(poses), Kt, H, W, roi_of=members)
    for v, pose in enumerate(poses):
        full = _pairs(splat.render(means, sigma, opacity, pose, Kt, H, W), 0, H * W)
        box = _pairs(rb, v * H * W, (v + 1) * H * W)
        mine = {k: x for k, x in full.items() if k[0] in set(members.tolist())}
        assert mine and _same({k: x for k, x in box.items() if k[0] in set(members.tolist())}, mine)
        pix = {p for _, p in mine}
        # every pair on a member's pixel is kept (occluders included); pixels outside the members' box are empty
        assert _same({k: x for k, x in box.items() if k[1] in pix}, {k: x for k, x in full.items() if k[1] in pix})
        rows, cols = np.array([p // W for p in pix]), np.array([p % W for p in pix])
        for _, p in box:
            assert rows.min() - 8 <= p // W <= rows.max() + 8 and cols.min() - 8 <= p % W <= cols.max() + 8
        assert len(box) < len(full)


def test_optimistic_each_is_optimistic_of_each_pose_alone() -> None:
    layer = ObjectLayer(["mug", "table"], ObjectLayerConfig(render_scale=1.0))
    depth = np.full((H, W), 3.0, np.float32)
    cls = np.full((H, W), 2, np.int64)
    depth[40:80, 60:100], cls[40:80, 60:100] = 2.5, 0  # a mug
    depth[70:110, 20:140], cls[70:110, 20:140] = 2.0, 1  # a table in front of its lower part
    layer.update(depth, cls, np.eye(4), K, 0)
    poses = [camera_from_gaze(x, 0.0, math.pi / 2 + a, 0.0, 0.0) for x, a in ((0.0, 0.0), (0.3, -0.1), (-0.4, 0.15))]
    poses = [torch.as_tensor(np.eye(4), dtype=torch.float32), *poses]
    insts = layer.instances()
    assert len(insts) == 2
    for inst in insts:
        for c in (0, 1):
            each = layer.optimistic_each(inst.instance_id, c, poses, width=W)
            alone = [layer.optimistic(inst.instance_id, c, [p], width=W) for p in poses]
            for a, b in zip(each, alone, strict=True):
                assert a.ig == pytest.approx(b.ig, rel=1e-4, abs=1e-4)
                want = (b.psi_prime, b.s_prime, b.u_prime)
                assert (a.psi_prime, a.s_prime, a.u_prime) == pytest.approx(want, abs=1e-6)
                # pixels of Y* showing the class: counted inside the instance's box only
                assert a.pixels <= b.pixels and (b.pixels > 0 or a.pixels == 0)
    assert layer.optimistic_each(insts[0].instance_id, 0, []) == []

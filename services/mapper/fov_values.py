"""Field-of-view confidence fusion of a frame's value into a 2D value layer (HELIOS 3.1.2, after VLFM,
Yokoyama et al. 2023): "fusing the results using a confidence based on the field-of-view cone for each
observation".

A frame's value ``v`` (the VLM's score of "Seems like there is a (class) ahead") is written into every cell of
the frame's field-of-view cone with the confidence ``c = cos^2(theta / (hfov / 2) * pi / 2)``, ``theta`` the
horizontal angle of the cell's ray from the optical axis (1 on the axis, 0 at the image's edge). The cone is cut
along each image column where the frame's depth ends (the farthest measured point of that column, at most
``max_range_m``): what lies behind a surface was not seen. A cell keeps a value and a confidence and fuses a new
observation as VLFM does::

    v <- (c_old v_old + c v) / (c_old + c),    c_old <- (c_old^2 + c^2) / (c_old + c)

so a view straight at a cell outweighs one that saw it at the edge of the image, and a cell seen once keeps its
value until seen again. Pure numpy; the mapper keeps the confidence as a plane of the map.
"""

from __future__ import annotations

import math

import numpy as np

from eqa import grid as gridm

MAX_RANGE_M = 5.0  # VLFM's depth range for its value map (HM3D camera, 0.5 .. 5 m)
N_RAYS = 96  # image columns sampled for the cone


def fov_cells(depth: np.ndarray, K: np.ndarray, cam_pose: np.ndarray, origin: tuple[float, float],
              resolution: float, shape: tuple[int, int], max_range_m: float = MAX_RANGE_M,
              n_rays: int = N_RAYS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(rows, cols, confidence)`` of the cells of the frame's field-of-view cone on a grid of ``shape``
    (module doc); a cell on several rays takes its highest confidence. ``depth`` (H, W) metres, ``K`` the
    pinhole intrinsics, ``cam_pose`` camera-to-world (x right, y down, z forward)."""
    d = np.nan_to_num(np.asarray(depth, np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    h, w = d.shape
    fx, fy, cx, cy = float(K[0][0]), float(K[1][1]), float(K[0][2]), float(K[1][2])
    half = math.atan((w / 2) / fx)
    cam = np.asarray(cam_pose, np.float64)
    cols = np.unique(np.linspace(0, w - 1, max(2, min(n_rays, w))).round().astype(int))
    rows = np.arange(h)
    sub = d[:, cols]  # (H, R)
    U, V = np.meshgrid(cols.astype(np.float64), rows.astype(np.float64))
    pc = np.stack([(U - cx) / fx * sub, (V - cy) / fy * sub, sub], axis=-1)  # camera frame
    pw = pc @ cam[:3, :3].T + cam[:3, 3]
    ox, oy = float(cam[0, 3]), float(cam[1, 3])
    horiz = np.hypot(pw[..., 0] - ox, pw[..., 1] - oy)
    valid = sub > 0
    horiz = np.where(valid, horiz, -1.0)
    far = horiz.argmax(axis=0)
    reach = np.minimum(horiz[far, np.arange(len(cols))], max_range_m)
    ok = reach > 0
    if not ok.any():
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0)
    # each ray's ground-plane direction: that of its farthest point
    dirx = pw[far, np.arange(len(cols)), 0] - ox
    diry = pw[far, np.arange(len(cols)), 1] - oy
    norm = np.hypot(dirx, diry)
    ok &= norm > 1e-9
    theta = np.arctan((cols - cx) / fx)
    conf = np.cos(np.clip(theta / half, -1.0, 1.0) * math.pi / 2) ** 2
    step = resolution / 2
    out_r, out_c, out_w = [], [], []
    for k in np.flatnonzero(ok):
        n = max(1, math.ceil(float(reach[k]) / step))
        t = np.linspace(0.0, float(reach[k]), n + 1)
        x, y = ox + t * dirx[k] / norm[k], oy + t * diry[k] / norm[k]
        r, c = gridm.cell_of(x, y, origin, resolution)
        inside = gridm.inside(r, c, shape)
        out_r.append(r[inside])
        out_c.append(c[inside])
        out_w.append(np.full(int(inside.sum()), conf[k]))
    if not out_r:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0)
    r, c, cw = np.concatenate(out_r), np.concatenate(out_c), np.concatenate(out_w)
    flat = r * shape[1] + c
    order = np.lexsort((-cw, flat))  # per cell, highest confidence first
    flat, cw = flat[order], cw[order]
    first = np.ones(len(flat), bool)
    first[1:] = flat[1:] != flat[:-1]
    flat, cw = flat[first], cw[first]
    return flat // shape[1], flat % shape[1], cw


def fuse(values: np.ndarray, confidence: np.ndarray, rows: np.ndarray, cols: np.ndarray, conf: np.ndarray,
         value: float) -> None:
    """VLFM's update of ``values`` / ``confidence`` (same shape, in place) at the cells with confidence
    ``conf`` > 0 (module doc)."""
    keep = conf > 0
    r, c, cn = rows[keep], cols[keep], conf[keep]
    old_c = confidence[r, c].astype(np.float64)
    old_v = values[r, c].astype(np.float64)
    tot = old_c + cn
    values[r, c] = ((old_c * old_v + cn * float(value)) / tot).astype(values.dtype)
    confidence[r, c] = ((old_c**2 + cn**2) / tot).astype(confidence.dtype)

"""Instances of the object layer (HELIOS section 3.1.3 "Instances", appendix 6.1 "3DGS instance creation").

Gaussians of the same most-likely class are put into a ``voxel_m`` (0.5 m) grid aligned with the world
frame, clustered by 26-connected components of occupied voxels, and each cluster takes the minimum of the
previous instance labels of its Gaussians; a cluster none of whose Gaussians had a label gets a new one (the
paper: max label + 1; here a counter that never hands out a dropped label again). Only the Gaussians updated
by the last frame and every Gaussian of their instances are re-clustered; the rest keep their labels.

Labels stay unique: when two clusters would take the same previous label (an instance split in two, or a
Gaussian whose class flipped carries its old label into a cluster of another class), clusters are served
largest first and each takes the smallest previous label not yet taken by a larger one, else a new label.
The paper computes the components by 20 min-pooling passes on a voxel graph (PyTorch Geometric); here
``scipy.ndimage.label`` with a 3x3x3 structure gives the same 26-connected components exactly.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

_26 = np.ones((3, 3, 3), dtype=bool)


def components(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """Component index (0..k-1) of each point (M,3) under 26-connectivity of its ``voxel_m`` voxels."""
    if len(points) == 0:
        return np.zeros(0, dtype=np.int64)
    vox = np.floor(points / voxel_m).astype(np.int64)
    uniq, inv = np.unique(vox, axis=0, return_inverse=True)
    lo = uniq.min(0)
    dims = uniq.max(0) - lo + 1
    grid = np.zeros(tuple(int(d) for d in dims), dtype=bool)
    rel = uniq - lo
    grid[rel[:, 0], rel[:, 1], rel[:, 2]] = True
    labels, _ = ndimage.label(grid, structure=_26)
    comp_of_voxel = labels[rel[:, 0], rel[:, 1], rel[:, 2]] - 1
    return comp_of_voxel[inv.reshape(-1)].astype(np.int64)


def relabel(
    means: np.ndarray,
    cls: np.ndarray,
    previous: np.ndarray,
    subset: np.ndarray,
    next_label: int,
    voxel_m: float = 0.5,
) -> tuple[np.ndarray, int]:
    """New instance labels of the Gaussians ``subset`` (indices) and the next free label.

    ``means`` (N,3), ``cls`` (N,) most-likely class, ``previous`` (N,) labels (-1 = none). See the module
    docstring for the rule."""
    out = previous[subset].copy()
    if len(subset) == 0:
        return out, next_label
    clusters: list[np.ndarray] = []  # positions in ``subset``
    sub_cls = cls[subset]
    for c in np.unique(sub_cls):
        pos = np.flatnonzero(sub_cls == c)
        comp = components(means[subset[pos]], voxel_m)
        order = np.argsort(comp, kind="stable")
        splits = np.flatnonzero(np.diff(comp[order])) + 1
        clusters.extend(pos[g] for g in np.split(order, splits))
    clusters.sort(key=lambda g: (-len(g), int(subset[g].min())))
    taken: set[int] = set()
    for g in clusters:
        prev = sorted({int(v) for v in previous[subset[g]] if v >= 0} - taken)
        if prev:
            label = prev[0]
        else:
            label = next_label
            next_label += 1
        taken.add(label)
        out[g] = label
    return out, next_label

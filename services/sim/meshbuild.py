"""Building triangle meshes out of axis-aligned boxes and quads, each triangle tagged with an instance id
and a flat colour (what :class:`services.sim.scene.Scene` stores)."""

from __future__ import annotations

import numpy as np

# The 12 triangles of a box over its 8 corners (corner k = bits x|y<<1|z<<2), wound outwards.
_BOX_TRIS = np.array(
    [
        [0, 2, 3], [0, 3, 1],  # bottom z0
        [4, 5, 7], [4, 7, 6],  # top z1
        [0, 1, 5], [0, 5, 4],  # y0
        [2, 6, 7], [2, 7, 3],  # y1
        [0, 4, 6], [0, 6, 2],  # x0
        [1, 3, 7], [1, 7, 5],  # x1
    ],
    np.int32,
)
_CORNERS = np.array([[(k >> 0) & 1, (k >> 1) & 1, (k >> 2) & 1] for k in range(8)], np.float64)


class MeshBuilder:
    """Collects boxes and quads; :meth:`arrays` builds the mesh in one vectorised pass."""

    def __init__(self) -> None:
        self._boxes: list[tuple[float, float, float, float, float, float, int, int, int, int, bool]] = []
        self._quads: list[tuple[float, float, float, float, float, int, int, int, int]] = []

    def box(self, lo: tuple[float, ...], hi: tuple[float, ...], instance: int,
            color: tuple[int, int, int], faces: str = "all") -> None:
        """An axis-aligned box from corner ``lo`` to ``hi``. ``faces="open_top"`` leaves the top off."""
        if hi[0] - lo[0] <= 0 or hi[1] - lo[1] <= 0 or hi[2] - lo[2] <= 0:
            return
        self._boxes.append((float(lo[0]), float(lo[1]), float(lo[2]), float(hi[0]), float(hi[1]), float(hi[2]),
                            int(instance), int(color[0]), int(color[1]), int(color[2]), faces == "all"))

    def quad_z(self, x0: float, y0: float, x1: float, y1: float, z: float, instance: int,
               color: tuple[int, int, int]) -> None:
        """A horizontal rectangle at height ``z``."""
        self._quads.append((x0, y0, x1, y1, z, int(instance), int(color[0]), int(color[1]), int(color[2])))

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(vertices float32, triangles int32, triangle_instance int32, triangle_colors uint8)``; the
        order is the order of the calls (quads first, then boxes)."""
        verts, tris, inst, cols = [], [], [], []
        n = 0
        if self._quads:
            q = np.array(self._quads, np.float64)
            k = len(q)
            v = np.empty((k, 4, 3))
            v[:, :, 2] = q[:, 4, None]
            v[:, [0, 3], 0] = q[:, 0, None]
            v[:, [1, 2], 0] = q[:, 2, None]
            v[:, [0, 1], 1] = q[:, 1, None]
            v[:, [2, 3], 1] = q[:, 3, None]
            t = np.array([[0, 1, 2], [0, 2, 3]], np.int32)[None] + (np.arange(k, dtype=np.int32) * 4)[:, None, None]
            verts.append(v.reshape(-1, 3))
            tris.append(t.reshape(-1, 3))
            inst.append(np.repeat(q[:, 5].astype(np.int32), 2))
            cols.append(np.repeat(q[:, 6:9].astype(np.uint8), 2, axis=0))
            n = 4 * k
        if self._boxes:
            b = np.array(self._boxes, np.float64)
            k = len(b)
            lo, hi = b[:, None, 0:3], b[:, None, 3:6]
            v = lo + _CORNERS[None] * (hi - lo)  # (k,8,3)
            full = b[:, 10] > 0.5
            ntri = np.where(full, 12, 10)
            t = _BOX_TRIS[None] + (n + np.arange(k, dtype=np.int32) * 8)[:, None, None]  # (k,12,3)
            keep = np.ones((k, 12), bool)
            keep[~full, 2:4] = False
            verts.append(v.reshape(-1, 3))
            tris.append(t[keep])
            inst.append(np.repeat(b[:, 6].astype(np.int32), ntri))
            cols.append(np.repeat(b[:, 7:10].astype(np.uint8), ntri, axis=0))
        return (
            np.concatenate(verts).astype(np.float32),
            np.concatenate(tris).astype(np.int32),
            np.concatenate(inst).astype(np.int32),
            np.concatenate(cols).astype(np.uint8),
        )


class Frame2D:
    """A local frame on the floor for placing things against a wall: local ``u`` runs along the wall,
    local ``v`` points away from it into the room; ``facing`` is one of ``(+-1, 0), (0, +-1)``."""

    def __init__(self, origin: tuple[float, float], facing: tuple[int, int]) -> None:
        self.o = origin
        self.f = facing
        self.u = (facing[1], -facing[0])  # right-hand along-wall direction

    def to_world(self, u: float, v: float) -> tuple[float, float]:
        return (self.o[0] + u * self.u[0] + v * self.f[0], self.o[1] + u * self.u[1] + v * self.f[1])

    def box(self, u0: float, u1: float, v0: float, v1: float) -> tuple[float, float, float, float]:
        """World AABB ``(x0, y0, x1, y1)`` of the local rectangle ``[u0,u1] x [v0,v1]``."""
        a = self.to_world(u0, v0)
        b = self.to_world(u1, v1)
        return (min(a[0], b[0]), min(a[1], b[1]), max(a[0], b[0]), max(a[1], b[1]))

"""Top-down floor plan pictures (for people to look at): rooms with their kinds, walls, doors, furniture
and small objects, and optionally a trajectory. Real-mesh scenes without rooms show the navigable grid."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from services.sim.catalog import SMALL_OBJECTS, display_name
from services.sim.scene import Scene

ROOM_FILL = {
    "kitchen": "#f6e7c8", "bedroom": "#dfe8f5", "bathroom": "#d6f0f0", "living_room": "#f3dfd2",
    "dining_room": "#efe2c4", "hallway": "#e8e8e8", "office": "#e2efdc", "laundry": "#e6e0f3",
    "garage": "#d9d9d9", "storage": "#e9e2da",
}


def read_trajectory(path: Path) -> np.ndarray:
    """``(N,2)`` xy points from a JSON list (``[[x, y(, yaw)], ...]`` or ``[{"x":..,"y":..}, ...]``) or a
    text file with one ``x,y[,yaw]`` per line. Raises ``ValueError`` with the reason."""
    text = Path(path).read_text()
    pts: list[tuple[float, float]] = []
    try:
        data = json.loads(text)
    except json.JSONDecodeError:
        data = None
    if data is not None:
        if not isinstance(data, list):
            raise ValueError(f"{path}: expected a JSON list of points")
        for p in data:
            if isinstance(p, dict):
                pts.append((float(p["x"]), float(p["y"])))
            else:
                pts.append((float(p[0]), float(p[1])))
    else:
        for n, line in enumerate(text.splitlines(), start=1):
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            parts = line.replace(",", " ").split()
            if len(parts) < 2:
                raise ValueError(f"{path}:{n}: expected 'x,y[,yaw]'")
            pts.append((float(parts[0]), float(parts[1])))
    arr = np.asarray(pts, np.float64).reshape(-1, 2)
    if not np.isfinite(arr).all():
        raise ValueError(f"{path}: trajectory has non-finite values")
    return arr


def draw_floorplan(scene: Scene, out: Path, trajectory: np.ndarray | None = None, dpi: int = 110,
                   label_objects: bool = True) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    lo, hi = scene.bounds
    w, h = hi[0] - lo[0], hi[1] - lo[1]
    scale = 0.55 if max(w, h) < 40 else 0.3
    fig, ax = plt.subplots(figsize=(max(4.0, w * scale), max(3.0, h * scale)))
    if scene.rooms:
        for r in scene.rooms:
            x0, y0, x1, y1 = r.rect
            ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, facecolor=ROOM_FILL.get(r.kind, "#eee"),
                                   edgecolor="#333", linewidth=2.0, zorder=1))
            ax.text((x0 + x1) / 2, y1 - 0.35, f"{display_name(r.kind)} ({r.id})", ha="center", va="top",
                    fontsize=7, weight="bold", zorder=5)
        for d in scene.doors:
            cx, cy = d.center
            if d.axis == "x":
                ax.plot([cx - d.width / 2, cx + d.width / 2], [cy, cy], color="white", linewidth=3.5, zorder=2)
            else:
                ax.plot([cx, cx], [cy - d.width / 2, cy + d.width / 2], color="white", linewidth=3.5, zorder=2)
        for o in scene.objects():
            px, py, _ = o.position
            sx, sy, _ = o.size
            small = o.category in SMALL_OBJECTS
            ax.add_patch(Rectangle((px - sx / 2, py - sy / 2), sx, sy, zorder=4 if small else 3,
                                   facecolor="#d62728" if small else "#8c6d46", alpha=0.9 if small else 0.55,
                                   edgecolor="none"))
            if label_objects and small:
                desc = " ".join(v for k, v in sorted(o.attributes.items()) if k in ("color", "state"))
                ax.text(px, py + sy / 2 + 0.05, f"{display_name(o.category)} #{o.id}\n{desc}", fontsize=4.5,
                        ha="center", va="bottom", zorder=6)
    else:
        grid, ox, oy = scene.navigable_grid(0.1)
        extent = (ox, ox + grid.shape[1] * 0.1, oy, oy + grid.shape[0] * 0.1)
        ax.imshow(grid, origin="lower", cmap="Greys", extent=extent)
    if trajectory is not None and len(trajectory):
        t = np.asarray(trajectory)
        ax.plot(t[:, 0], t[:, 1], "-o", color="#1f77b4", markersize=2.5, linewidth=1.2, zorder=7)
        ax.plot(t[0, 0], t[0, 1], "s", color="green", markersize=6, zorder=8, label="start")
        ax.plot(t[-1, 0], t[-1, 1], "*", color="black", markersize=9, zorder=8, label="end")
        ax.legend(loc="lower right", fontsize=7)
    ax.set_xlim(lo[0] - 0.5, hi[0] + 0.5)
    ax.set_ylim(lo[1] - 0.5, hi[1] + 0.5)
    ax.set_aspect("equal")
    ax.set_title(f"{scene.id}: {scene.floor_area_m2:.0f} m2, {len(scene.rooms)} rooms", fontsize=9)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return out

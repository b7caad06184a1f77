"""``attachments.png``: the bones with the attachment sites and the joint axes, seen from the
front and from the medial side, in the tibia's frame (people check sites by looking)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from kneemesh_core.anatomy.frames import Frame

#: One colour per bundle (matplotlib's tab20).
_BUNDLES = ("ACLam", "ACLpl", "PCLal", "PCLpm", "MCLs", "MCLd", "MCLp", "LCL", "PFL", "pCAP", "PT", "mPFL", "lPFL", "ITB")


def _matplotlib():
    """The parts of matplotlib the figure is drawn with, imported on first use (0.4 s)."""
    from matplotlib import colormaps
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.collections import LineCollection
    from matplotlib.figure import Figure

    return colormaps, FigureCanvasAgg, LineCollection, Figure


def load() -> None:
    """Import matplotlib now rather than in the first :func:`draw`."""
    _matplotlib()


def draw(document: dict, bones: dict, frames: dict[str, Frame], path: Path, title: str = "") -> None:
    """Write the figure; ``bones``: pyvista meshes per bone (LPS mm).

    Drawn on a bare Agg figure (no pyplot: its import alone took a second of the job's critical
    path), with one artist per bundle rather than one per fibre."""
    colormaps, FigureCanvasAgg, LineCollection, Figure = _matplotlib()
    ref = frames["tibia"]
    side = document.get("side", "")
    # columns: lateral, anterior, proximal; seen from the front, a left knee's lateral side is on the left
    mirror = np.array([-1.0 if side == "left" else 1.0, 1.0, 1.0])
    basis = np.stack([ref.lateral, ref.anterior, ref.proximal], 1) * mirror

    def local(p: np.ndarray) -> np.ndarray:
        return (np.asarray(p, float) - ref.origin) @ basis

    cmap = colormaps["tab20"]
    colour = {b: cmap(i % 20) for i, b in enumerate(_BUNDLES)}
    fig = Figure(figsize=(11, 6.5), dpi=80)
    FigureCanvasAgg(fig)
    axs = fig.subplots(1, 2)
    fig.subplots_adjust(left=0.05, right=0.87, bottom=0.08, top=0.88, wspace=0.15)
    views = ((0, 2, "front (lateral to the right)" if side == "right" else "front (lateral to the left)"),
             (1, 2, "medial side (anterior to the right)"))
    outline = np.concatenate([local(m.points)[:: max(1, m.n_points // 1500)] for m in bones.values() if m is not None])
    fibres: dict[str, list[np.ndarray]] = {}
    for fibre in document["fibres"]:
        ends = [e["lps_mm"] for e in fibre["ends"] if e["lps_mm"] is not None]
        if len(ends) >= 2:
            fibres.setdefault(fibre["bundle"], []).append(local(np.array(ends)))
    for ax, (h, v, name) in zip(axs, views):
        ax.scatter(outline[:, h], outline[:, v], s=0.4, c="0.75", linewidths=0)
        for bundle, lines in fibres.items():
            c = colour.get(bundle, "k")
            ax.add_collection(LineCollection([q[:, [h, v]] for q in lines], colors=[c], linewidths=0.6, alpha=0.7))
            ends = np.concatenate(lines)
            ax.scatter(ends[:, h], ends[:, v], s=9, color=c, label=bundle, zorder=3)
        for frame in frames.values():
            o = local(frame.origin[None])[0]
            for axis, c in ((frame.lateral, "r"), (frame.anterior, "g"), (frame.proximal, "b")):
                tip = local((frame.origin + 25.0 * axis)[None])[0]
                ax.annotate("", (tip[h], tip[v]), (o[h], o[v]), arrowprops={"arrowstyle": "->", "color": c, "lw": 1.5})
        ax.set_aspect("equal")
        ax.set_title(name, fontsize=10)
        ax.set_xlabel("mm")
        ax.grid(alpha=0.2)
    axs[1].legend(fontsize=7, loc="center left", bbox_to_anchor=(1.0, 0.5), markerscale=1.5)
    angles = document.get("angles_deg", {})
    fig.suptitle(f"{title} {side} knee: {len(document['fibres'])} fibres; axes red lateral, green anterior, blue "
                 f"proximal; flexion {angles.get('flexion')} deg, varus {angles.get('varus')} deg", fontsize=10)
    fig.savefig(path)

"""``attachments.png``: the bones with the attachment sites and the joint axes, seen from the
front and from the medial side, in the tibia's frame (people check sites by looking)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from kneemesh_core.anatomy.frames import Frame

#: One colour per bundle (matplotlib's tab20).
_BUNDLES = ("ACLam", "ACLpl", "PCLal", "PCLpm", "MCLs", "MCLd", "MCLp", "LCL", "PFL", "pCAP", "PT", "mPFL", "lPFL", "ITB")


def draw(document: dict, bones: dict, frames: dict[str, Frame], path: Path, title: str = "") -> None:
    """Write the figure; ``bones``: pyvista meshes per bone (LPS mm)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ref = frames["tibia"]
    basis = np.stack([ref.lateral, ref.anterior, ref.proximal], 1)  # columns: lateral, anterior, proximal

    def local(p: np.ndarray) -> np.ndarray:
        return (np.asarray(p, float) - ref.origin) @ basis

    cmap = plt.get_cmap("tab20")
    colour = {b: cmap(i % 20) for i, b in enumerate(_BUNDLES)}
    fig, axs = plt.subplots(1, 2, figsize=(11, 6.5), dpi=80)
    side = document.get("side", "")
    views = ((0, 2, "front (lateral to the right)" if side == "right" else "front (lateral to the left)"),
             (1, 2, "medial side (anterior to the right)"))
    for ax, (h, v, name) in zip(axs, views):
        for bone, mesh in bones.items():
            if mesh is None:
                continue
            p = local(mesh.points)[:: max(1, mesh.n_points // 1500)]
            hx = p[:, h] if not (h == 0 and side == "left") else -p[:, h]
            ax.scatter(hx, p[:, v], s=0.4, c="0.75", linewidths=0)
        seen = set()
        for fibre in document["fibres"]:
            ends = [e["lps_mm"] for e in fibre["ends"] if e["lps_mm"] is not None]
            if len(ends) < 2:
                continue
            q = local(np.array(ends))
            qh = q[:, h] if not (h == 0 and side == "left") else -q[:, h]
            label = fibre["bundle"] if fibre["bundle"] not in seen else None
            seen.add(fibre["bundle"])
            ax.plot(qh, q[:, v], "-", color=colour.get(fibre["bundle"], "k"), lw=0.6, alpha=0.7)
            ax.scatter(qh, q[:, v], s=9, color=colour.get(fibre["bundle"], "k"), label=label, zorder=3)
        for name_f, frame in frames.items():
            o = local(frame.origin[None])[0]
            for axis, c in ((frame.lateral, "r"), (frame.anterior, "g"), (frame.proximal, "b")):
                tip = local((frame.origin + 25.0 * axis)[None])[0]
                oh, th = (o[h], tip[h]) if not (h == 0 and side == "left") else (-o[h], -tip[h])
                ax.annotate("", (th, tip[v]), (oh, o[v]), arrowprops={"arrowstyle": "->", "color": c, "lw": 1.5})
        ax.set_aspect("equal")
        ax.set_title(name, fontsize=10)
        ax.set_xlabel("mm")
        ax.grid(alpha=0.2)
    axs[1].legend(fontsize=7, loc="center left", bbox_to_anchor=(1.0, 0.5), markerscale=1.5)
    angles = document.get("angles_deg", {})
    fig.suptitle(f"{title} {side} knee: {len(document['fibres'])} fibres; axes red lateral, green anterior, blue "
                 f"proximal; flexion {angles.get('flexion')} deg, varus {angles.get('varus')} deg", fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)

"""``kneemesh compare A B --out DIR``: two results of one knee side by side (``compare.json``,
``deviation.png``, ``contact.png``): the labels (Dice), the meshes (articular surface deviation, volume,
elements and their size, coverage) and the contact; the measures are :mod:`kneemesh_core.metrics.compare`."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyvista as pv
import SimpleITK as sitk

from kneemesh_core.errors import KneeMeshError
from kneemesh_core.fe.results import loaded
from kneemesh_core.fe.run import RESULT_FILES
from kneemesh_core.io.files import atomic_write_text
from kneemesh_core.job.outputs import LABELS_FILE, MESHES_DIR, REPORT_FILE
from kneemesh_core.metrics.compare import contact_differences, surface_deviation
from kneemesh_core.metrics.labels import dice
from kneemesh_core.tissues import CARTILAGES


def _results(folder: Path, name: str) -> dict | None:
    f = folder / name
    return json.loads(f.read_text()) if f.exists() else None


def compare(a: Path, b: Path, out: Path) -> dict:
    """Compare job folders ``a`` and ``b``; writes ``out/compare.json`` and the figures, returns the summary."""
    a, b, out = Path(a), Path(b), Path(out)
    for folder in (a, b):
        if not (folder / MESHES_DIR).is_dir():
            raise KneeMeshError("not_a_job", f"{folder}: expected a KneeMesh result folder (with meshes/ and labels.nrrd).")
    out.mkdir(parents=True, exist_ok=True)
    summary: dict = {"a": str(a), "b": str(b)}
    if (a / LABELS_FILE).exists() and (b / LABELS_FILE).exists():
        summary["dice"] = {t: None if d is None else round(d, 5) for t, d in
                           dice(sitk.ReadImage(str(a / LABELS_FILE)), sitk.ReadImage(str(b / LABELS_FILE))).items()}
    deviations, meshes = {}, {}
    reports = [_results(folder, REPORT_FILE) or {} for folder in (a, b)]
    for t in CARTILAGES:
        fa, fb = a / MESHES_DIR / f"{t}.vtu", b / MESHES_DIR / f"{t}.vtu"
        if fa.exists() and fb.exists():
            ga, gb = pv.read(fa), pv.read(fb)
            deviations[t] = surface_deviation(ga, gb)
            meshes[t] = _mesh_figures(t, (ga, gb), reports)
    summary["meshes"] = meshes
    summary["surface_deviation_mm"] = {t: {k: v for k, v in d.items() if k != "distances_mm"} for t, d in deviations.items()}
    kind = next((n for n in RESULT_FILES if (a / n).exists() and (b / n).exists()), None)
    if kind:
        ra, rb = _results(a, kind), _results(b, kind)
        summary["contact"] = {"results": kind, "completed": [ra["completed"], rb["completed"]],
                              "differences": contact_differences(ra, rb)}
        _plot_contact(ra, rb, out / "contact.png")
    if deviations:
        _plot_deviation(deviations, out / "deviation.png")
    atomic_write_text(out / "compare.json", json.dumps(summary, indent=1))
    return summary


def _mesh_figures(tissue: str, grids: tuple[pv.UnstructuredGrid, pv.UnstructuredGrid], reports: list[dict]) -> dict:
    """The two meshes of one cartilage side by side, [A, B]: volume (ml) and elements measured on the files, the
    in-plane element size that shipped and the size asked for, the coverage of each label's cartilage (from
    their reports: a Dice of the labels compares nothing when both meshings read the same labels)."""
    entries = [r.get("tissues", {}).get(tissue, {}) for r in reports]
    return {"volume_ml": [round(g.volume / 1000.0, 4) for g in grids], "n_elements": [g.n_cells for g in grids],
            **{key: [e.get(key) for e in entries] for key in ("element_size_mm", "element_size_asked_mm", "coverage", "status")}}


def _plot_deviation(deviations: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4), dpi=90)
    for t, d in deviations.items():
        v = d["distances_mm"]
        if len(v):
            ax.hist(v, bins=np.linspace(0, max(2.0, float(np.percentile(v, 99))), 60), histtype="step", density=True,
                    label=f"{t.replace('_', ' ')}: median {d['median']:.2f} mm, coverage {d['coverage']:.0%}")
    ax.set_xlabel("articular surface deviation, mm (rays within 20 deg of the normal)")
    ax.set_ylabel("density")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _plot_contact(ra: dict, rb: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axs = plt.subplots(2, 2, figsize=(9, 6), dpi=90)
    for col, side in enumerate(("medial", "lateral")):
        for row, (key, label) in enumerate((("area_mm2", "contact area, mm^2"), ("peak_pressure_mpa", "peak pressure, MPa"))):
            ax = axs[row, col]
            for r, style, name in ((ra, "-o", "A"), (rb, "--s", "B")):
                inc = loaded(r["increments"])
                ax.plot([i["flexion_deg"] for i in inc], [i[side][key] for i in inc], style, ms=3, label=name)
            ax.set_title(side, fontsize=9)
            ax.set_xlabel("flexion, deg")
            ax.set_ylabel(label)
            ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)

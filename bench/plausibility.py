"""The figures a segmentation's plausibility checks read, on every real label map: the ranges
behind :mod:`kneemesh_core.segmentation.plausibility` (which widens them), and whether every real
map passes its checks.  Also what the anatomical post-processing (:mod:`.postprocess`) would
remove from each true map, as a share of each tissue: on true anatomy it should remove nothing.

    .venv/bin/python bench/plausibility.py [MAPS_OR_GLOBS ...] [--json F]
"""

from __future__ import annotations

import argparse
import glob
import json
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from rich.table import Table

from kneemesh.console import console as make_console

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"
console = make_console()


def one(path: str) -> tuple[str, dict]:
    import SimpleITK as sitk

    from kneemesh_core.knee import load_knee
    from kneemesh_core.segmentation.plausibility import figures
    from kneemesh_core.segmentation.postprocess import clean_classes
    from kneemesh_core.segmentation.preprocess import CANONICAL_TO_NET, NET_CLASSES, NET_ORIENTATION

    labels = load_knee(path).labels
    oriented = sitk.DICOMOrient(labels, NET_ORIENTATION)
    truth = CANONICAL_TO_NET[sitk.GetArrayFromImage(oriented)]
    cleaned = clean_classes(truth, oriented.GetSpacing()[::-1])
    removed = {name: round(float(((truth == c) & (cleaned != c)).sum() / max(1, (truth == c).sum())), 5)
               for c, name in enumerate(NET_CLASSES) if c}
    return path, {**figures(labels), "postprocess_removed": removed}


def main() -> None:
    from kneemesh_core.segmentation.plausibility import check

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("maps", nargs="*")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    maps = [p for m in args.maps for p in sorted(glob.glob(m))] or [
        str(p) for p in sorted((REAL / "oai_labels").glob("*.nii.gz")) + sorted((REAL / "gibbons_imorphics" / "labels").glob("*.nii.gz"))
        + sorted((REAL / "pymskt" / "labels").glob("*.nrrd"))]
    with ProcessPoolExecutor(args.workers) as pool:
        rows = dict(pool.map(one, maps))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    table = Table(title=f"plausibility figures of {len(rows)} real label maps: min / median / max")
    table.add_column("figure")
    table.add_column("min / median / max")
    keys = [("volumes_ml", t) for t in next(iter(rows.values()))["volumes_ml"]]
    keys += [("largest_component", b) for b in ("femur", "tibia", "patella")]
    keys += [("on_bone", c) for c in ("femoral_cartilage", "medial_tibial_cartilage", "lateral_tibial_cartilage", "patellar_cartilage")]
    keys += [("patella_anterior_mm", None), ("patellar_cartilage_facing_mm", None)]
    removed = list(next(iter(rows.values()))["postprocess_removed"])
    keys += [("postprocess_removed", c) for c in removed]
    for group, name in keys:
        v = np.array([r[group][name] if name else r[group] for r in rows.values()
                      if (name is None and group in r) or (name is not None and name in r[group])], float)
        table.add_row(f"{group} {name or ''}", f"{v.min():.3f} / {np.median(v):.3f} / {v.max():.3f}")
    console.print(table)
    for c in removed:
        p = max(rows, key=lambda p: rows[p]["postprocess_removed"][c])
        console.print(f"post-processing removes at most {rows[p]['postprocess_removed'][c]:.2%} of {c} ({Path(p).name})",
                      highlight=False)
    flagged = {Path(p).name: check(f)[1] for p, f in rows.items() if check(f)[0] != "ok"}
    console.print(f"{len(rows) - len(flagged)}/{len(rows)} real maps pass every check", highlight=False)
    for name, reasons in flagged.items():
        console.print(f"  {name}: {'; '.join(reasons)}", highlight=False)


if __name__ == "__main__":
    main()

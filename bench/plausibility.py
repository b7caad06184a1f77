"""The figures a segmentation's plausibility checks read, on every real label map: the ranges
behind :mod:`kneemesh_core.segmentation.plausibility` (which widens them), and whether every real
map passes its checks.

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
    from kneemesh_core.knee import load_knee
    from kneemesh_core.segmentation.plausibility import figures

    return path, figures(load_knee(path).labels)


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
    keys += [("patella_anterior_mm", None)]
    for group, name in keys:
        v = np.array([r[group][name] if name else r[group] for r in rows.values()
                      if (name is None and group in r) or (name is not None and name in r[group])], float)
        table.add_row(f"{group} {name or ''}", f"{v.min():.3f} / {np.median(v):.3f} / {v.max():.3f}")
    console.print(table)
    flagged = {Path(p).name: check(f)[1] for p, f in rows.items() if check(f)[0] != "ok"}
    console.print(f"{len(rows) - len(flagged)}/{len(rows)} real maps pass every check", highlight=False)
    for name, reasons in flagged.items():
        console.print(f"  {name}: {'; '.join(reasons)}", highlight=False)


if __name__ == "__main__":
    main()

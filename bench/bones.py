"""Bone meshing benchmark: KneeMesh against pymskt on the same real label maps.

For every knee: the three bone shells by KneeMesh (sequential in this process,
and wall time with the 2-process pool the CLI uses) and by pymskt (``mskt``:
``BoneMesh.create_mesh`` then ``resample_surface`` to the same number of
points), each measured with the same metrics against the label surface.

    .venv/bin/python bench/bones.py [MAPS ...] [--no-pymskt] [--limit N]

Default maps: every label map in ../shared/data/real (pymskt and oai_labels).
"""

from __future__ import annotations

import argparse
import glob
import statistics
import time
import warnings
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import pyvista as pv
from rich.table import Table

from kneemesh.console import console as make_console
from kneemesh_core.knee import load_knee
from kneemesh_core.surfaces.metrics import surface_distance, topology
from kneemesh_core.surfaces.tissue import SurfaceOptions, label_surface, reconstruct_bone
from kneemesh_core.tissues import BONES, LABEL

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"
console = make_console()


def kneemesh_bone(labels, bone):
    t = time.perf_counter()
    mesh, facts = reconstruct_bone(labels, bone, SurfaceOptions())
    return mesh, time.perf_counter() - t


def _pool_bone(args):
    path, bone = args
    return kneemesh_bone(load_knee(path).labels, bone)[1]


def pymskt_bone(labels, bone, n_points):
    from pymskt.mesh import BoneMesh

    t = time.perf_counter()
    bm = BoneMesh(seg_image=labels, label_idx=LABEL[bone], bone=bone)
    bm.create_mesh(smooth_image=True)
    bm.resample_surface(subdivisions=2, clusters=n_points)
    mesh = pv.wrap(bm.mesh)
    return mesh, time.perf_counter() - t


def measure(mesh, labels, bone, reference):
    topo = topology(mesh)
    sd = surface_distance(mesh, reference)
    label_ml = float((np.asarray(__import__("SimpleITK").GetArrayViewFromImage(labels)) == LABEL[bone]).sum()
                     * np.prod(labels.GetSpacing()) / 1000)
    return {"mean": sd["mean"], "p95": sd["p95"], "vol_err": abs(abs(mesh.volume) / 1000 - label_ml) / label_ml,
            "closed": topo["watertight"] and topo["manifold"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("maps", nargs="*")
    ap.add_argument("--no-pymskt", action="store_true")
    ap.add_argument("--limit", type=int, default=0)
    args = ap.parse_args()
    maps = [Path(p) for m in args.maps for p in sorted(glob.glob(m))] or (
        sorted((REAL / "pymskt" / "labels").glob("*.nrrd")) + sorted((REAL / "oai_labels").glob("*.nii.gz")))
    if args.limit:
        maps = maps[: args.limit]
    warnings.filterwarnings("ignore")
    rows = []
    table = Table(title="bone meshing: KneeMesh vs pymskt (three bones per knee)")
    for col in ("knee", "KM s (seq)", "KM s (2 proc)", "KM dist mean/p95", "KM vol err", "KM closed",
                "pymskt s", "pymskt dist mean/p95", "pymskt vol err", "pymskt closed", "speed-up"):
        table.add_column(col)
    with ProcessPoolExecutor(2) as pool:
        for i, path in enumerate(maps, 1):
            knee = load_knee(path)
            r = {"knee": path.name, "km_s": 0.0, "pm_s": 0.0, "km": [], "pm": []}
            for bone in BONES:
                ref = label_surface(knee.labels, bone)
                mesh, dt = kneemesh_bone(knee.labels, bone)
                r["km_s"] += dt
                r["km"].append(measure(mesh, knee.labels, bone, ref))
                if not args.no_pymskt:
                    pm, dt = pymskt_bone(knee.labels, bone, mesh.n_points)
                    r["pm_s"] += dt
                    r["pm"].append(measure(pm, knee.labels, bone, ref))
            t = time.perf_counter()
            list(pool.map(_pool_bone, [(path, b) for b in ("femur", "tibia", "patella")]))
            r["km_wall"] = time.perf_counter() - t
            rows.append(r)
            # a line per knee, in a terminal or a log: a long run shows that it is alive
            console.print(f"[{i}/{len(maps)}] {path.name}: KneeMesh {r['km_s']:.1f} s, pymskt {r['pm_s']:.1f} s",
                          highlight=False)

            def fmt(ms):
                if not ms:
                    return ["-"] * 3
                return [f"{np.mean([m['mean'] for m in ms]):.3f}/{np.mean([m['p95'] for m in ms]):.3f}",
                        f"{max(m['vol_err'] for m in ms):.2%}", "yes" if all(m["closed"] for m in ms) else "NO"]

            table.add_row(path.name[:28], f"{r['km_s']:.2f}", f"{r['km_wall']:.2f}", *fmt(r["km"]),
                          f"{r['pm_s']:.2f}" if r["pm"] else "-", *fmt(r["pm"]),
                          f"{r['pm_s'] / r['km_s']:.1f}x" if r["pm"] else "-")
    console.print(table)
    km = [m for r in rows for m in r["km"]]
    console.print(f"knees: {len(rows)}  bones: {len(km)}")
    console.print(f"KneeMesh: median {statistics.median(r['km_s'] for r in rows):.2f} s/knee sequential, "
                  f"{statistics.median(r['km_wall'] for r in rows):.2f} s/knee wall on 2 processes "
                  f"(max {max(r['km_wall'] for r in rows):.2f} s); "
                  f"mean distance {np.mean([m['mean'] for m in km]):.3f} mm (worst {max(m['mean'] for m in km):.3f}), "
                  f"p95 {np.mean([m['p95'] for m in km]):.3f} mm (worst {max(m['p95'] for m in km):.3f}), "
                  f"volume error worst {max(m['vol_err'] for m in km):.2%}, "
                  f"closed+manifold {sum(m['closed'] for m in km)}/{len(km)}")
    pm = [m for r in rows for m in r["pm"]]
    if pm:
        console.print(f"pymskt:   median {statistics.median(r['pm_s'] for r in rows):.2f} s/knee; "
                      f"mean distance {np.mean([m['mean'] for m in pm]):.3f} mm (worst {max(m['mean'] for m in pm):.3f}), "
                      f"p95 {np.mean([m['p95'] for m in pm]):.3f} mm (worst {max(m['p95'] for m in pm):.3f}), "
                      f"volume error worst {max(m['vol_err'] for m in pm):.2%}, "
                      f"closed+manifold {sum(m['closed'] for m in pm)}/{len(pm)}")
        ratio = [r["pm_s"] / r["km_s"] for r in rows]
        console.print(f"speed-up (pymskt time / KneeMesh time, same process, sequential): "
                      f"median {statistics.median(ratio):.1f}x, min {min(ratio):.1f}x")


if __name__ == "__main__":
    main()

"""Simulation benchmark: CalculiX runs of the decks of real knees, smoke (to 15 deg), full (to 90 deg) and the
knee bend (from anatomical extension to 90 deg and back, the load rising to 3.5 kN).

    .venv/bin/python bench/simulate.py [MAPS_OR_GLOBS ...] [--full N] [--knee-bend N] [--deformable] [--element-size 1.0]
                                       [--timeout 1800] [--json F] [--threads T]

Default maps: the real label maps in ../shared/data/real (pymskt and oai_labels).  Each knee is meshed
as the job does (bones, cartilage, anatomy, decks), then simulated: smoke on every knee, full flexion on
the first N (listed).  Prints completion and physiology (:func:`kneemesh_core.fe.results.physiology`),
time, the reason of each failure or miss, the contact figures at the end of the run (the knee bend's: back at
extension; its deepest increment in the JSON), the femur's force balance and the plates' peak pressure over the
run; one knee at a time (ccx on ``--threads``).
``--deformable`` adds the smoke run with deformable cartilage and sets its contact (plates' area and peak in
extension and at 15 deg) beside the rigid model's, with the cartilage's peak stress and strains.
"""

from __future__ import annotations

import argparse
import glob
import json
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
from rich.table import Table

from kneemesh.console import console as make_console

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"
console = make_console()


#: The runs of a knee: name -> (smoke, cartilage, activity).
RUNS = {"smoke": (True, "rigid", "flexion"), "deformable": (True, "deformable", "flexion"),
        "full": (False, "rigid", "flexion"), "knee_bend": (False, "rigid", "knee_bend")}


def one(path: str, element_size: float, kinds: list[str], timeout: float) -> dict:
    warnings.filterwarnings("ignore")
    from dataclasses import replace

    from kneemesh_core.fe.results import loaded, plates_peak
    from kneemesh_core.fe.run import FE_DIR, deck_load, simulate
    from kneemesh_core.job import JobRequest, run

    with tempfile.TemporaryDirectory(prefix="kneemesh-sim-") as tmp:
        t0 = time.perf_counter()
        report = run(path, Path(tmp), JobRequest.build(element_size=element_size).job_options(), workers=2)
        mesh_s = time.perf_counter() - t0
        if report.get("fe", {}).get("status") != "ok":
            return {"knee": Path(path).name, "error": report.get("fe", {}).get("reason", "no decks")}
        out = {"knee": Path(path).name, "mesh_seconds": mesh_s, "seating": report["fe"]["seating"]}
        for kind in kinds:
            smoke, cartilage, activity = RUNS[kind]
            try:
                r = simulate(Path(tmp), smoke=smoke, timeout_s=timeout,
                             load=replace(deck_load(Path(tmp) / FE_DIR), cartilage=cartilage, activity=activity))
            except Exception as exc:  # noqa: BLE001 - the benchmark records every failure
                out[kind] = {"completed": False, "reason": f"{type(exc).__name__}: {exc}", "seconds": 0.0}
                continue
            last = r["increments"][-1] if r["increments"] else {}
            peak = plates_peak(r["increments"])[0]
            out[kind] = {"completed": r["completed"], "reason": r["reason"], "seconds": r["seconds"],
                         "reached": r["reached_flexion_deg"], "last": last, "plate_peak_mpa": peak,
                         "first": next(iter(loaded(r["increments"])), {}),
                         "deepest": max(loaded(r["increments"]), key=lambda x: x["flexion_deg"] or 0.0, default={}),
                         "physiology_reasons": r["physiology_reasons"]}
        return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("maps", nargs="*")
    ap.add_argument("--full", type=int, default=0, help="also run the full flexion on the first N knees")
    ap.add_argument("--knee-bend", type=int, default=0, help="also the knee bend on the first N knees")
    ap.add_argument("--deformable", action="store_true", help="also the smoke run with deformable cartilage")
    ap.add_argument("--element-size", type=float, default=1.0)
    ap.add_argument("--timeout", type=float, default=1800.0)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--threads", type=int, help="ccx threads per run (default: the product's, up to 2)")
    args = ap.parse_args()
    if args.threads:
        import kneemesh_core.fe.simulate

        kneemesh_core.fe.simulate.CCX_THREADS = args.threads
    maps = [p for m in args.maps for p in sorted(glob.glob(m))] or [
        str(p) for p in sorted((REAL / "pymskt" / "labels").glob("*.nrrd")) + sorted((REAL / "oai_labels").glob("*.nii.gz"))]
    rows = []
    for i, m in enumerate(maps):
        r = one(m, args.element_size, ["smoke", *(["deformable"] if args.deformable else []), *(["full"] if i < args.full else []),
                                       *(["knee_bend"] if i < args.knee_bend else [])], args.timeout)
        rows.append(r)
        msg = r.get("error") or "; ".join(
            f"{k}: {'completed' if r[k]['completed'] else 'stopped (' + str(r[k]['reason']) + ')'} in {r[k]['seconds']:.0f} s"
            for k in RUNS if k in r)
        console.print(f"[{i + 1}/{len(maps)}] {r['knee']}: {msg}", highlight=False)
        if args.json:
            args.json.write_text(json.dumps(rows, indent=1, default=float))
    table = Table(title=f"CalculiX runs of {len(rows)} knees (element size {args.element_size} mm)")
    for col in ("run", "completed", "completed, physiological", "seconds: median (max)", "medial N / mm^2 / peak MPa", "lateral", "balance error max",
                "plates' peak MPa over the run: median (max)"):
        table.add_column(col)
    for kind in RUNS:
        rs = [r[kind] for r in rows if kind in r]
        if not rs:
            continue
        done = [x for x in rs if x["completed"] and x.get("last")]
        secs = np.array([x["seconds"] for x in rs])

        def fig(side: str) -> str:
            if not done:
                return "-"
            v = np.array([[x["last"][side]["force_n"], x["last"][side]["area_mm2"], x["last"][side]["peak_pressure_mpa"]]
                          for x in done])
            return " / ".join(f"{q:.0f}" if j < 2 else f"{q:.1f}" for j, q in enumerate(np.median(v, 0)))

        table.add_row(kind, f"{len(done)}/{len(rs)}", f"{sum(not x['physiology_reasons'] for x in done)}/{len(rs)}", f"{np.median(secs):.0f} ({secs.max():.0f})", fig("medial"), fig("lateral"),
                      f"{max((x['last']['balance_error'] for x in done), default=float('nan')):.4f}",
                      f"{np.median([x['plate_peak_mpa'] for x in done]):.1f} ({max(x['plate_peak_mpa'] for x in done):.1f})"
                      if done else "-")
    console.print(table)
    if args.deformable:
        console.print(deformable_table(rows))
    for r in rows:
        for kind in RUNS:
            if kind in r and not r[kind]["completed"]:
                console.print(f"{r['knee']} {kind}: {r[kind]['reason']}", highlight=False)
            elif kind in r and r[kind]["physiology_reasons"]:
                console.print(f"{r['knee']} {kind}: completed, but " + "; ".join(r[kind]["physiology_reasons"]), highlight=False)


def deformable_table(rows: list[dict]) -> Table:
    """Deformable against rigid cartilage on the knees where both smoke runs completed: per plate, the
    medians of area (mm^2) and peak pressure (MPa) in extension and at 15 deg, and of the cartilages' peaks."""
    both = [r for r in rows if r.get("smoke", {}).get("completed") and r.get("deformable", {}).get("completed")]
    table = Table(title=f"deformable against rigid cartilage, smoke runs, {len(both)} knees (medians; area mm^2 / peak MPa)")
    for col in ("plate", "when", "rigid", "deformable", "area ratio (median, range)"):
        table.add_column(col)
    for side in ("medial", "lateral"):
        for when in ("first", "last"):
            fig = {k: np.array([[r[k][when][side]["area_mm2"], r[k][when][side]["peak_pressure_mpa"]] for r in both])
                   for k in ("smoke", "deformable")} if both else {}
            ratio = fig["deformable"][:, 0] / np.maximum(fig["smoke"][:, 0], 1e-9) if both else np.array([np.nan])
            table.add_row(side, "extension" if when == "first" else "15 deg",
                          *(" / ".join(f"{v:.1f}" for v in np.median(fig[k], 0)) if both else "-" for k in ("smoke", "deformable")),
                          f"{np.median(ratio):.2f} ({ratio.min():.2f}-{ratio.max():.2f})")
    for tissue in sorted({t for r in both for t in r["deformable"]["last"].get("cartilage", {})}):
        peaks = [r["deformable"]["last"]["cartilage"][tissue] for r in both if tissue in r["deformable"]["last"].get("cartilage", {})]
        table.add_row(tissue, "15 deg", "", "von Mises {:.1f} MPa, compressive {:.2f}, shear {:.2f}".format(
            *(np.median([p[k] for p in peaks]) for k in ("peak_von_mises_mpa", "peak_compressive_strain", "peak_shear_strain"))), "")
    return table


if __name__ == "__main__":
    main()

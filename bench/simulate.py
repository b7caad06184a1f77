"""Simulation benchmark: CalculiX runs of the decks of real knees, smoke (to 15 deg) and full (to 90 deg).

    .venv/bin/python bench/simulate.py [MAPS_OR_GLOBS ...] [--full N] [--element-size 1.0] [--timeout 1800] [--json F] [--threads T]

Default maps: the real label maps in ../shared/data/real (pymskt and oai_labels).  Each knee is meshed
as the job does (bones, cartilage, anatomy, decks), then simulated: smoke on every knee, full flexion on
the first N (listed).  Prints completion and physiology (:func:`kneemesh_core.fe.results.physiology`),
time, the reason of each failure or miss, the contact figures at the end of the run, the femur's force
balance and the plates' peak pressure over the run; one knee at a time (ccx on ``--threads``).
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


def one(path: str, element_size: float, full: bool, timeout: float) -> dict:
    warnings.filterwarnings("ignore")
    from kneemesh_core.fe.results import plates_peak
    from kneemesh_core.fe.run import simulate
    from kneemesh_core.job import JobRequest, run

    with tempfile.TemporaryDirectory(prefix="kneemesh-sim-") as tmp:
        t0 = time.perf_counter()
        report = run(path, Path(tmp), JobRequest.build(element_size=element_size).job_options(), workers=2)
        mesh_s = time.perf_counter() - t0
        if report.get("fe", {}).get("status") != "ok":
            return {"knee": Path(path).name, "error": report.get("fe", {}).get("reason", "no decks")}
        out = {"knee": Path(path).name, "mesh_seconds": mesh_s, "seating": report["fe"]["seating"]}
        for kind in ("smoke", "full") if full else ("smoke",):
            try:
                r = simulate(Path(tmp), smoke=kind == "smoke", timeout_s=timeout)
            except Exception as exc:  # noqa: BLE001 - the benchmark records every failure
                out[kind] = {"completed": False, "reason": f"{type(exc).__name__}: {exc}", "seconds": 0.0}
                continue
            last = r["increments"][-1] if r["increments"] else {}
            peak = plates_peak(r["increments"])[0]
            out[kind] = {"completed": r["completed"], "reason": r["reason"], "seconds": r["seconds"],
                         "reached": r["reached_flexion_deg"], "last": last, "plate_peak_mpa": peak,
                         "physiology_reasons": r["physiology_reasons"]}
        return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("maps", nargs="*")
    ap.add_argument("--full", type=int, default=0, help="also run the full flexion on the first N knees")
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
        r = one(m, args.element_size, i < args.full, args.timeout)
        rows.append(r)
        msg = r.get("error") or "; ".join(
            f"{k}: {'completed' if r[k]['completed'] else 'stopped (' + str(r[k]['reason']) + ')'} in {r[k]['seconds']:.0f} s"
            for k in ("smoke", "full") if k in r)
        console.print(f"[{i + 1}/{len(maps)}] {r['knee']}: {msg}", highlight=False)
        if args.json:
            args.json.write_text(json.dumps(rows, indent=1, default=float))
    table = Table(title=f"CalculiX runs of {len(rows)} knees (element size {args.element_size} mm)")
    for col in ("run", "completed", "completed, physiological", "seconds: median (max)", "medial N / mm^2 / peak MPa", "lateral", "balance error max",
                "plates' peak MPa over the run: median (max)"):
        table.add_column(col)
    for kind in ("smoke", "full"):
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
    for r in rows:
        for kind in ("smoke", "full"):
            if kind in r and not r[kind]["completed"]:
                console.print(f"{r['knee']} {kind}: {r[kind]['reason']}", highlight=False)
            elif kind in r and r[kind]["physiology_reasons"]:
                console.print(f"{r['knee']} {kind}: completed, but " + "; ".join(r[kind]["physiology_reasons"]), highlight=False)


if __name__ == "__main__":
    main()

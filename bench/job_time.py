"""Whole-knee job time: `kneemesh mesh` as a lab runs it, one knee after another, on this machine.

    .venv/bin/python bench/job_time.py [MAPS_OR_GLOBS ...] [--every 4] [--workers 2] [--json F]
    .venv/bin/python bench/job_time.py --cohort --simulate full --json cohort.json [--resume]

Default maps: every 4th OAI label map in ../shared/data/real/oai_labels (10 knees; OAI-size
384x384x160 maps); `--cohort`: all 126 real maps (the 40 OAI maps, the 2 pymskt maps and the 84 of the
paper's cohort, interleaved so that a run stopped early is a fair sample of all three). Each knee is
one `kneemesh mesh` process (start-up included), so run this on an idle machine. `--simulate smoke|full`
adds the CalculiX run (a cohort study's cost: meshing plus the activity); the table then gains its
time and the run's outcome. With `--json`, every knee is written as it ends; `--resume` skips the knees
already in that file, so a long cohort run can be continued. Prints per knee the wall time and where
it went along the critical path, read from the job's step records: start-up (process start to the
first step), then how much later each stage of the plan ended than the one before (ingest; meshing:
bones and cartilage meshes; blends: the cartilages' blends beside the anatomy; conform; decks beside the
overlaps; report) with its longest step, and the exit; then median, p90 and max of each.
"""

from __future__ import annotations

import argparse
import datetime as dt
import glob
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from rich.table import Table

from kneemesh.console import console as make_console
from kneemesh_core.job.options import JobOptions
from kneemesh_core.job.plan import plan

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT.parent / "shared" / "data" / "real"
console = make_console()


def _t(stamp: str) -> float:
    return dt.datetime.fromisoformat(stamp).timestamp()


def cohort_maps() -> list[Path]:
    """The 126 real label maps, the three sets interleaved (OAI, the paper's cohort, pymskt in turn)."""
    sets = [sorted((REAL / "oai_labels").glob("*.nii.gz")),
            sorted((REAL / "gibbons_imorphics" / "labels").glob("*.nii.gz")),
            sorted((REAL / "pymskt" / "labels").glob("*.nrrd"))]
    return [s[i] for i in range(max(map(len, sets))) for s in sets if i < len(s)]


def time_job(path: Path, workers: int, tmp: Path, simulate: str = "none") -> dict:
    """Run one job as a process and return its wall time and where it went: the start-up (process
    start to the first step), then for each stage of its plan how much later than the stage before
    it ended (its steps may start before that stage ends: each step waits only for what it reads)
    and its longest step, and the exit after the last step."""
    out = tmp / path.name.split(".")[0]
    t0 = time.time()
    proc = subprocess.run([sys.executable, "-m", "kneemesh", "mesh", str(path), "--out", str(out),
                           "--workers", str(workers), "--simulate", simulate], capture_output=True, text=True)
    wall = time.time() - t0
    if proc.returncode != 0:
        return {"knee": path.name, "wall": wall, "error": proc.stderr.strip().splitlines()[-1:]}
    steps = {p.stem: json.loads(p.read_text()) for p in (out / "steps").glob("*.json")}
    report = json.loads((out / "report.json").read_text())
    first = min(_t(r["started_at"]) for r in steps.values())
    stages, end = [], first
    for stage in plan(JobOptions(simulate=simulate)):
        recs = {s: steps[s] for s in stage if s in steps}
        if not recs:
            continue
        longest = max(recs, key=lambda s: recs[s]["seconds"])
        stage_end = max(end, max(_t(r["finished_at"]) for r in recs.values()))
        stages.append({"stage": _stage_name(stage), "span": stage_end - end, "longest": longest,
                       "longest_s": recs[longest]["seconds"]})
        end = stage_end
    return {"knee": path.name, "wall": wall, "startup": first - t0, "stages": stages, "exit": t0 + wall - end,
            "verdict": report.get("verdict", {}).get("status"), "simulation": _simulation(report),
            "steps": {s: {"seconds": r["seconds"], "start": _t(r["started_at"]) - first} for s, r in steps.items()}}


def _simulation(report: dict) -> dict | None:
    """The CalculiX run's outcome as the report gives it: completed, how far, ccx's own seconds."""
    sim = report.get("simulation")
    if not sim:
        return None
    return {k: sim.get(k) for k in ("status", "completed", "physiological", "reason", "reached_flexion_deg",
                                    "target_flexion_deg", "solver_seconds")}


def _stage_name(stage: tuple[str, ...]) -> str:
    """A stage's name in the table: its step, or what its steps mesh."""
    return ("bones" if "femur" in stage else "cartilages" if "femoral_cartilage" in stage
            else "decks" if "decks" in stage else "simulation" if "simulate" in stage else "+".join(stage))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("maps", nargs="*")
    ap.add_argument("--every", type=int, default=4, help="default maps: every Nth OAI map (default 4: 10 knees)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--cohort", action="store_true", help="all 126 real maps (see above)")
    ap.add_argument("--simulate", choices=("none", "smoke", "full"), default="none")
    ap.add_argument("--json", type=Path, help="also write every knee's timings to this file, each as it ends")
    ap.add_argument("--resume", action="store_true", help="skip the knees already in --json")
    a = ap.parse_args()
    maps = ([Path(p) for m in a.maps for p in sorted(glob.glob(m))] if a.maps
            else cohort_maps() if a.cohort else sorted((REAL / "oai_labels").glob("*.nii.gz"))[:: a.every])
    rows = json.loads(a.json.read_text()) if a.resume and a.json and a.json.exists() else []
    done = {r["knee"] for r in rows}
    with tempfile.TemporaryDirectory(prefix="kneemesh-jobtime-") as tmpdir:
        for m in maps:
            if m.name in done:
                continue
            r = time_job(m, a.workers, Path(tmpdir), a.simulate)
            shutil.rmtree(Path(tmpdir) / m.name.split(".")[0], ignore_errors=True)
            rows.append(r)
            if a.json:
                a.json.write_text(json.dumps(rows, indent=1))
            parts = ", ".join(f"{s['stage']} {s['span']:.1f} ({s['longest']} {s['longest_s']:.1f})" for s in r.get("stages", []))
            sim = r.get("simulation") or {}
            ran = (f"; ccx {sim['solver_seconds']:.0f} s, {'completed' if sim['completed'] else 'stopped'} at "
                   f"{sim['reached_flexion_deg']} deg" if sim.get("solver_seconds") is not None else "")
            console.print(f"{r['knee']}: {r['wall']:.1f} s" + (f" [red]{r['error']}" if "error" in r else
                                                                 f"; start-up {r['startup']:.1f}, {parts}; {r['verdict']}{ran}"))
    ok = [r for r in rows if "error" not in r]
    sims = [r["simulation"] for r in ok if r.get("simulation")]
    title = (f"Whole-knee job, `kneemesh mesh --workers {a.workers} --simulate {a.simulate}`, "
             f"{len(ok)}/{len(rows)} knees meshed")
    if a.simulate != "none":
        title += (f", {sum(bool(s['completed']) for s in sims)}/{len(rows)} runs completed, "
                  f"{sum(bool(s['physiological']) for s in sims)} physiological")
    table = Table(title=title + f"; {sum(r['wall'] for r in rows) / 3600:.2f} h of wall time in all")
    cols_named = ("", "wall s", "start-up s", "ingest s", "meshing s", "blends s", "conform to report s", "exit s")
    for col in cols_named + (("simulation s",) if a.simulate != "none" else ()):
        table.add_column(col, justify="right")

    def span(r: dict, *names: str) -> float:
        return sum(s["span"] for s in r["stages"] if s["stage"] in names)

    cols = [lambda r: r["wall"], lambda r: r["startup"], lambda r: span(r, "ingest"), lambda r: span(r, "bones"),
            lambda r: span(r, "cartilages"), lambda r: span(r, "conform", "decks", "report"), lambda r: r["exit"]]
    if a.simulate != "none":
        cols.append(lambda r: span(r, "simulation"))
    for label, f in (("median", statistics.median), ("p90", lambda v: sorted(v)[int(0.9 * (len(v) - 1))]), ("max", max)):
        table.add_row(label, *(f"{f([c(r) for r in ok]):.1f}" for c in cols))
    console.print(table)
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()

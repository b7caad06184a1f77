"""The cohort commands a lab runs on its own machine: ``submit`` a cohort to a server and bring its
results home, ``compare`` two results of one knee, ``report`` over a cohort tree."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Optional

import typer

from kneemesh.cli.app import PresetOpt, app, clear_errors, err, out, with_mesh_flags
from kneemesh.cli.render import compare_table
from kneemesh_core import KneeMeshError
from kneemesh_core.job import JobRequest


@app.command()
@with_mesh_flags
def submit(
    cohort: Path = typer.Argument(..., metavar="COHORT", help="A cohort folder (DICOM series, NIfTI/NRRD/MHA volumes) or a "
                                                             "CSV manifest with columns id, path[, side, input_type, visit]."),
    server: str = typer.Option(..., "--server", help="The KneeMesh server, e.g. http://localhost:8000."),
    key: Optional[str] = typer.Option(None, "--key", envvar="KNEEMESH_API_KEY", help="API key (or $KNEEMESH_API_KEY)."),
    out_dir: Path = typer.Option(..., "--out", help="Results: one folder per knee mirroring the cohort, summary.csv."),
    concurrency: int = typer.Option(4, "--concurrency", min=1, help="Knees in flight at once."),
    input_type: Optional[str] = typer.Option(None, "--input-type", help="labels or image for every volume "
                                                                           "(default: judged from each volume)."),
    preset: Optional[str] = PresetOpt,
    poll: float = typer.Option(2.0, "--poll", min=0.1, help="Seconds between status checks of a job."),
    mesh_flags: dict = None,
):
    """Submit a cohort to a KneeMesh server and bring every knee's results home: resumable (rerun the
    same command after Ctrl-C, a crash or a server restart), every file checked against its SHA-256."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from kneemesh.cohort.client import Api
    from kneemesh.cohort.discover import find_knees
    from kneemesh.cohort.submit import DONE, SUMMARY_FILE, submit_cohort

    with clear_errors():
        if input_type not in (None, "labels", "image"):
            raise KneeMeshError("bad_option", f"--input-type {input_type!r}: expected labels or image.")
        options = {k: v for k, v in {"preset": preset, **mesh_flags}.items() if v is not None}
        JobRequest.build(**options)
        knees = find_knees(cohort, input_type)
    out.print(f"{len(knees)} knees in {cohort}; results in {out_dir}", highlight=False)
    api = Api(server, key)
    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
    with Progress(*columns, console=err, transient=False) as bar:
        task = bar.add_task("knees", total=len(knees))
        shown: dict[str, str] = {}  # each knee in flight: where its job stands
        lock = threading.Lock()

        def progress(knee, line):
            with lock:
                if shown.get(knee.id) != line:  # a line when it changes; in a terminal, a row that updates
                    shown[knee.id] = line
                    if bar.console.is_terminal:
                        bar.update(task, description=" | ".join(f"{k}: {v}" for k, v in shown.items()))
                    else:
                        bar.console.print(f"{knee.id}: {line}", highlight=False)

        def done(knee, rec):
            with lock:
                shown.pop(knee.id, None)
                bar.update(task, description="knees", advance=1)
            what = rec.get("verdict") if rec.get("state") == DONE else rec.get("state") or "unfinished"
            bar.console.print(f"{knee.id}: {what}" + (f" ({rec.get('reason') or rec.get('last_error')})"
                                                      if rec.get("state") != DONE else ""), highlight=False)

        try:
            records = submit_cohort(knees, api, out_dir, options, concurrency, poll, done, progress)
        except KeyboardInterrupt:
            err.print("interrupted: rerun the same command to resume (finished knees are kept).")
            raise typer.Exit(130)
        finally:
            api.close()
    counts = {s: sum(r.get("state") == s for r in records) for s in (DONE, "failed", "rejected")}
    unfinished = len(records) - sum(counts.values())
    out.print(f"done {counts[DONE]}, failed {counts['failed']}, rejected {counts['rejected']}, unfinished {unfinished}; "
              f"{out_dir / SUMMARY_FILE}", highlight=False)
    if unfinished:
        raise typer.Exit(3)


@app.command()
def compare(
    a: Path = typer.Argument(..., metavar="A", help="A KneeMesh result folder (e.g. from manual labels)."),
    b: Path = typer.Argument(..., metavar="B", help="Another result of the same knee (e.g. from predicted labels)."),
    out_dir: Path = typer.Option(..., "--out", help="Where compare.json, deviation.png and contact.png go."),
):
    """Two results of one knee: Dice per tissue, articular surface deviation A to B (rays within 20 deg
    of the normal; percent nodal coverage), and RMS differences of the contact curves when both were simulated."""
    from kneemesh.cohort.compare import compare as run_compare

    with clear_errors():
        s = run_compare(a, b, out_dir)
    out.print(compare_table(f"{a} vs {b}", s))
    for name, d in (s.get("contact") or {}).get("differences", {}).items():
        if d and d["rms"] is not None:
            out.print(f"{name}: RMS {d['rms']:.3g}" + (f" ({d['rms_of_range']:.0%} of A's range)" if d["rms_of_range"] is not None else ""),
                      highlight=False)
    out.print(f"written: {out_dir / 'compare.json'}")


@app.command()
def report(
    cohort_out: Path = typer.Argument(..., metavar="OUT", help="A cohort result tree (e.g. the --out of kneemesh submit)."),
    out_file: Optional[Path] = typer.Option(None, "--out", help="The HTML file (default: OUT/report.html)."),
):
    """One self-contained HTML page over a cohort tree: verdicts, per-tissue quality, timings, failures, contact curves."""
    from kneemesh.cohort.report import collect, write_report

    if not cohort_out.is_dir() or not collect(cohort_out)["knees"] and not (cohort_out / "kneemesh-submit.json").exists():
        err.print(f"[bold red]error[/] (no_knees): {cohort_out}: expected a folder holding KneeMesh results (report.json files).")
        raise typer.Exit(2)
    out.print(f"written: {write_report(cohort_out, out_file)}")


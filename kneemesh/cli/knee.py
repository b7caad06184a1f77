"""The commands on one knee: ``inspect``, ``phantom``, ``mesh``, ``run`` (an image: segment, then mesh)
and ``simulate``, in this process."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Optional

import typer

from kneemesh.cli.app import (LabelsOpt, PresetOpt, SideOpt, WorkersOpt, app, clear_errors, err, job_option, out,
                              with_mesh_flags)
from kneemesh.cli.render import inspect_table, stage_table, tissue_table, verdict_lines
from kneemesh.console import step_progress
from kneemesh_core.job import SIMULATE, STAGES, JobRequest


@app.command()
def inspect(
    file: Path = typer.Argument(..., help="Label map (NIfTI, NRRD, MHA, DICOM folder or .zip)."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object for scripts."),
    preset: Optional[str] = PresetOpt,
    labels: Optional[str] = LabelsOpt,
    side: Optional[str] = SideOpt,
):
    """Size, spacing, orientation, label convention, side and tissue volumes of a label map."""
    from kneemesh_core.knee import describe, load_knee

    with clear_errors():
        info = describe(load_knee(file, preset=preset, labels=labels, side=side))
    if as_json:
        sys.stdout.write(json.dumps(info) + "\n")
        return
    out.print(inspect_table(str(file), info))


@app.command()
def phantom(
    out_dir: Path = typer.Argument(..., help="Folder to write image.nii.gz and labels.nii.gz into."),
    seed: int = typer.Option(0, "--seed", help="Random seed: the same seed gives the same knee."),
    side: str = typer.Option("right", "--side", help="left or right."),
    severity: int = typer.Option(0, "--severity", min=0, max=3, help="OA severity 0 (healthy) to 3 (severe)."),
):
    """Write a synthetic OAI-like DESS knee and its labels (canonical preset)."""
    from kneemesh_core.phantom import write_phantom

    with clear_errors():
        paths = write_phantom(out_dir, seed=seed, side=side, severity=severity)
    for p in paths.values():
        out.print(str(p))


@app.command()
@with_mesh_flags
def mesh(
    labels_file: Path = typer.Argument(..., metavar="LABELS", help="Label map (NIfTI, NRRD, MHA, DICOM)."),
    out_dir: Path = typer.Option(..., "--out", help="Output folder: meshes/, surfaces/, report.json."),
    preset: Optional[str] = PresetOpt,
    labels: Optional[str] = LabelsOpt,
    side: Optional[str] = SideOpt,
    workers: int = WorkersOpt,
    mesh_flags: dict = None,
):
    """Mesh a knee: closed bone shells (meshes/*.vtp), all-hex cartilage (meshes/*.vtu), report.json."""
    with clear_errors():
        request = JobRequest.build(preset=preset, labels=labels, side=side, **mesh_flags)
    run_job(labels_file, out_dir, request, workers)


@app.command("run")
@with_mesh_flags
def run_image(
    image_file: Path = typer.Argument(..., metavar="IMAGE", help="Sagittal knee MRI (NIfTI, NRRD, MHA, DICOM folder or zip)."),
    out_dir: Path = typer.Option(..., "--out", help="Output folder: labels.nrrd, meshes/, surfaces/, report.json."),
    model: Optional[Path] = job_option("model", "--model"),
    side: Optional[str] = SideOpt,
    workers: int = WorkersOpt,
    mesh_flags: dict = None,
):
    """Segment a knee MRI, then mesh it: the whole job from an image, in this process."""
    with clear_errors():
        request = JobRequest.build(input_type="image", model=str(model) if model else None, side=side, **mesh_flags)
    run_job(image_file, out_dir, request, workers)


def run_job(input_path: Path, out_dir: Path, request: JobRequest, workers: int) -> None:
    """Run the pipeline in-process with a progress line per step, then print the report's tables;
    exit 1 when a tissue failed."""
    from kneemesh_core.job import run

    with clear_errors(), step_progress(err) as progress:
        report = run(input_path, out_dir, request.job_options(), workers=workers, progress=progress)
    out.print(tissue_table(f"{out_dir} ({report['input']['side']} knee, {report['input']['preset']} labels)", report))
    stages = stage_table(report)
    if stages is not None:
        out.print(stages)
    out.print(verdict_lines(report, Path(out_dir)), highlight=False)
    if report["summary"]["failed"]:
        raise typer.Exit(1)


@app.command()
def simulate(
    job_dir: Path = typer.Argument(..., metavar="DIR", help="A job folder written by `kneemesh mesh` or `kneemesh run`."),
    to: Optional[float] = typer.Option(None, "--to", min=1.0, max=120.0,
                                       help="Flexion to reach, deg (default: the deck's 90): from the image pose, or "
                                            "anatomical for the knee bend."),
    smoke: bool = typer.Option(False, "--smoke", help="A few increments to 15 deg: a quick proof that the deck runs."),
    timeout: float = typer.Option(1800.0, "--timeout", min=10.0, help="Stop ccx after this many seconds."),
    joint_load: Optional[float] = job_option("joint_load", "--joint-load"),
    medial_offset: Optional[float] = job_option("medial_offset", "--medial-offset"),
    quadriceps: Optional[float] = job_option("quadriceps", "--quadriceps"),
    fe_cartilage: Optional[str] = job_option("fe_cartilage", "--fe-cartilage"),
    activity: Optional[str] = job_option("activity", "--activity"),
    peak_load: Optional[float] = job_option("peak_load", "--peak-load"),
):
    """Run CalculiX on a job's decks (fe/knee_ccx.inp): contact forces, areas and pressures over flexion
    in fe/results.json and fe/contact.png (fe/smoke/ for --smoke); another load, medial offset, quadriceps
    force or cartilage than the decks' runs a model of its own in its own folder (fe/smoke_1500N_300N_10mm_rigid/,
    say); a knee bend runs in fe/knee_bend_90_3500N/ (say).  Deformable cartilage adds its stress and strain
    (cartilage_<tissue>.vtu) and takes minutes."""
    from dataclasses import replace

    from kneemesh_core.fe.run import FE_DIR, deck_load, simulate as run_simulation, simulation_entry

    with clear_errors():
        decks = deck_load(job_dir / FE_DIR)
        load = None
        asked = {"joint_load_n": joint_load, "medial_offset_mm": medial_offset, "quadriceps_n": quadriceps,
                 "cartilage": fe_cartilage, "activity": activity, "peak_load_n": peak_load}
        if any(v is not None for v in asked.values()):
            request = JobRequest.build(joint_load=joint_load, medial_offset=medial_offset, quadriceps=quadriceps,
                                       fe_cartilage=fe_cartilage, activity=activity, peak_load=peak_load)  # a job's bounds
            load = replace(decks or request.job_options().load, **{k: v for k, v in asked.items() if v is not None})
        r = run_simulation(job_dir, flexion_deg=to, smoke=smoke, timeout_s=timeout, load=load)
    entry = simulation_entry(r, "smoke" if smoke else r["activity"], r["folder"])
    out.print(f"simulation: {entry['status']}: {STAGES[SIMULATE].summary(entry)}"
              + "".join(f"\n  {reason}" for reason in entry["reasons"]), highlight=False)
    if not r["completed"]:
        raise typer.Exit(1)

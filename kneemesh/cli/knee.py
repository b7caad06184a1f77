"""``kneemesh`` command line: the same pipeline as the service, run in-process."""

from __future__ import annotations

import functools
import json
import logging
import os
import sys
import threading
from inspect import Parameter, signature
from contextlib import contextmanager
from pathlib import Path
from typing import Optional

import typer
from rich.table import Table

from kneemesh.console import console, step_progress
from kneemesh_core import KneeMeshError, __version__
from kneemesh_core.fe.results import CONTACTS
from kneemesh_core.job import JobRequest

app = typer.Typer(add_completion=False, no_args_is_help=True, help="Knee MRI or label maps to FE-ready knee models.")
out = console()
err = console(stderr=True)


def entry() -> None:
    """The ``kneemesh`` command: :data:`app`, then out of the process without the interpreter's
    teardown once nothing is left running.  By then every output is written; freeing the
    meshing libraries' modules and objects would add about 0.4 s to each knee of a cohort run
    knee by knee (``kneemesh mesh``)."""
    try:
        app()
        code = 0
    except SystemExit as exc:  # click ends every command this way, with the exit status
        if threading.active_count() > 1 or not isinstance(exc.code, (int, type(None))):
            raise  # a thread still running, or a message to print: Python's own exit
        code = exc.code or 0
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def job_option(field: str, *flags: str):
    """A command-line flag for one option of :class:`JobRequest`, with its help and default from
    there (the flag's own default is None: not given, so the request's default applies)."""
    f = JobRequest.model_fields[field]
    default = "" if f.default is None else f" (default: {f.default})"
    return typer.Option(None, *flags, help=f"{f.description}{default}", show_default=False)


PresetOpt = job_option("preset", "--preset")
LabelsOpt = typer.Option(None, "--labels", help="Custom mapping 'femur=5,tibia=6,...' or a JSON file.")
SideOpt = job_option("side", "--side")
WorkersOpt = typer.Option(2, "--workers", min=1, help="Processes meshing tissues in parallel.")
#: The meshing flags `mesh` and `run` share: name -> (type, flag).
MESH_FLAGS = {
    "only": (Optional[str], job_option("only", "--only")),
    "stl": (Optional[bool], job_option("stl", "--stl/--no-stl")),
    "bone_edge": (Optional[float], job_option("bone_edge", "--bone-edge")),
    "element_size": (Optional[float], job_option("element_size", "--element-size")),
    "layers": (Optional[int], job_option("layers", "--layers")),
    "blend": (Optional[bool], job_option("blend", "--blend/--no-blend")),
    "blend_angle": (Optional[float], job_option("blend_angle", "--blend-angle")),
    "simulate": (Optional[str], job_option("simulate", "--simulate")),
    "fe_cartilage": (Optional[str], job_option("fe_cartilage", "--fe-cartilage")),
}


def with_mesh_flags(command):
    """Give a command the shared :data:`MESH_FLAGS` (after its own parameters); they reach it as
    one dict, ``mesh_flags``."""
    sig = signature(command, eval_str=True)
    own = [p for p in sig.parameters.values() if p.name != "mesh_flags"]
    shared = [Parameter(name, Parameter.KEYWORD_ONLY, default=flag, annotation=kind)
              for name, (kind, flag) in MESH_FLAGS.items()]

    @functools.wraps(command)
    def wrapper(*args, **kwargs):
        return command(*args, mesh_flags={name: kwargs.pop(name) for name in MESH_FLAGS}, **kwargs)

    wrapper.__signature__ = sig.replace(parameters=own + shared)
    return wrapper


@contextmanager
def _clear_errors():
    """Bad input ends in one red line and a non-zero exit, never a traceback."""
    try:
        yield
    except KneeMeshError as exc:
        err.print(f"[bold red]error[/] ({exc.code}): {exc.message}", highlight=False, soft_wrap=True)
        raise typer.Exit(2)


def _version(value: bool):
    if value:
        out.print(f"kneemesh {__version__}")
        raise typer.Exit()


@app.callback()
def main(
    version: Optional[bool] = typer.Option(None, "--version", callback=_version, is_eager=True, help="Print the version."),
):
    """KneeMesh: robust hexahedral knee models from MRI and label maps."""


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

    with _clear_errors():
        info = describe(load_knee(file, preset=preset, labels=labels, side=side))
    if as_json:
        sys.stdout.write(json.dumps(info) + "\n")
        return
    t = Table(title=str(file), show_header=False)
    t.add_row("size (voxels)", " x ".join(map(str, info["shape"])))
    t.add_row("spacing (mm)", " x ".join(f"{s:.4f}" for s in info["spacing_mm"]))
    t.add_row("origin (LPS mm)", ", ".join(f"{o:.2f}" for o in info["origin_mm"]))
    t.add_row("axes point toward", info["orientation"])
    t.add_row("label convention", info["preset"])
    t.add_row("side", f"{info['side']} (by {info['side_method']})")
    for tissue, ml in info["tissues"].items():
        t.add_row(tissue, f"{ml:.2f} ml")
    out.print(t)


@app.command()
def phantom(
    out_dir: Path = typer.Argument(..., help="Folder to write image.nii.gz and labels.nii.gz into."),
    seed: int = typer.Option(0, "--seed", help="Random seed: the same seed gives the same knee."),
    side: str = typer.Option("right", "--side", help="left or right."),
    severity: int = typer.Option(0, "--severity", min=0, max=3, help="OA severity 0 (healthy) to 3 (severe)."),
):
    """Write a synthetic OAI-like DESS knee and its labels (canonical preset)."""
    from kneemesh_core.phantom import write_phantom

    with _clear_errors():
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
    with _clear_errors():
        request = JobRequest.build(preset=preset, labels=labels, side=side, **mesh_flags)
    _run_job(labels_file, out_dir, request, workers)


def _run_job(input_path: Path, out_dir: Path, request: JobRequest, workers: int) -> None:
    """Run the pipeline in-process with a progress line per step, then print the report table."""
    from kneemesh_core.job import run

    with _clear_errors(), step_progress(err) as progress:
        report = run(input_path, out_dir, request.job_options(), workers=workers, progress=progress)
    t = Table(title=f"{out_dir} ({report['input']['side']} knee, {report['input']['preset']} labels)")
    for col in ("tissue", "status", "s", "elements", "volume ml", "label ml", "quality", "fidelity"):
        t.add_column(col)
    for tissue, e in report["tissues"].items():
        if e["status"] == "failed" and "n_elements" not in e and "n_cells" not in e:  # no mesh at all
            t.add_row(tissue, "[red]failed[/]", f"{e['seconds']:.1f}", "", "", "", "", e["reason"])
            continue
        status = {"ok": "ok", "review": "[yellow]review[/]"}.get(e["status"], "[red]failed[/]")
        if "n_elements" in e:  # hex cartilage
            quality = f"min SJ {e['min_scaled_jacobian']:.2f}, {e['frac_sj_below_0_5']:.2%} < 0.5"
            fid = f"cover {e['coverage']:.1%}, dev p95 {e['surface_deviation_mm']['p95']:.2f} mm"
            if rim := e.get("blend", {}).get("beyond_rim"):  # the blended file; beyond the rim its blend reshapes
                fid += f" (beyond the blended rim {rim['coverage']:.1%}, {rim['surface_deviation_mm']['p95']:.2f} mm)"
            count = str(e["n_elements"])
        else:  # bone shell
            closed = "closed, manifold" if e["watertight"] and e["manifold"] else "[red]open[/]"
            quality = f"{closed}, edge {e['edge_mm']['mean']:.1f} mm"
            fid = f"dist {e['surface_distance_mm']['mean']:.2f}/{e['surface_distance_mm']['p95']:.2f} mm"
            count = str(e["n_cells"])
        t.add_row(tissue, status, f"{e['seconds']:.1f}", count, f"{e['volume_ml']:.2f}", f"{e['label_volume_ml']:.2f}",
                  quality, fid)
    out.print(t)
    if "anatomy" in report:
        a = report["anatomy"]
        if a["status"] == "failed":
            out.print(f"anatomy: [red]failed[/]: {a['reason']}")
        else:
            res = ", ".join(f"{b} {r:.2f}" for b, r in a["residuals_mm"].items())
            ang = a["angles_deg"]
            out.print(f"anatomy: {a['status']}; {a['sites_placed']} attachment sites of {a['fibres']} fibres; registration "
                      f"residuals {res} mm; flexion {ang['flexion']:.1f}, varus {ang['varus']:.1f}, internal rotation "
                      f"{ang['internal_rotation']:.1f} deg" + "".join(f"\n  review: {r}" for r in a["reasons"]), highlight=False)
    if "fe" in report:
        fe = report["fe"]
        out.print(f"decks: {', '.join(fe['files'][:3])}" if fe["status"] == "ok" else f"decks: [red]failed[/]: {fe['reason']}",
                  highlight=False)
    if "simulation" in report:
        _print_simulation(report["simulation"])
    verdict = report["verdict"]
    colour = {"ok": "green", "review": "yellow"}.get(verdict["status"], "red")
    out.print(f"verdict: [{colour}]{verdict['status']}[/]" + "".join(f"\n  {r}" for r in verdict["reasons"]), highlight=False)
    out.print(f"report: {Path(out_dir) / 'report.json'}")
    if report["summary"]["failed"]:
        raise typer.Exit(1)


def _print_simulation(sim: dict) -> None:
    if sim.get("status") == "failed" and "completed" not in sim:
        out.print(f"simulation: [red]failed[/]: {sim['reason']}", highlight=False)
        return
    final = sim["final"]
    line = (f"simulation ({sim['kind']}, {sim['solver']}, {sim['solver_seconds']:.0f} s): "
            f"{'completed' if sim['completed'] else '[red]stopped[/]: ' + str(sim['reason'])} at "
            f"{sim['reached_flexion_deg']:.1f} of {sim['target_flexion_deg']:.0f} deg")
    if final.get("medial"):
        line += "; " + ", ".join(f"{k} {final[k]['force_n']:.0f} N on {final[k]['area_mm2']:.0f} mm^2, peak "
                                 f"{final[k]['peak_pressure_mpa']:.1f} MPa" for k in CONTACTS if k in final)
    out.print(line, highlight=False)
    if sim["completed"]:  # a stopped run's reason is on the line already
        for reason in sim.get("reasons", []):
            out.print(f"  [yellow]review[/]: {reason}", highlight=False)


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
    with _clear_errors():
        request = JobRequest.build(input_type="image", model=str(model) if model else None, side=side, **mesh_flags)
    _run_job(image_file, out_dir, request, workers)


@app.command()
def simulate(
    job_dir: Path = typer.Argument(..., metavar="DIR", help="A job folder written by `kneemesh mesh` or `kneemesh run`."),
    to: Optional[float] = typer.Option(None, "--to", min=1.0, max=120.0, help="Flexion to reach, deg (default: the deck's 90)."),
    smoke: bool = typer.Option(False, "--smoke", help="A few increments to 15 deg: a quick proof that the deck runs."),
    timeout: float = typer.Option(1800.0, "--timeout", min=10.0, help="Stop ccx after this many seconds."),
):
    """Run CalculiX on a job's decks (fe/knee_ccx.inp): contact forces, areas and pressures over flexion
    in fe/results.json and fe/contact.png (fe/smoke/ for --smoke)."""
    from kneemesh_core.fe.run import simulate as run_simulation

    with _clear_errors():
        r = run_simulation(job_dir, flexion_deg=to, smoke=smoke, timeout_s=timeout)
    last = r["increments"][-1] if r["increments"] else {}
    _print_simulation({"kind": "smoke" if smoke else "flexion", "solver": r["solver"], "solver_seconds": r["seconds"],
                       "completed": r["completed"], "reason": r["reason"], "reached_flexion_deg": r["reached_flexion_deg"],
                       "target_flexion_deg": r["target_flexion_deg"], "final": last, "reasons": r["physiology_reasons"]})
    if not r["completed"]:
        raise typer.Exit(1)


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

    with _clear_errors():
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

        def done(knee, rec):
            bar.advance(task)
            what = rec.get("verdict") if rec.get("state") == DONE else rec.get("state") or "unfinished"
            bar.console.print(f"{knee.id}: {what}" + (f" ({rec.get('reason') or rec.get('last_error')})"
                                                      if rec.get("state") != DONE else ""), highlight=False)

        try:
            records = submit_cohort(knees, api, out_dir, options, concurrency, poll, done)
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

    with _clear_errors():
        s = run_compare(a, b, out_dir)
    t = Table(title=f"{a} vs {b}")
    for col in ("tissue", "Dice", "deviation median / p75 / max mm", "coverage"):
        t.add_column(col)
    dev = s["surface_deviation_mm"]
    for tissue, d in s.get("dice", {}).items():
        row = dev.get(tissue)
        t.add_row(tissue, "" if d is None else f"{d:.3f}",
                  "" if not row or row["median"] is None else f"{row['median']:.2f} / {row['p75']:.2f} / {row['max']:.2f}",
                  "" if not row else f"{row['coverage']:.1%}")
    out.print(t)
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


@app.command()
def train(
    data: list[Path] = typer.Option(..., "--data", help="Folder of label maps (any supported convention); repeatable."),
    out_file: Path = typer.Option(..., "--out", help="The ONNX model to write (its run record goes beside it as .json)."),
    epochs: int = typer.Option(40, "--epochs", min=1),
    steps: int = typer.Option(100, "--steps", min=1, help="Batches per epoch."),
    batch: int = typer.Option(12, "--batch", min=1),
    crop: int = typer.Option(256, "--crop", min=64, help="Training crop size, pixels (a multiple of 32)."),
    lr: float = typer.Option(3e-3, "--lr", help="Peak learning rate (one-cycle schedule)."),
    widths: str = typer.Option("16,32,64,96", "--widths", help="Channels of the four levels."),
    head: int = typer.Option(12, "--head", help="Channels of the full-resolution head."),
    patience: int = typer.Option(8, "--patience", help="Stop after this many epochs without a better validation Dice."),
    phantoms: int = typer.Option(0, "--phantoms", min=0, help="Also train on this many phantom knees."),
    max_minutes: float = typer.Option(0.0, "--max-minutes", help="Time budget in minutes: the learning-rate schedule runs on the clock and ends with it (0: none)."),
    seed: int = typer.Option(0, "--seed"),
):
    """Train the segmentation network on synthetic images of label maps (random and DESS-like contrast); export ONNX (needs the train extra)."""
    with _clear_errors():
        try:
            from kneemesh_core.segmentation.train import TrainOptions, train as run_training
        except ImportError as exc:
            raise KneeMeshError("missing_extra", f"training needs PyTorch: pip install 'kneemesh[train]' ({exc}).") from exc
        if crop % 32:
            raise KneeMeshError("bad_option", "--crop must be a multiple of 32.")
        opts = TrainOptions(epochs=epochs, steps_per_epoch=steps, batch=batch, crop=crop, lr=lr, head=head,
                            widths=tuple(int(w) for w in widths.split(",")), patience=patience, seed=seed,
                            max_minutes=max_minutes)
        run_training(data, out_file, opts, phantoms=phantoms, log=lambda m: err.print(m, highlight=False))


@app.command()
def segment(
    image_file: Path = typer.Argument(..., metavar="IMAGE", help="Sagittal knee MRI (NIfTI, NRRD, MHA, DICOM folder or zip)."),
    out_file: Path = typer.Option(..., "--out", help="Label map to write (canonical kneemesh labels 1..7)."),
    model: Optional[Path] = typer.Option(None, "--model", help="ONNX model (default: the shipped one)."),
    side: Optional[str] = SideOpt,
    probabilities: Optional[Path] = typer.Option(None, "--probabilities", help="Also write per-class probabilities (uint8, 255 = 1) here."),
    threads: int = typer.Option(0, "--threads", min=0, help="onnxruntime threads (0: all cores)."),
):
    """Segment a knee MRI into bones and cartilages with the ONNX network, on the CPU."""
    from rich.progress import Progress

    from kneemesh_core.io import read_volume, write_image
    from kneemesh_core.segmentation.infer import SegmentationModel, segment as run_segment

    with _clear_errors():
        vol = read_volume(image_file)
        net = SegmentationModel.load(model, threads)
        with Progress(console=err, transient=not err.is_terminal) as bar:
            task = bar.add_task("segmenting slices", total=None)
            result = run_segment(vol, net, side=side, probabilities=probabilities is not None,
                                 progress=lambda done, n: bar.update(task, completed=done, total=n))
        write_image(result.knee.labels, out_file)
        if probabilities is not None:
            write_image(result.probabilities, probabilities)
    vols = result.knee.volumes_ml()
    out.print(f"{out_file}: {result.knee.side} knee ({result.knee.side_method}); " + ", ".join(
        f"{t} {v:.1f} ml" for t, v in vols.items()) + f"; {result.seconds['total']:.1f} s")


@app.command("evaluate-seg")
def evaluate_seg(
    pred: Path = typer.Option(..., "--pred", help="Predicted label map, or a folder of them."),
    truth: Path = typer.Option(..., "--truth", help="Reference label map, or a folder with the same file names."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON instead of a table."),
):
    """Dice, average symmetric surface distance and 95 % Hausdorff per tissue (mean over files for folders)."""
    from kneemesh_core.knee import load_knee
    from kneemesh_core.segmentation.evaluate import compare
    from kneemesh_core.tissues import TISSUES

    with _clear_errors():
        pairs = ([(p, truth / p.name) for p in sorted(pred.iterdir()) if (truth / p.name).exists()]
                 if pred.is_dir() else [(pred, truth)])
        if not pairs:
            raise KneeMeshError("not_found", f"no file of {pred} has a namesake in {truth}.")
        rows = {p.name: compare(load_knee(p).labels, load_knee(t).labels) for p, t in pairs}
    if as_json:
        out.print_json(json.dumps(rows))
        return
    t = Table(title=f"segmentation accuracy ({len(rows)} map{'s' if len(rows) > 1 else ''})")
    for col in ("tissue", "Dice", "ASSD mm", "HD95 mm"):
        t.add_column(col)
    for tissue in [t for t in TISSUES if any(t in r for r in rows.values())]:
        vals = [r[tissue] for r in rows.values() if tissue in r]
        mean = lambda k: sum(v[k] for v in vals if v[k] is not None) / max(1, sum(v[k] is not None for v in vals))  # noqa: E731
        t.add_row(tissue, f"{mean('dice'):.3f}", f"{mean('assd_mm'):.3f}", f"{mean('hd95_mm'):.3f}")
    out.print(t)


DataDirOpt = typer.Option(None, "--data-dir", help="Job folders live here (default: $KNEEMESH_DATA_DIR or ./kneemesh-data).")
BrokerOpt = typer.Option(None, "--broker", help="redis://host:port/db (default: $KNEEMESH_BROKER_URL).")


def _service_env(data_dir: Optional[Path], broker: Optional[str]) -> None:
    """The service reads its settings from KNEEMESH_* variables; flags override them for this process and its children."""
    import os

    if data_dir is not None:
        os.environ["KNEEMESH_DATA_DIR"] = str(data_dir)
    if broker is not None:
        os.environ["KNEEMESH_BROKER_URL"] = broker


@app.command()
def serve(
    host: str = typer.Option("127.0.0.1", "--host", help="Address to listen on."),
    port: int = typer.Option(8000, "--port", help="Port to listen on."),
    broker: Optional[str] = BrokerOpt,
    data_dir: Optional[Path] = DataDirOpt,
    workers: int = typer.Option(2, "--workers", min=1, help="Embedded mode: processes meshing tissues."),
):
    """Run the HTTP API. With no broker, jobs run on an in-process pool; with --broker they go to Celery workers."""
    import os

    import uvicorn

    _service_env(data_dir, broker)
    os.environ.setdefault("KNEEMESH_WORKERS", str(workers))
    with _clear_errors():
        from services.api import create_app

        api = create_app()
        loopback = host in ("127.0.0.1", "::1", "localhost")
        if not api.state.settings.api_keys and not loopback and os.environ.get("KNEEMESH_AUTH", "on").lower() != "off":
            raise KneeMeshError("api_keys_required", f"the API would listen on {host}, reachable from the network, with no "
                                "API keys: set KNEEMESH_API_KEYS='lab-a:a-long-secret,...', or KNEEMESH_AUTH=off to run "
                                "without keys on a closed network.")
    mode = f"Celery on {api.state.settings.broker_url}" if api.state.settings.broker_url else f"embedded, {workers} worker processes"
    err.print(f"kneemesh API on http://{host}:{port} ({mode}); jobs in {api.state.jobs.store.root}")
    uvicorn.run(api, host=host, port=port, log_level="info")


@app.command()
def worker(
    broker: Optional[str] = BrokerOpt,
    data_dir: Optional[Path] = DataDirOpt,
    concurrency: int = typer.Option(2, "--concurrency", "-c", min=1, help="Worker processes."),
    loglevel: str = typer.Option("info", "--loglevel", help="Celery log level."),
    name: Optional[str] = typer.Option(None, "--name", help="Worker node name (default: kneemesh@host)."),
):
    """Start a Celery worker for the service's jobs (needs --broker or $KNEEMESH_BROKER_URL)."""
    _service_env(data_dir, broker)
    from services.settings import Settings

    settings = Settings.from_env()
    if not settings.broker_url:
        err.print("[bold red]error[/] (no_broker): a worker needs a broker: --broker redis://host:6379/0 or KNEEMESH_BROKER_URL.")
        raise typer.Exit(2)
    from services.worker.celery_app import QUEUE, app as celery_app

    celery_app.worker_main(["worker", "-Q", QUEUE, "-c", str(concurrency), "-l", loglevel,
                                     "-n", name or "kneemesh@%h"])


@app.command()
def cleanup(
    data_dir: Optional[Path] = DataDirOpt,
    older_than: Optional[float] = typer.Option(None, "--older-than", help="Days (default: $KNEEMESH_RETENTION_DAYS or 30)."),
):
    """Delete finished jobs older than the retention period, with their uploads and artifacts."""
    _service_env(data_dir, None)
    from services.jobs import Jobs
    from services.settings import Settings
    from services.store import FileStore

    settings = Settings.from_env()
    days = settings.retention_days if older_than is None else older_than
    gone = Jobs(FileStore(settings.data_dir)).expire(days)
    out.print(f"removed {len(gone)} job(s) older than {days:g} days from {settings.data_dir}")


@app.command()
def openapi(out_file: Optional[Path] = typer.Option(None, "--out", help="Write here instead of stdout.")):
    """Print the API's OpenAPI document (YAML), as committed in openapi.yaml."""
    from services.api.openapi import openapi_yaml

    text = openapi_yaml()
    if out_file is None:
        sys.stdout.write(text)
    else:
        out_file.write_text(text)


if __name__ == "__main__":  # pragma: no cover
    app()

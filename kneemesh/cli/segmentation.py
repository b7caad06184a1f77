"""The segmentation commands: ``segment`` an image, ``evaluate-seg`` against reference labels, ``train``."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from kneemesh.cli.app import SideOpt, app, clear_errors, dataclass_flags, err, out, with_flags
from kneemesh.cli.render import accuracy_table
from kneemesh_core import KneeMeshError


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

    with clear_errors():
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

    with clear_errors():
        pairs = ([(p, truth / p.name) for p in sorted(pred.iterdir()) if (truth / p.name).exists()]
                 if pred.is_dir() else [(pred, truth)])
        if not pairs:
            raise KneeMeshError("not_found", f"no file of {pred} has a namesake in {truth}.")
        rows = {p.name: compare(load_knee(p).labels, load_knee(t).labels) for p, t in pairs}
    if as_json:
        out.print_json(json.dumps(rows))
        return
    out.print(accuracy_table(rows))


def _train_flags() -> dict:
    """The flags of ``train``: the fields of :class:`kneemesh_core.segmentation.train.TrainOptions`, with its
    defaults (read without importing PyTorch)."""
    from kneemesh_core.segmentation.options import TrainOptions

    return dataclass_flags(TrainOptions, skip=("val_slices", "threads"), help={
        "steps_per_epoch": "Batches per epoch.", "crop": "Training crop size, pixels (a multiple of 32).",
        "lr": "Peak learning rate (one-cycle schedule).", "widths": "Channels of the four levels, comma-separated.",
        "head": "Channels of the full-resolution head.",
        "patience": "Stop after this many epochs without a better validation Dice, all in the schedule's last 30 %.",
        "max_minutes": "Time budget in minutes: the learning-rate schedule runs on the clock and ends with it (0: none)."},
        names={"steps_per_epoch": "--steps"})


@app.command()
@with_flags(_train_flags(), "train_flags")
def train(
    data: list[Path] = typer.Option(..., "--data", help="Folder of label maps (any supported convention); repeatable."),
    out_file: Path = typer.Option(..., "--out", help="The ONNX model to write (its run record goes beside it as .json)."),
    phantoms: int = typer.Option(0, "--phantoms", min=0, help="Also train on this many phantom knees."),
    train_flags: dict = None,
):
    """Train the segmentation network on synthetic images of label maps (random and DESS-like contrast); export ONNX (needs the train extra)."""
    from kneemesh_core.segmentation.options import TrainOptions

    with clear_errors():
        opts = TrainOptions(**{**train_flags, "widths": tuple(int(w) for w in train_flags["widths"].split(","))})
        if opts.crop % 32:
            raise KneeMeshError("bad_option", "--crop must be a multiple of 32.")
        try:
            from kneemesh_core.segmentation.train import train as run_training
        except ImportError as exc:
            raise KneeMeshError("missing_extra", f"training needs PyTorch: pip install 'kneemesh[train]' ({exc}).") from exc
        run_training(data, out_file, opts, phantoms=phantoms, log=lambda m: err.print(m, highlight=False))

"""The steps that read a job's input: ``ingest`` (every job) and ``segment`` (images).

They run first and alone, in the runner's own process, and load no meshing code (only
:mod:`.steps` does): the in-process runner's workers import it meanwhile.
"""

from __future__ import annotations

import os
from pathlib import Path

from kneemesh_core import __version__
from kneemesh_core.errors import KneeMeshError
from kneemesh_core.io import read_label_map, read_volume, write_image
from kneemesh_core.job.options import INPUT_TYPES, JobOptions
from kneemesh_core.job.outputs import JOB_FILE, LABELS_FILE, read_json, write_json
from kneemesh_core.knee import canonicalise, describe, describe_image
from kneemesh_core.tissues import resolve_convention


def ingest(input_path: str | os.PathLike, out_dir: str | os.PathLike, options: JobOptions) -> dict:
    """Validate the input and write canonical labels and ``job.json``.

    Nothing is written unless the input is valid.
    """
    options.tissues()
    if options.input_type not in INPUT_TYPES:
        raise KneeMeshError("bad_option", f"input type {options.input_type!r}: expected one of {', '.join(INPUT_TYPES)}.")
    knee = None
    if options.input_type == "image":  # checked here, segmented by the segment step
        from kneemesh_core.segmentation.infer import SegmentationModel

        vol = read_volume(input_path)
        SegmentationModel.load(options.model)  # a missing or foreign model fails here, before anything is queued
        description = describe_image(vol.image, vol.source)
    else:
        knee = canonicalise(read_label_map(input_path), resolve_convention(options.preset, options.labels), options.side)
        description = describe(knee)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if knee is not None:
        write_image(knee.labels, out / LABELS_FILE)
    job = {"kneemesh_version": __version__, "input": description, "options": options.to_dict()}
    write_json(out / JOB_FILE, job)
    return job


def segment_input(input_path: str | os.PathLike, out_dir: str | os.PathLike, options: JobOptions) -> dict:
    """Image inputs: segment the image into canonical labels ``labels.nrrd``; ``job.json`` gains the
    knee's description and the segmentation's facts.  Returns the report's ``segmentation`` entry:
    ``review`` with the reasons when the labels are not a plausible knee
    (:mod:`kneemesh_core.segmentation.plausibility`)."""
    from kneemesh_core.segmentation.infer import SegmentationModel, segment
    from kneemesh_core.segmentation.plausibility import check, figures

    out = Path(out_dir)
    model = SegmentationModel.load(options.model)
    result = segment(read_volume(input_path), model, side=options.side)
    write_image(result.knee.labels, out / LABELS_FILE)
    job = read_json(out / JOB_FILE)
    facts = {"model": model.path.name, "model_version": model.meta.get("version"), "seconds": result.seconds,
             "image": job["input"]}
    job["input"] = {**describe(result.knee), "preset": "segmented", "segmentation": facts}
    write_json(out / JOB_FILE, job)
    plausibility = figures(result.knee.labels)
    status, reasons = check(plausibility)
    return {"status": status, "reasons": reasons, "side": result.knee.side, "seconds": result.seconds["total"],
            "tissues_ml": job["input"]["tissues"], "plausibility": plausibility}

"""Taking an upload in: a safe file name, the job's options, validation before anything is queued,
and the hand-over to the runner.  A rejected upload leaves nothing behind."""

from __future__ import annotations

import logging
import re
import shutil

from fastapi import UploadFile
from starlette.concurrency import run_in_threadpool

from kneemesh_core import KneeMeshError
from kneemesh_core.job import INGEST, JobRequest, run_step
from services.api.errors import ApiError
from services.api.metrics import Metrics
from services.jobs import JobRecord, Jobs

log = logging.getLogger("kneemesh.api")

SUFFIXES = (".nii.gz", ".nii", ".nrrd", ".mha", ".zip")
#: A model named in a request is a plain file name among the server's models, never a path.
MODEL_NAME = re.compile(r"^[A-Za-z0-9._-]+\.onnx$")


def safe_filename(name: str | None) -> str:
    """The upload's base name with only safe characters, or a 415 for an unsupported format."""
    base = re.sub(r"[^A-Za-z0-9._-]", "_", (name or "").replace("\\", "/").rsplit("/", 1)[-1]).lstrip(".")
    if not base.lower().endswith(SUFFIXES):
        raise ApiError(415, "unsupported_format",
                       f"{name!r}: expected a NIfTI (.nii, .nii.gz), NRRD (.nrrd), MHA (.mha) file or a DICOM series as .zip.")
    return base[-200:]


def server_side(request: JobRequest) -> JobRequest:
    """The request with the options that name files checked for a server: ``labels`` must be a
    mapping (files are read only by the command line), ``model`` the name of a shipped model."""
    if request.labels is not None and "=" not in request.labels:
        raise ApiError(422, "bad_labels_spec", f"labels {request.labels!r}: expected a mapping such as "
                                               "'femur=5,tibia=6,...' (a JSON file is for the command line).")
    if request.model is not None:
        from kneemesh_core.segmentation.infer import MODELS_DIR

        if not MODEL_NAME.match(request.model):
            raise ApiError(422, "model_missing", f"model {request.model!r}: expected the file name of a model "
                                                 f"shipped with the server (e.g. kneemesh-seg.onnx).")
        request = request.model_copy(update={"model": str(MODELS_DIR / request.model)})
    return request


async def accept(jobs: Jobs, metrics: Metrics, upload: UploadFile, request: JobRequest, who: str,
                 batch_id: str | None) -> JobRecord:
    """Store and validate one upload; returns its job record (not yet queued). Nothing is left on failure."""
    name = safe_filename(upload.filename)
    # an image is checked here (readable, 3-D, a model to segment it) and segmented by the first queued step
    rec = jobs.create(who, name, request.input_type, server_side(request).job_options(bundle=True), batch_id)
    try:
        with open(jobs.input_path(rec), "wb") as fh:  # the upload is spooled to disk; copy it in chunks
            await run_in_threadpool(shutil.copyfileobj, upload.file, fh, 1 << 20)
        metrics.uploaded(jobs.input_path(rec).stat().st_size)
        await run_in_threadpool(run_step, jobs.out_dir(rec), INGEST, rec.options, jobs.input_path(rec))
    except KneeMeshError as exc:
        jobs.store.purge(rec.id)
        raise ApiError(422, exc.code, exc.message) from exc
    except BaseException:
        jobs.store.purge(rec.id)
        raise
    return rec


def enqueue(jobs: Jobs, metrics: Metrics, runner, rec: JobRecord) -> None:
    """Hand a validated job to the runner; a queue that cannot take it is a 503 and the job is removed."""
    try:
        runner.submit(rec)
    except Exception as exc:
        jobs.store.purge(rec.id)
        log.warning("could not queue job %s: %s", rec.id, exc)
        raise ApiError(503, "queue_unavailable", f"the job queue could not take the job ({type(exc).__name__}); try again later.") from exc
    metrics.submitted()

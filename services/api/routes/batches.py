"""``/v1/batches``: many knees with the same options as one batch."""

from __future__ import annotations

import uuid
from typing import Annotated, get_args

from fastapi import APIRouter, Depends, File, Form, Request, UploadFile

from kneemesh_core.job import JobRequest
from services.api import deps, schemas
from services.api.errors import ERRORS, ApiError
from services.api.metrics import Metrics
from services.api.uploads import accept, enqueue
from services.api.views import job_created, job_summary
from services.jobs import FINISHED, JobRecord, Jobs

router = APIRouter(prefix="/v1/batches", tags=["batches"], responses=ERRORS)


@router.post("", status_code=202, response_model=schemas.BatchCreated)
async def create_batch(request: Request, files: Annotated[list[UploadFile], File(description="The label maps or images.")],
                       options: Annotated[JobRequest, Form()], who: str = Depends(deps.owner),
                       jobs: Jobs = Depends(deps.jobs), metrics: Metrics = Depends(deps.metrics),
                       runner=Depends(deps.runner)):
    """Many knees with the same options as one batch; all are validated before any is queued."""
    batch_id = uuid.uuid4().hex
    accepted: list[JobRecord] = []
    try:
        for f in files:
            try:
                accepted.append(await accept(jobs, metrics, f, options, who, batch_id))
            except ApiError as exc:
                exc.message = f"file {len(accepted) + 1} ({f.filename}): {exc.message} No job of the batch was queued."
                raise
    except BaseException:
        for rec in accepted:
            jobs.store.purge(rec.id)
        raise
    jobs.save_batch(batch_id, who, [r.id for r in accepted])
    positions = jobs.queue_positions([r.id for r in accepted])  # taken together: strictly increasing
    for rec in accepted:
        enqueue(jobs, metrics, runner, rec)
    return schemas.BatchCreated(id=batch_id, jobs=[job_created(request, jobs, r, positions.get(r.id)) for r in accepted],
                                url=str(request.url_for("get_batch", batch_id=batch_id)))


def _own_batch(batch_id: str, who: str, jobs: Jobs) -> dict:
    batch = jobs.get_batch(batch_id)
    if batch is None or batch["owner"] != who:
        raise ApiError(404, "batch_not_found", f"no batch {batch_id!r} for this API key.")
    return batch


@router.get("/{batch_id}", response_model=schemas.BatchStatus)
def get_batch(request: Request, batch_id: str, who: str = Depends(deps.owner), jobs: Jobs = Depends(deps.jobs)):
    """Counts per state and every job of the batch, with its verdict and failed tissues."""
    batch = _own_batch(batch_id, who, jobs)
    rows = [job_summary(request, jobs, r) for r in (jobs.get(j) for j in batch["jobs"]) if r is not None]
    counts = {s: sum(r.state == s for r in rows) for s in get_args(schemas.State)}
    return schemas.BatchStatus(id=batch_id, created_at=batch["created_at"], counts=counts,
                               done=all(r.state in FINISHED for r in rows), jobs=rows)


@router.get("/{batch_id}/manifest", response_model=schemas.BatchManifest)
def get_batch_manifest(request: Request, batch_id: str, who: str = Depends(deps.owner), jobs: Jobs = Depends(deps.jobs)):
    """Every artifact of every job of the batch, with its URL and SHA-256: what a client downloads and checks."""
    batch = _own_batch(batch_id, who, jobs)
    entries = []
    for rec in (jobs.get(j) for j in batch["jobs"]):
        if rec is None:
            continue
        state = jobs.state(rec, jobs.steps(rec))
        listed = (jobs.store.artifacts(rec.id) or []) if state in ("succeeded", "failed") else []
        entries.append(schemas.ManifestEntry(
            id=rec.id, input_name=rec.input_name, state=state, verdict=jobs.verdict(rec),
            artifacts=[schemas.Artifact(**a, url=str(request.url_for("get_artifact", job_id=rec.id, name=a["name"])))
                       for a in listed]))
    return schemas.BatchManifest(id=batch_id, done=all(e.state in FINISHED for e in entries), jobs=entries)

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
    for rec in accepted:
        enqueue(jobs, metrics, runner, rec)
    return schemas.BatchCreated(id=batch_id, jobs=[job_created(request, jobs, r) for r in accepted],
                                url=str(request.url_for("get_batch", batch_id=batch_id)))


@router.get("/{batch_id}", response_model=schemas.BatchStatus)
def get_batch(request: Request, batch_id: str, who: str = Depends(deps.owner), jobs: Jobs = Depends(deps.jobs)):
    """Counts per state and every job of the batch."""
    batch = jobs.get_batch(batch_id)
    if batch is None or batch["owner"] != who:
        raise ApiError(404, "batch_not_found", f"no batch {batch_id!r} for this API key.")
    rows = [job_summary(request, jobs, r) for r in (jobs.get(j) for j in batch["jobs"]) if r is not None]
    counts = {s: sum(r.state == s for r in rows) for s in get_args(schemas.State)}
    return schemas.BatchStatus(id=batch_id, created_at=batch["created_at"], counts=counts,
                               done=all(r.state in FINISHED for r in rows), jobs=rows)

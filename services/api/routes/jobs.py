"""``/v1/jobs``: upload one knee and queue its job, list, status, cancel and delete."""

from __future__ import annotations

import asyncio
import time
from typing import Annotated

from fastapi import APIRouter, Depends, File, Form, Header, Request, UploadFile

from kneemesh_core.job import JobRequest
from services.api import deps, schemas
from services.api.errors import ERRORS, ApiError
from services.api.metrics import Metrics
from services.api.uploads import accept, enqueue
from services.api.views import job_created, job_status, job_summary
from services.jobs import FINISHED, JobRecord, Jobs

router = APIRouter(prefix="/v1/jobs", tags=["jobs"], responses=ERRORS)


@router.post("", status_code=202, response_model=schemas.JobCreated)
async def create_job(request: Request, file: Annotated[UploadFile, File(description="The label map or image.")],
                     options: Annotated[JobRequest, Form()], who: str = Depends(deps.owner),
                     jobs: Jobs = Depends(deps.jobs), metrics: Metrics = Depends(deps.metrics),
                     runner=Depends(deps.runner),
                     idempotency_key: Annotated[str | None, Header(
                         alias="Idempotency-Key", max_length=200,
                         description="A client's name for this submission: repeating it returns the job it created "
                                     "instead of queueing a second one (a client that crashed before recording "
                                     "the answer can safely submit again).")] = None):
    """Upload one knee and queue its job; the input is validated first, and a bad one queues nothing."""
    if idempotency_key and (known := await _claim_or_known(jobs, who, idempotency_key)) is not None:
        return job_created(request, jobs, known)
    try:
        rec = await accept(jobs, metrics, file, options, who, None)
        enqueue(jobs, metrics, runner, rec)
    except BaseException:
        if idempotency_key:
            jobs.release_key(who, idempotency_key)
        raise
    if idempotency_key:
        jobs.remember_key(who, idempotency_key, rec.id)
    return job_created(request, jobs, rec)


#: How long (s) a repeated submission waits for the first one with its Idempotency-Key to be accepted.
KEY_WAIT_S = 60.0


async def _claim_or_known(jobs: Jobs, who: str, key: str) -> JobRecord | None:
    """The job already created with ``key``, or None once this request holds the key's claim; while
    another request holds it, wait for its job (its upload is still being accepted)."""
    deadline = time.monotonic() + KEY_WAIT_S
    while time.monotonic() < deadline:
        if (known := jobs.by_key(who, key)) is not None:
            return known
        if jobs.claim_key(who, key):
            return None
        await asyncio.sleep(0.2)
    raise ApiError(503, "submission_in_progress", "a submission with this Idempotency-Key is still being accepted; "
                   "try again shortly (the same key returns its job).")


@router.get("", response_model=schemas.JobList)
def list_jobs(request: Request, who: str = Depends(deps.owner), jobs: Jobs = Depends(deps.jobs)):
    """This key's jobs, oldest first."""
    return schemas.JobList(jobs=[job_summary(request, jobs, r) for r in jobs.all() if r.owner == who])


@router.get("/{job_id}", response_model=schemas.JobStatus)
def get_job(request: Request, rec: JobRecord = Depends(deps.own_job), jobs: Jobs = Depends(deps.jobs)):
    """State, queue position, progress of every step (ingest, segment, each bone, each cartilage, conform, report, bundle), errors."""
    return job_status(request, jobs, rec)


@router.delete("/{job_id}", response_model=schemas.JobStatus)
def delete_job(request: Request, rec: JobRecord = Depends(deps.own_job), jobs: Jobs = Depends(deps.jobs),
               runner=Depends(deps.runner)):
    """Cancel the job if it has not finished, and delete its upload and artifacts."""
    steps = jobs.steps(rec)
    if jobs.state(rec, steps) not in FINISHED:
        rec.cancelled = True
    rec.deleted = True
    jobs.save(rec)
    runner.cancel(rec, steps)
    jobs.store.delete(rec.id)
    return job_status(request, jobs, rec)

"""What the API shows of a job: its links, its status and its one-line summary."""

from __future__ import annotations

from fastapi import Request

from services.api import schemas
from services.jobs import JobRecord, Jobs


def links(request: Request, job_id: str) -> schemas.Links:
    return schemas.Links(self=str(request.url_for("get_job", job_id=job_id)),
                         artifacts=str(request.url_for("list_artifacts", job_id=job_id)),
                         bundle=str(request.url_for("get_bundle", job_id=job_id)))


def _state_and_position(jobs: Jobs, rec: JobRecord, steps: list[dict] | None = None) -> tuple[str, int | None]:
    """A job's state and, while it is queued, its position: a number whenever the state says queued (a job
    that starts between the two readings is running, with no position)."""
    state = jobs.state(rec, steps if steps is not None else jobs.steps(rec))
    if state != "queued":
        return state, None
    position = jobs.queue_position(rec)
    return (state, position) if position is not None else (jobs.state(rec, jobs.steps(rec)), None)


def job_status(request: Request, jobs: Jobs, rec: JobRecord) -> schemas.JobStatus:
    steps = jobs.steps(rec)
    state, position = _state_and_position(jobs, rec, steps)
    failed_step = next((s for s in steps if s["state"] == "failed"), None)
    tissues = [s for s in steps if s["kind"] in ("bone", "cartilage") and s["state"] == "done"]
    return schemas.JobStatus(
        id=rec.id, state=state, created_at=rec.created_at, input_name=rec.input_name, input_type=rec.input_type,
        options=rec.options, batch_id=rec.batch_id,
        queue_position=position,
        progress=round(sum(s["state"] in ("done", "failed") for s in steps) / max(len(steps), 1), 3),
        steps=steps, tissues_ok=[s["step"] for s in tissues if s["status"] == "ok"],
        tissues_review=[s["step"] for s in tissues if s["status"] == "review"],
        tissues_failed=[s["step"] for s in tissues if s["status"] == "failed"], verdict=jobs.verdict(rec),
        error=failed_step.get("error") if failed_step else None, deleted=rec.deleted, urls=links(request, rec.id))


def job_summary(request: Request, jobs: Jobs, rec: JobRecord) -> schemas.JobSummary:
    steps = jobs.steps(rec)
    return schemas.JobSummary(id=rec.id, state=jobs.state(rec, steps), created_at=rec.created_at,
                              input_name=rec.input_name, url=str(request.url_for("get_job", job_id=rec.id)),
                              verdict=jobs.verdict(rec),
                              tissues_failed=[s["step"] for s in steps if s["kind"] in ("bone", "cartilage")
                                              and s["state"] == "done" and s["status"] == "failed"])


def job_created(request: Request, jobs: Jobs, rec: JobRecord, position: int | None = None) -> schemas.JobCreated:
    """A new (or repeated) job's answer; ``position`` when the caller took it before queueing."""
    if position is None:
        state, position = _state_and_position(jobs, rec)
    else:
        state = jobs.state(rec, jobs.steps(rec))
    return schemas.JobCreated(id=rec.id, state=state, queue_position=position if state == "queued" else None,
                              urls=links(request, rec.id))

"""FastAPI dependencies: the settings, the job store and the runner of this app, and who is asking."""

from __future__ import annotations

import hmac

from fastapi import Depends, Request, Security
from fastapi.security import APIKeyHeader

from services.api.errors import ApiError
from services.api.metrics import Metrics
from services.jobs import JobRecord, Jobs
from services.settings import Settings

key_header = APIKeyHeader(name="X-API-Key", auto_error=False,
                          description="Required when the server has API keys configured; a key sees only its own jobs.")


def settings(request: Request) -> Settings:
    return request.app.state.settings


def jobs(request: Request) -> Jobs:
    return request.app.state.jobs


def runner(request: Request):
    """The job runner: Celery (``services.worker.celery_app.CeleryRunner``) or the embedded pool."""
    return request.app.state.runner


def metrics(request: Request) -> Metrics:
    return request.app.state.metrics


def owner(key: str | None = Security(key_header), conf: Settings = Depends(settings)) -> str:
    """The name behind the request's API key ("anonymous" when the server has no keys)."""
    if not conf.api_keys:
        return "anonymous"
    if not key:
        raise ApiError(401, "missing_api_key", "send your API key in the X-API-Key header.")
    for known, name in conf.api_keys.items():
        if hmac.compare_digest(known.encode(), key.encode()):
            return name
    raise ApiError(401, "invalid_api_key", "the X-API-Key header holds no key this server knows.")


def own_job(job_id: str, who: str = Depends(owner), store: Jobs = Depends(jobs)) -> JobRecord:
    """The job ``job_id`` if the caller owns it; another owner's job is as unknown as a missing one."""
    rec = store.get(job_id)
    if rec is None or rec.owner != who:
        raise ApiError(404, "job_not_found", f"no job {job_id!r} for this API key.")
    return rec

"""Health, readiness and Prometheus metrics."""

from __future__ import annotations

from fastapi import APIRouter, Depends
from fastapi.responses import JSONResponse, Response

from kneemesh_core import __version__
from services.api import deps, schemas
from services.api.metrics import Metrics
from services.jobs import Jobs

router = APIRouter(tags=["operations"])


@router.get("/healthz", response_model=schemas.Health)
def healthz():
    """The process is up."""
    return schemas.Health(status="ok", version=__version__)


@router.get("/readyz", response_model=schemas.Readiness, responses={503: {"model": schemas.Readiness}})
def readyz(jobs: Jobs = Depends(deps.jobs), runner=Depends(deps.runner)):
    """Ready to run jobs: the store is writable and the broker and at least one worker answer."""
    info = runner.ready()
    if info["ready"] and not jobs.store.root.is_dir():
        info = {**info, "ready": False, "detail": f"data folder {jobs.store.root} is missing"}
    return JSONResponse(info, status_code=200 if info["ready"] else 503)


@router.get("/metrics", response_class=Response,
            responses={200: {"content": {"text/plain": {}}, "description": "Prometheus text format."}})
def prometheus(metrics: Metrics = Depends(deps.metrics)):
    """Prometheus metrics: requests, uploads, rejections, jobs by state."""
    return Response(metrics.render(), media_type=metrics.content_type)

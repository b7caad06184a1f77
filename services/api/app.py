"""FastAPI application: uploads in, jobs queued, status out, artifacts by URL.

Routes, one module each under :mod:`services.api.routes` (all JSON, errors as
``{"code", "message"}``, see :mod:`.errors`):

- ``jobs``: ``POST /v1/jobs`` one knee (a label map or an image: NIfTI, NRRD, MHA, DICOM
  series as .zip) and its options, validated (read, label convention, side) before anything
  is queued; ``GET /v1/jobs``, ``GET /v1/jobs/{id}``, ``DELETE /v1/jobs/{id}``;
- ``artifacts``: ``GET /v1/jobs/{id}/artifacts``, ``.../artifacts/{name}``, ``.../bundle.zip``;
- ``batches``: ``POST /v1/batches``, ``GET /v1/batches/{id}``;
- ``operations``: ``GET /healthz``, ``/readyz``, ``/metrics``.

The settings, the job store, the runner and the caller's identity reach the routes as
dependencies (:mod:`.deps`).
"""

from __future__ import annotations

import contextlib
import time

from fastapi import FastAPI, Request

from kneemesh_core import __version__
from services.api import errors
from services.api.limits import BodySizeLimit
from services.api.metrics import Metrics
from services.api.routes import artifacts, batches, jobs as job_routes, operations
from services.jobs import Jobs
from services.settings import Settings
from services.store import FileStore


def create_app(settings: Settings | None = None, runner=None) -> FastAPI:
    """The API over ``settings.data_dir``; jobs go to Celery when a broker is set, else to an in-process pool."""
    settings = settings or Settings()
    jobs = Jobs(FileStore(settings.data_dir))
    if runner is None:
        if settings.broker_url:
            from services.worker.celery_app import CeleryRunner

            runner = CeleryRunner(settings)
        else:
            from services.worker.embedded import EmbeddedRunner

            runner = EmbeddedRunner(settings.workers)
    metrics = Metrics(jobs)

    @contextlib.asynccontextmanager
    async def lifespan(_app):
        runner.start(jobs)
        yield
        runner.stop()

    app = FastAPI(title="KneeMesh", version=__version__, lifespan=lifespan,
                  description="Knee label maps in, simulation-ready knee models out: bone surfaces, all-hexahedral "
                              "cartilage meshes and reports, by job, with artifacts served by URL.")
    app.add_middleware(BodySizeLimit, limit=settings.max_upload_bytes)
    app.state.jobs, app.state.runner, app.state.settings, app.state.metrics = jobs, runner, settings, metrics
    errors.install(app)

    @app.middleware("http")
    async def _measure(request: Request, call_next):
        t0 = time.perf_counter()
        response = await call_next(request)
        route = request.scope.get("route")
        metrics.request(request.method, getattr(route, "path", "unmatched"), response.status_code, time.perf_counter() - t0)
        return response

    for module in (job_routes, artifacts, batches, operations):
        app.include_router(module.router)
    return app

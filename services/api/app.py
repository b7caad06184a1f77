"""FastAPI application: uploads in, jobs queued, status out, artifacts by URL.

Routes (all JSON, errors as ``{"code", "message"}``):

- ``POST /v1/jobs`` a label map (NIfTI, NRRD, MHA, DICOM series as .zip) and options;
  validated (read, label convention, side) before anything is queued; 202.
- ``GET /v1/jobs``, ``GET /v1/jobs/{id}`` state, queue position, per-step progress.
- ``GET /v1/jobs/{id}/artifacts``, ``.../artifacts/{name}``, ``.../bundle.zip``.
- ``DELETE /v1/jobs/{id}`` cancel and delete.
- ``POST /v1/batches``, ``GET /v1/batches/{id}`` many knees as one batch.
- ``GET /healthz``, ``GET /readyz``, ``GET /metrics``.
"""

from __future__ import annotations

import contextlib
import hmac
import logging
import re
import shutil
import time
import uuid
from typing import Annotated, Literal, get_args

from fastapi import Depends, FastAPI, File, Form, HTTPException, Request, Security, UploadFile
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse, RedirectResponse, Response
from fastapi.security import APIKeyHeader
from starlette.concurrency import run_in_threadpool

from kneemesh_core import KneeMeshError, __version__
from kneemesh_core.pipeline import BUNDLE_FILE, INGEST, JobOptions, run_step
from kneemesh_core.hexmesh import BlendOptions, HexOptions
from services.api import schemas
from services.api.limits import TOO_LARGE, BodySizeLimit
from services.api.metrics import Metrics
from services.jobs import FINISHED, JobRecord, Jobs
from services.settings import Settings
from services.store import FileStore

log = logging.getLogger("kneemesh.api")

SUFFIXES = (".nii.gz", ".nii", ".nrrd", ".mha", ".zip")
ERRORS = {code: {"model": schemas.Error} for code in (400, 401, 404, 409, 413, 415, 422, 503)}


class ApiError(Exception):
    def __init__(self, status: int, code: str, message: str):
        self.status, self.code, self.message = status, code, message


def safe_filename(name: str | None) -> str:
    """The upload's base name with only safe characters, or a 415 for an unsupported format."""
    base = re.sub(r"[^A-Za-z0-9._-]", "_", (name or "").replace("\\", "/").rsplit("/", 1)[-1]).lstrip(".")
    if not base.lower().endswith(SUFFIXES):
        raise ApiError(415, "unsupported_format",
                       f"{name!r}: expected a NIfTI (.nii, .nii.gz), NRRD (.nrrd), MHA (.mha) file or a DICOM series as .zip.")
    return base[-200:]


def form_options(
    input_type: Annotated[Literal["labels", "image"], Form(description="labels (a segmentation) or image (a DESS volume).")] = "labels",
    preset: Annotated[str | None, Form(description="Label convention: kneemesh, pymskt, oai-zib, imorphics (default: detect).")] = None,
    side: Annotated[Literal["left", "right"] | None, Form(description="left or right (default: detect).")] = None,
    only: Annotated[Literal["all", "bones", "cartilage"], Form(description="Tissues to mesh.")] = "all",
    element_size: Annotated[float, Form(gt=0.2, le=5.0, description="Cartilage in-plane element edge, mm.")] = 1.0,
    layers: Annotated[int, Form(ge=1, le=12, description="Cartilage element layers through the thickness.")] = 4,
    blend: Annotated[bool, Form(description="Blend the cartilage edge into the bone and fuse it onto the bone.")] = True,
) -> schemas.Options:
    return schemas.Options(input_type=input_type, preset=preset or None, side=side, only=only,
                           element_size=element_size, layers=layers, blend=blend)


def create_app(settings: Settings | None = None, runner=None) -> FastAPI:
    """The API over ``settings.data_dir``; jobs go to Celery when a broker is set, else to an in-process pool."""
    settings = settings or Settings.from_env()
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
    app.state.jobs, app.state.runner, app.state.settings = jobs, runner, settings

    # errors: always {"code", "message"}
    @app.exception_handler(ApiError)
    async def _api_error(request: Request, exc: ApiError):
        if request.method == "POST":
            metrics.rejected(exc.code)
        return JSONResponse({"code": exc.code, "message": exc.message}, status_code=exc.status)

    @app.exception_handler(HTTPException)
    async def _http_error(request: Request, exc: HTTPException):
        if request.scope.get(TOO_LARGE):
            return await _api_error(request, ApiError(413, "upload_too_large",
                                                      f"the upload is larger than this server's limit of {settings.max_upload_bytes} bytes."))
        codes = {400: "bad_request", 404: "not_found", 405: "method_not_allowed"}
        return JSONResponse({"code": codes.get(exc.status_code, "http_error"), "message": str(exc.detail)},
                            status_code=exc.status_code, headers=getattr(exc, "headers", None))

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, exc: RequestValidationError):
        errors = [{"loc": list(map(str, e.get("loc", ()))), "msg": e.get("msg", "")} for e in exc.errors()]
        message = "; ".join(f"{'.'.join(e['loc'][1:] or e['loc'])}: {e['msg']}" for e in errors) or "invalid request"
        metrics.rejected("invalid_request")
        return JSONResponse({"code": "invalid_request", "message": message, "details": errors}, status_code=422)

    @app.middleware("http")
    async def _measure(request: Request, call_next):
        t0 = time.perf_counter()
        response = await call_next(request)
        route = request.scope.get("route")
        metrics.request(request.method, getattr(route, "path", "unmatched"), response.status_code, time.perf_counter() - t0)
        return response

    # who is asking
    key_header = APIKeyHeader(name="X-API-Key", auto_error=False,
                              description="Required when the server has API keys configured; a key sees only its own jobs.")

    def owner(key: str | None = Security(key_header)) -> str:
        if not settings.api_keys:
            return "anonymous"
        if not key:
            raise ApiError(401, "missing_api_key", "send your API key in the X-API-Key header.")
        for known, name in settings.api_keys.items():
            if hmac.compare_digest(known.encode(), key.encode()):
                return name
        raise ApiError(401, "invalid_api_key", "the X-API-Key header holds no key this server knows.")

    def own_job(job_id: str, who: str = Depends(owner)) -> JobRecord:
        rec = jobs.get(job_id)
        if rec is None or rec.owner != who:  # another owner's job is as unknown as a missing one
            raise ApiError(404, "job_not_found", f"no job {job_id!r} for this API key.")
        return rec

    def links(request: Request, job_id: str) -> schemas.Links:
        return schemas.Links(self=str(request.url_for("get_job", job_id=job_id)),
                             artifacts=str(request.url_for("list_artifacts", job_id=job_id)),
                             bundle=str(request.url_for("get_bundle", job_id=job_id)))

    def status(request: Request, rec: JobRecord) -> schemas.JobStatus:
        steps = jobs.steps(rec)
        state = jobs.state(rec, steps)
        failed_step = next((s for s in steps if s["state"] == "failed"), None)
        tissues = [s for s in steps if s["kind"] in ("bone", "cartilage") and s["state"] == "done"]
        return schemas.JobStatus(
            id=rec.id, state=state, created_at=rec.created_at, input_name=rec.input_name, input_type=rec.input_type,
            options=rec.options, batch_id=rec.batch_id,
            queue_position=jobs.queue_position(rec) if state == "queued" else None,
            progress=round(sum(s["state"] in ("done", "failed") for s in steps) / max(len(steps), 1), 3),
            steps=steps, tissues_ok=[s["step"] for s in tissues if s["status"] == "ok"],
            tissues_failed=[s["step"] for s in tissues if s["status"] != "ok"],
            error=failed_step.get("error") if failed_step else None, deleted=rec.deleted, urls=links(request, rec.id))

    def summary(request: Request, rec: JobRecord) -> schemas.JobSummary:
        return schemas.JobSummary(id=rec.id, state=jobs.state(rec, jobs.steps(rec)), created_at=rec.created_at,
                                  input_name=rec.input_name, url=str(request.url_for("get_job", job_id=rec.id)))

    async def accept(upload: UploadFile, opts: schemas.Options, who: str, batch_id: str | None) -> JobRecord:
        """Store and validate one upload; returns its job record (not yet queued). Nothing is left on failure."""
        name = safe_filename(upload.filename)
        # an image is checked here (readable, 3-D, a model to segment it) and segmented by the first queued step
        options = JobOptions(input_type=opts.input_type, preset=opts.preset, side=opts.side, only=opts.only, bundle=True,
                             hex=HexOptions(element_size=opts.element_size, layers=opts.layers),
                             blend=BlendOptions() if opts.blend else None)
        rec = jobs.create(who, name, opts.input_type, options, batch_id)
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

    def queue(rec: JobRecord) -> None:
        try:
            runner.submit(rec)
        except Exception as exc:
            jobs.store.purge(rec.id)
            log.warning("could not queue job %s: %s", rec.id, exc)
            raise ApiError(503, "queue_unavailable", f"the job queue could not take the job ({type(exc).__name__}); try again later.") from exc
        metrics.submitted()

    def created(request: Request, rec: JobRecord) -> schemas.JobCreated:
        return schemas.JobCreated(id=rec.id, state="queued", queue_position=jobs.queue_position(rec),
                                  urls=links(request, rec.id))

    # routes
    @app.post("/v1/jobs", status_code=202, response_model=schemas.JobCreated, responses=ERRORS, tags=["jobs"])
    async def create_job(request: Request, file: Annotated[UploadFile, File(description="The label map.")],
                         opts: schemas.Options = Depends(form_options), who: str = Depends(owner)):
        """Upload one knee and queue its job; the input is validated first, and a bad one queues nothing."""
        rec = await accept(file, opts, who, None)
        queue(rec)
        return created(request, rec)

    @app.get("/v1/jobs", response_model=schemas.JobList, responses=ERRORS, tags=["jobs"])
    def list_jobs(request: Request, who: str = Depends(owner)):
        """This key's jobs, oldest first."""
        return schemas.JobList(jobs=[summary(request, r) for r in jobs.all() if r.owner == who])

    @app.get("/v1/jobs/{job_id}", response_model=schemas.JobStatus, responses=ERRORS, tags=["jobs"])
    def get_job(request: Request, rec: JobRecord = Depends(own_job)):
        """State, queue position, progress of every step (ingest, segment, each bone, each cartilage, conform, report, bundle), errors."""
        return status(request, rec)

    @app.delete("/v1/jobs/{job_id}", response_model=schemas.JobStatus, responses=ERRORS, tags=["jobs"])
    def delete_job(request: Request, rec: JobRecord = Depends(own_job)):
        """Cancel the job if it has not finished, and delete its upload and artifacts."""
        steps = jobs.steps(rec)
        if jobs.state(rec, steps) not in FINISHED:
            rec.cancelled = True
        rec.deleted = True
        jobs.save(rec)
        runner.cancel(rec, steps)
        jobs.store.delete(rec.id)
        return status(request, rec)

    @app.get("/v1/jobs/{job_id}/artifacts", response_model=schemas.ArtifactList, responses=ERRORS, tags=["artifacts"])
    def list_artifacts(request: Request, rec: JobRecord = Depends(own_job)):
        """Every artifact (name, size, SHA-256, URL); available once the job has succeeded."""
        listed = jobs.store.artifacts(rec.id)
        if listed is None:
            raise ApiError(409, "not_ready", f"job {rec.id} has no artifacts yet (state: {jobs.state(rec, jobs.steps(rec))}).")
        return schemas.ArtifactList(job_id=rec.id, artifacts=[
            schemas.Artifact(**a, url=str(request.url_for("get_artifact", job_id=rec.id, name=a["name"]))) for a in listed])

    def serve(rec: JobRecord, name: str):
        where = jobs.store.locate(rec.id, name)
        if where is None:
            raise ApiError(404, "artifact_not_found", f"job {rec.id} has no artifact {name!r}.")
        if isinstance(where, str):
            return RedirectResponse(where)
        return FileResponse(where, filename=where.name)

    @app.get("/v1/jobs/{job_id}/artifacts/{name:path}", responses=ERRORS, tags=["artifacts"],
             response_class=FileResponse)
    def get_artifact(name: str, rec: JobRecord = Depends(own_job)):
        """Download one artifact by the name the artifact list gives."""
        return serve(rec, name)

    @app.get("/v1/jobs/{job_id}/bundle.zip", responses=ERRORS, tags=["artifacts"], response_class=FileResponse)
    def get_bundle(rec: JobRecord = Depends(own_job)):
        """The bundle: labels used, meshes, surfaces and report.json."""
        return serve(rec, BUNDLE_FILE)

    @app.post("/v1/batches", status_code=202, response_model=schemas.BatchCreated, responses=ERRORS, tags=["batches"])
    async def create_batch(request: Request, files: Annotated[list[UploadFile], File(description="The label maps.")],
                           opts: schemas.Options = Depends(form_options), who: str = Depends(owner)):
        """Many knees with the same options as one batch; all are validated before any is queued."""
        batch_id = uuid.uuid4().hex
        accepted: list[JobRecord] = []
        try:
            for f in files:
                try:
                    accepted.append(await accept(f, opts, who, batch_id))
                except ApiError as exc:
                    exc.message = f"file {len(accepted) + 1} ({f.filename}): {exc.message} No job of the batch was queued."
                    raise
        except BaseException:
            for rec in accepted:
                jobs.store.purge(rec.id)
            raise
        jobs.save_batch(batch_id, who, [r.id for r in accepted])
        for rec in accepted:
            queue(rec)
        return schemas.BatchCreated(id=batch_id, jobs=[created(request, r) for r in accepted],
                                    url=str(request.url_for("get_batch", batch_id=batch_id)))

    @app.get("/v1/batches/{batch_id}", response_model=schemas.BatchStatus, responses=ERRORS, tags=["batches"])
    def get_batch(request: Request, batch_id: str, who: str = Depends(owner)):
        """Counts per state and every job of the batch."""
        batch = jobs.get_batch(batch_id)
        if batch is None or batch["owner"] != who:
            raise ApiError(404, "batch_not_found", f"no batch {batch_id!r} for this API key.")
        rows = [summary(request, r) for r in (jobs.get(j) for j in batch["jobs"]) if r is not None]
        counts = {s: sum(r.state == s for r in rows) for s in get_args(schemas.State)}
        return schemas.BatchStatus(id=batch_id, created_at=batch["created_at"], counts=counts,
                                   done=all(r.state in FINISHED for r in rows), jobs=rows)

    @app.get("/healthz", response_model=schemas.Health, tags=["operations"])
    def healthz():
        """The process is up."""
        return schemas.Health(status="ok", version=__version__)

    @app.get("/readyz", response_model=schemas.Readiness, responses={503: {"model": schemas.Readiness}}, tags=["operations"])
    def readyz():
        """Ready to run jobs: the store is writable and the broker and at least one worker answer."""
        info = runner.ready()
        if info["ready"] and not jobs.store.root.is_dir():
            info = {**info, "ready": False, "detail": f"data folder {jobs.store.root} is missing"}
        return JSONResponse(info, status_code=200 if info["ready"] else 503)

    @app.get("/metrics", tags=["operations"], response_class=Response,
             responses={200: {"content": {"text/plain": {}}, "description": "Prometheus text format."}})
    def prometheus():
        """Prometheus metrics: requests, uploads, rejections, jobs by state."""
        return Response(metrics.render(), media_type=metrics.content_type)

    return app

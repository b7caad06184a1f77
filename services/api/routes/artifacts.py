"""``/v1/jobs/{id}/artifacts`` and the bundle: a finished job's files, by URL."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Request
from fastapi.responses import FileResponse, RedirectResponse

from kneemesh_core.job import BUNDLE_FILE
from services.api import deps, schemas
from services.api.errors import ERRORS, ApiError
from services.jobs import JobRecord, Jobs

router = APIRouter(prefix="/v1/jobs/{job_id}", tags=["artifacts"], responses=ERRORS)


@router.get("/artifacts", response_model=schemas.ArtifactList)
def list_artifacts(request: Request, rec: JobRecord = Depends(deps.own_job), jobs: Jobs = Depends(deps.jobs)):
    """Every artifact (name, size, SHA-256, URL); available once every step has run (a job that ended failed for its
    knee's verdict has them too)."""
    listed = jobs.store.artifacts(rec.id)
    if listed is None:
        raise ApiError(409, "not_ready", f"job {rec.id} has no artifacts yet (state: {jobs.state(rec, jobs.steps(rec))}).")
    return schemas.ArtifactList(job_id=rec.id, artifacts=[
        schemas.Artifact(**a, url=str(request.url_for("get_artifact", job_id=rec.id, name=a["name"]))) for a in listed])


def _serve(jobs: Jobs, rec: JobRecord, name: str):
    where = jobs.store.locate(rec.id, name)
    if where is None:
        raise ApiError(404, "artifact_not_found", f"job {rec.id} has no artifact {name!r}.")
    if isinstance(where, str):
        return RedirectResponse(where)
    return FileResponse(where, filename=where.name)


@router.get("/artifacts/{name:path}", response_class=FileResponse)
def get_artifact(name: str, rec: JobRecord = Depends(deps.own_job), jobs: Jobs = Depends(deps.jobs)):
    """Download one artifact by the name the artifact list gives."""
    return _serve(jobs, rec, name)


@router.get("/bundle.zip", response_class=FileResponse)
def get_bundle(rec: JobRecord = Depends(deps.own_job), jobs: Jobs = Depends(deps.jobs)):
    """The bundle: labels used, meshes, surfaces, attachments and report.json."""
    return _serve(jobs, rec, BUNDLE_FILE)

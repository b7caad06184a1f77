"""Request and response bodies of the API (pydantic v2); the OpenAPI document is built from them."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field

State = Literal["queued", "running", "succeeded", "failed", "cancelled"]
StepState = Literal["pending", "running", "done", "failed"]


class Error(BaseModel):
    code: str = Field(description="Stable machine-readable code, e.g. `not_an_image`, `upload_too_large`.")
    message: str = Field(description="What is wrong and what is expected.")
    details: list[dict] | None = None


class Verdict(BaseModel):
    status: Literal["ok", "review", "failed"]
    reasons: list[str]


class Links(BaseModel):
    self: str
    artifacts: str
    bundle: str


class JobCreated(BaseModel):
    id: str
    state: State
    queue_position: int | None
    urls: Links


def _stage_kinds(schema: dict) -> None:
    """The ``kind`` of a step: the name of its stage, one of the job's stages as declared
    (``kneemesh_core.job.stages``), read when the schema is built."""
    from kneemesh_core.job import STAGES

    schema["enum"] = [stage.name for stage in STAGES]
    schema["description"] = "The step's stage: " + "; ".join(f"`{s.name}`, {s.about}" for s in STAGES) + "."


class StepProgress(BaseModel):
    step: str = Field(description="The step's name: its stage's, or for a stage of one step per tissue the tissue's "
                                  "(`bone`, `cartilage`) or `hex_<cartilage>` (`hexmesh`).")
    kind: str = Field(json_schema_extra=_stage_kinds)
    stage: int = Field(description="The step's stage in the job's plan: steps of one stage may run in parallel, and a step "
                                   "starts once the steps of earlier stages it reads from are done.")
    state: StepState
    status: str | None = Field(None, description="A tissue's outcome: ok, or failed with `error`.")
    started_at: str | None = None
    finished_at: str | None = None
    seconds: float | None = None
    task_id: str | None = Field(None, description="The Celery task that ran the step (Celery mode).")
    worker: str | None = None
    error: Error | None = None


STATE_MEANING = ("queued: waiting for a worker; running: a step has started; succeeded: every step ran and the knee's "
                 "verdict is ok or review; failed: a step failed (see `error`), or every step ran and the knee's verdict is "
                 "failed (see `verdict`; its files can still be downloaded); cancelled: deleted before it finished.")


class JobStatus(BaseModel):
    id: str
    state: State = Field(description=STATE_MEANING)
    created_at: str
    input_name: str
    input_type: str
    options: dict
    batch_id: str | None
    queue_position: int | None = Field(description="1 = next to start; null unless queued.")
    progress: float = Field(description="Fraction of steps finished, 0 to 1.")
    steps: list[StepProgress]
    tissues_ok: list[str]
    tissues_review: list[str] = Field(default_factory=list, description="Meshed, but missing a fidelity or plausibility target (see verdict).")
    tissues_failed: list[str]
    verdict: Verdict | None = Field(None, description="The knee's verdict once its report is written: ok, review or failed, with every reason.")
    error: Error | None = None
    deleted: bool = False
    urls: Links


class JobSummary(BaseModel):
    id: str
    state: State
    created_at: str
    input_name: str
    url: str
    verdict: Verdict | None = Field(None, description="The knee's verdict once its report is written.")
    tissues_failed: list[str] = Field(default_factory=list, description="Tissues with no usable mesh.")


class JobList(BaseModel):
    jobs: list[JobSummary]


class Artifact(BaseModel):
    name: str
    size: int
    sha256: str
    url: str


class ArtifactList(BaseModel):
    job_id: str
    artifacts: list[Artifact]


class BatchCreated(BaseModel):
    id: str
    jobs: list[JobCreated]
    url: str


class BatchStatus(BaseModel):
    id: str
    created_at: str
    counts: dict[str, int]
    done: bool = Field(description="Every job of the batch has finished.")
    jobs: list[JobSummary]


class ManifestEntry(BaseModel):
    id: str
    input_name: str
    state: State
    verdict: Verdict | None = None
    artifacts: list[Artifact] = Field(description="Every file of the job with its SHA-256 (empty until every step has run).")


class BatchManifest(BaseModel):
    id: str
    done: bool = Field(description="Every job of the batch has finished.")
    jobs: list[ManifestEntry]


class Health(BaseModel):
    status: str
    version: str


class Readiness(BaseModel):
    ready: bool
    runner: str
    workers: int
    detail: str

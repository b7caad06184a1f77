"""Where jobs keep their files: one folder per job id, so jobs never collide.

``ROOT/jobs/<id>/record.json`` (who, when, options), ``input/<file>`` (the upload) and
``out/`` (the pipeline's job folder: labels, meshes, steps, report, bundle).
:class:`ArtifactStore` is the small interface the API needs to serve artifacts;
:class:`FileStore` implements it on a directory tree (local disk or a shared
mount, as workers on other machines need). An S3-compatible store would
publish ``out/`` after the bundle step and answer :meth:`ArtifactStore.locate`
with a presigned URL instead of a path.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import time
from pathlib import Path
from typing import Iterator, Protocol

from kneemesh_core.job import MANIFEST_FILE

JOB_ID = re.compile(r"^[0-9a-f]{32}$")
#: How long deleting a job's files waits for a step that was just stopped to stop writing, s.
DELETE_PATIENCE_S = 10.0


class ArtifactStore(Protocol):
    def artifacts(self, job_id: str) -> list[dict] | None:
        """``name``, ``size``, ``sha256`` of each artifact, or None before the job has them."""

    def locate(self, job_id: str, name: str) -> Path | str | None:
        """A local path or a URL for one listed artifact; None if ``name`` is not one."""

    def delete(self, job_id: str) -> None:
        """Remove the job's upload and outputs (its record stays)."""


class FileStore:
    """Job folders under ``root``; safe against ids and names that try to leave them."""

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root).resolve()
        (self.root / "jobs").mkdir(parents=True, exist_ok=True)
        (self.root / "batches").mkdir(parents=True, exist_ok=True)

    def job_dir(self, job_id: str) -> Path | None:
        """The job's folder, or None for an id that is malformed or unknown."""
        if not JOB_ID.match(job_id):
            return None
        d = self.root / "jobs" / job_id
        return d if d.is_dir() else None

    def create(self, job_id: str) -> Path:
        d = self.root / "jobs" / job_id
        d.mkdir()
        (d / "input").mkdir()
        (d / "out").mkdir()
        return d

    def job_ids(self) -> Iterator[str]:
        for d in (self.root / "jobs").iterdir():
            if JOB_ID.match(d.name) and (d / "record.json").exists():
                yield d.name

    def out_dir(self, job_id: str) -> Path:
        return self.root / "jobs" / job_id / "out"

    def input_dir(self, job_id: str) -> Path:
        return self.root / "jobs" / job_id / "input"

    def artifacts(self, job_id: str) -> list[dict] | None:
        try:
            return json.loads((self.out_dir(job_id) / MANIFEST_FILE).read_text())
        except (FileNotFoundError, json.JSONDecodeError):
            return None

    def locate(self, job_id: str, name: str) -> Path | None:
        # Only names in the manifest are served; the resolved path must still lie inside
        # out/ (a symlink planted in a job folder cannot lead elsewhere).
        listed = {a["name"] for a in self.artifacts(job_id) or []}
        if name not in listed:
            return None
        out = self.out_dir(job_id).resolve()
        path = (out / name).resolve()
        return path if path.is_relative_to(out) and path.is_file() else None

    def delete(self, job_id: str) -> None:
        """Remove a job's upload and outputs.  A step stopped a moment ago may still be writing into
        them while they go (rmtree then leaves a folder that is not empty), so this tries again
        until they are gone, for up to ``DELETE_PATIENCE_S``."""
        deadline = time.monotonic() + DELETE_PATIENCE_S
        for sub in ("input", "out"):
            path = self.root / "jobs" / job_id / sub
            shutil.rmtree(path, ignore_errors=True)
            while path.exists() and time.monotonic() < deadline:
                time.sleep(0.05)
                shutil.rmtree(path, ignore_errors=True)

    def purge(self, job_id: str) -> None:
        """Remove every trace of a job (a rejected upload, an expired job)."""
        if JOB_ID.match(job_id):
            shutil.rmtree(self.root / "jobs" / job_id, ignore_errors=True)

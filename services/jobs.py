"""Job records and what a status page shows, read from the files the pipeline writes.

A job's state is derived, never stored twice: the pipeline's step records
(``out/steps/<step>.json``, written by whichever process ran the step) say what
ran, when and how it ended, and the record says who owns the job and whether
it was cancelled. So the embedded pool and Celery workers on other machines
report progress the same way, and a restarted API loses nothing.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import hashlib
import json
import os
import time
import uuid
from pathlib import Path

from kneemesh_core.io.files import atomic_write_json
from kneemesh_core.job import INGEST, REPORT_FILE, STAGES, JobOptions, plan, read_step, utc_now
from services.store import FileStore

STATES = ("queued", "running", "succeeded", "failed", "cancelled")
FINISHED = ("succeeded", "failed", "cancelled")


_last_ns = 0


def _next_ns() -> int:
    """Wall-clock nanoseconds, strictly increasing within this process."""
    global _last_ns
    _last_ns = max(time.time_ns(), _last_ns + 1)
    return _last_ns


#: How long (s) a claimed Idempotency-Key may wait for its job before a repeat takes the claim over.
KEY_CLAIM_S = 600.0


@dataclasses.dataclass
class JobRecord:
    id: str
    owner: str
    created_at: str
    input_name: str
    input_type: str
    options: dict
    batch_id: str | None = None
    cancelled: bool = False
    deleted: bool = False
    created_ns: int = 0  # submission order (created_at ties within a millisecond)


class Jobs:
    """Create, find and describe jobs kept in a :class:`FileStore`."""

    def __init__(self, store: FileStore):
        self.store = store

    # records
    def create(self, owner: str, input_name: str, input_type: str, options: JobOptions,
               batch_id: str | None = None) -> JobRecord:
        rec = JobRecord(uuid.uuid4().hex, owner, utc_now(), input_name, input_type, options.to_dict(), batch_id,
                        created_ns=_next_ns())
        self.store.create(rec.id)
        self.save(rec)
        return rec

    def save(self, rec: JobRecord) -> None:
        atomic_write_json(self.store.root / "jobs" / rec.id / "record.json", dataclasses.asdict(rec))

    def get(self, job_id: str) -> JobRecord | None:
        d = self.store.job_dir(job_id)
        try:
            return JobRecord(**json.loads((d / "record.json").read_text())) if d else None
        except FileNotFoundError:
            return None

    def all(self) -> list[JobRecord]:
        recs = [r for r in (self.get(j) for j in self.store.job_ids()) if r is not None]
        return sorted(recs, key=lambda r: (r.created_ns, r.created_at, r.id))

    def input_path(self, rec: JobRecord) -> Path:
        return self.store.input_dir(rec.id) / rec.input_name

    def out_dir(self, rec: JobRecord) -> Path:
        return self.store.out_dir(rec.id)

    # status
    def steps(self, rec: JobRecord) -> list[dict]:
        """One entry per planned step: state pending/running/done/failed, times, tissue status, error."""
        out = self.out_dir(rec)
        rows = []
        options = JobOptions.from_dict(rec.options)
        for stage_index, stage in enumerate(plan(options)):
            for step in stage:
                r = read_step(out, step) or {"state": "pending"}
                result = r.get("result") if isinstance(r.get("result"), dict) else {}
                row = {"step": step, "kind": STAGES.of(options, step).name, "stage": stage_index, "state": r["state"],
                       "started_at": r.get("started_at"), "finished_at": r.get("finished_at"),
                       "seconds": r.get("seconds"), "status": result.get("status"),
                       "task_id": r.get("task_id"), "worker": r.get("worker")}
                code = r.get("code") or result.get("code")
                if code:
                    row["error"] = {"code": code, "message": r.get("reason") or result.get("reason", "")}
                rows.append(row)
        return rows

    def verdict(self, rec: JobRecord) -> dict | None:
        """The knee's verdict from its report, once written."""
        try:
            return json.loads((self.out_dir(rec) / REPORT_FILE).read_text()).get("verdict")
        except (FileNotFoundError, json.JSONDecodeError):
            return None

    def state(self, rec: JobRecord, steps: list[dict]) -> str:
        """``failed`` when a step failed or every step ran and the knee's verdict is ``failed`` (its files, the
        report among them, can still be downloaded); ``succeeded`` when every step ran and the verdict is ``ok``
        or ``review``; else ``cancelled``, ``running`` or ``queued``."""
        if rec.cancelled:
            return "cancelled"
        if any(s["state"] == "failed" for s in steps):
            return "failed"
        if steps and all(s["state"] == "done" for s in steps):
            return "failed" if (self.verdict(rec) or {}).get("status") == "failed" else "succeeded"
        if any(s["state"] != "pending" for s in steps if s["step"] != INGEST):
            return "running"
        return "queued"

    def queue_position(self, rec: JobRecord) -> int | None:
        """1 for the next job to start: queued jobs of every owner created before this one, plus one."""
        return self.queue_positions([rec.id]).get(rec.id)

    # repeated submissions
    def _key_file(self, owner: str, key: str) -> Path:
        return self.store.root / "idempotency" / (hashlib.sha256(f"{owner}\0{key}".encode()).hexdigest() + ".json")

    def by_key(self, owner: str, key: str) -> JobRecord | None:
        """The live job this owner already created with ``key`` (an ``Idempotency-Key``), if any."""
        try:
            job_id = json.loads(self._key_file(owner, key).read_text())["job"]
        except (FileNotFoundError, json.JSONDecodeError, KeyError):
            return None
        rec = self.get(job_id) if job_id else None  # None: claimed, its job not yet recorded
        return rec if rec is not None and not rec.deleted else None

    def claim_key(self, owner: str, key: str) -> bool:
        """Reserve ``key`` for the one request that may create its job (True), before the upload is
        accepted: a repeat that arrives while the first is still being accepted (a client killed
        mid-upload and started again) must not queue a second job.  False while another request
        holds it; a claim older than :data:`KEY_CLAIM_S` (a server that died holding it) is taken over."""
        path = self._key_file(owner, key)
        path.parent.mkdir(parents=True, exist_ok=True)
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            if time.time() - path.stat().st_mtime < KEY_CLAIM_S:
                return False
            path.unlink(missing_ok=True)
            return self.claim_key(owner, key)
        with os.fdopen(fd, "w") as fh:
            json.dump({"job": None, "claimed_at": utc_now()}, fh)
        return True

    def release_key(self, owner: str, key: str) -> None:
        """Give up a claim whose submission was refused, so that a corrected repeat may go ahead."""
        self._key_file(owner, key).unlink(missing_ok=True)

    def remember_key(self, owner: str, key: str, job_id: str) -> None:
        atomic_write_json(self._key_file(owner, key), {"job": job_id, "created_at": utc_now()})

    def queue_positions(self, ids: list[str]) -> dict[str, int]:
        """Queue positions of the given jobs in one pass (1 = next to start): queued jobs of every
        owner created before each, plus one; jobs not queued are left out."""
        wanted, ahead, out = set(ids), 0, {}
        for other in self.all():
            if self.state(other, self.steps(other)) == "queued":
                ahead += 1
                if other.id in wanted:
                    out[other.id] = ahead
        return out

    # batches
    def save_batch(self, batch_id: str, owner: str, job_ids: list[str]) -> None:
        atomic_write_json(self.store.root / "batches" / f"{batch_id}.json",
                          {"id": batch_id, "owner": owner, "created_at": utc_now(), "jobs": job_ids})

    def get_batch(self, batch_id: str) -> dict | None:
        if not batch_id.isalnum():
            return None
        try:
            return json.loads((self.store.root / "batches" / f"{batch_id}.json").read_text())
        except (FileNotFoundError, json.JSONDecodeError):
            return None

    # retention
    def expire(self, days: float) -> list[str]:
        """Remove jobs created more than ``days`` ago that are finished; returns their ids."""
        limit = dt.datetime.now(dt.timezone.utc) - dt.timedelta(days=days)
        gone = []
        for rec in self.all():
            if dt.datetime.fromisoformat(rec.created_at) < limit and self.state(rec, self.steps(rec)) in FINISHED:
                self.store.purge(rec.id)
                gone.append(rec.id)
        return gone

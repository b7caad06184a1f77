"""``kneemesh submit``: a cohort to a server and its results home, resumable.

Every knee's progress lives in ``OUT/kneemesh-submit.json``, written (atomically) at each change:
submitted with its job id, finished, downloaded and verified.  A rerun after Ctrl-C, a crash or a
server restart reads it and goes on: a knee already home is not touched, a knee with a job id is
polled (never submitted again), and a submission cut short between the upload and the record is
made safe by an ``Idempotency-Key`` (the cohort's and the knee's), which makes the server answer with
the job it already queued.  Each knee's bundle is unpacked into ``OUT/<knee id>/`` and every file is
checked against the job's SHA-256 manifest; ``summary.csv`` has a row per knee.
"""

from __future__ import annotations

import csv
import io
import json
import shutil
import threading
import time
import uuid
import zipfile
from concurrent.futures import ThreadPoolExecutor, as_completed
from pathlib import Path
from typing import Callable

from kneemesh.cohort.client import Api, Rejected, Unreachable
from kneemesh.cohort.discover import Knee
from kneemesh_core.io.files import atomic_write_json, atomic_write_text
from kneemesh_core.job import BUNDLE_FILE, MANIFEST_FILE, REPORT_FILE
from kneemesh_core.job.outputs import sha256
from kneemesh_core.tissues import BONES, CARTILAGES

STATE_FILE = "kneemesh-submit.json"
SUMMARY_FILE = "summary.csv"
FINISHED = ("succeeded", "failed", "cancelled")
#: A knee's client-side states: the last three are final.
DONE, FAILED, REJECTED = "done", "failed", "rejected"


class State:
    """The resumable record of a cohort's submission (thread-safe, written at each change)."""

    def __init__(self, path: Path, server: str, options: dict):
        self.path, self.lock = path, threading.Lock()
        data = json.loads(path.read_text()) if path.exists() else {}
        self.cohort = data.get("cohort") or uuid.uuid4().hex[:16]  # names this cohort's Idempotency-Keys
        self.server, self.options, self.knees = server, options, data.get("knees", {})
        self._write()

    def _write(self) -> None:
        atomic_write_json(self.path, {"cohort": self.cohort, "server": self.server, "options": self.options,
                                      "knees": self.knees})

    def get(self, knee_id: str) -> dict:
        with self.lock:
            return dict(self.knees.get(knee_id, {}))

    def update(self, knee_id: str, **fields) -> dict:
        with self.lock:
            self.knees.setdefault(knee_id, {}).update(fields)
            self._write()
            return dict(self.knees[knee_id])


def _verified(folder: Path, manifest: list[dict]) -> bool:
    for a in manifest:
        if a["name"] == BUNDLE_FILE:
            continue
        f = folder / a["name"]
        if not f.is_file() or f.stat().st_size != a["size"] or sha256(f) != a["sha256"]:
            return False
    return True


def _bring_home(api: Api, job_id: str, folder: Path) -> list[dict]:
    """Download the job's bundle, unpack it into ``folder`` and check every file; returns the manifest."""
    artifacts = api.artifacts(job_id)
    bundle = next(a for a in artifacts if a["name"] == BUNDLE_FILE)
    staging = folder.with_name(folder.name + ".partial")
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    api.download(bundle["url"], staging / BUNDLE_FILE, bundle["sha256"])
    with zipfile.ZipFile(staging / BUNDLE_FILE) as z:
        for name in z.namelist():
            if name.startswith("/") or ".." in Path(name).parts:
                raise Rejected(0, "unsafe_bundle", f"the bundle of job {job_id} holds an unsafe path {name!r}.")
        z.extractall(staging)
    (staging / BUNDLE_FILE).unlink()
    manifest = [a for a in artifacts if a["name"] != BUNDLE_FILE]
    if not _verified(staging, manifest):
        raise Unreachable(f"job {job_id}: the unpacked files do not match the SHA-256 manifest.")
    atomic_write_text(staging / MANIFEST_FILE, json.dumps(manifest, indent=1))
    shutil.rmtree(folder, ignore_errors=True)
    staging.replace(folder)
    return manifest


class Stopped(Exception):
    """The client was asked to stop (Ctrl-C); the state file already holds everything so far."""


def job_progress(job: dict) -> str:
    """One line of where a job stands: queued and its position, or the steps running and how many are done."""
    if job["state"] == "queued":
        position = job.get("queue_position")
        return "queued" + (f", position {position}" if position is not None else "")
    steps = job.get("steps", [])
    running = [s["step"] for s in steps if s["state"] == "running"]
    done = sum(s["state"] in ("done", "failed") for s in steps)
    return f"{job['state']}: " + (", ".join(running) + "; " if running else "") + f"{done}/{len(steps)} steps"


def process(knee: Knee, api: Api, state: State, out: Path, options: dict, poll_s: float,
            stop: threading.Event | None = None, on_progress: Callable[[Knee, str], None] | None = None) -> dict:
    """Take one knee as far as it goes: submit (once), wait, bring home.  Returns its record; ``on_progress``
    hears where its job stands (:func:`job_progress`) at each poll."""
    rec = state.get(knee.id)
    folder = out / knee.id
    if rec.get("state") == DONE and _verified(folder, rec.get("manifest", [])):
        return rec
    if rec.get("state") in (FAILED, REJECTED):
        return rec
    t0 = time.time()
    stop = stop or threading.Event()
    try:
        job_id = rec.get("job_id")
        if job_id:
            try:
                api.job(job_id)
            except Rejected as exc:
                if exc.status != 404:
                    raise
                job_id = None  # the server no longer has it (wiped): submit again
        if not job_id:
            created = api.submit(knee, options, f"{state.cohort}:{knee.id}")
            rec = state.update(knee.id, job_id=created["id"], state="submitted", submitted_at=time.time())
            job_id = created["id"]
        while True:
            job = api.job(job_id)
            if on_progress:
                on_progress(knee, job_progress(job))
            if job["state"] in FINISHED:
                break
            if stop.wait(poll_s):
                raise Stopped(knee.id)
        fields = {"job_state": job["state"], "verdict": (job.get("verdict") or {}).get("status"),
                  "reasons": (job.get("verdict") or {}).get("reasons", []), "tissues_failed": job.get("tissues_failed", []),
                  "job_seconds": round(sum(s.get("seconds") or 0.0 for s in job.get("steps", [])), 1)}
        if job["state"] != "succeeded" and not (job["state"] == "failed" and job.get("verdict")):
            err = job.get("error") or {}
            return state.update(knee.id, state=FAILED, reason=f"job {job['state']}: {err.get('code', '')} {err.get('message', '')}".strip(),
                                **fields)
        # (a job whose every step ran ends failed when the knee's verdict is failed: its files still come home)
        manifest = _bring_home(api, job_id, folder)
        return state.update(knee.id, state=DONE, manifest=manifest, reason=None,
                            client_seconds=round(time.time() - rec.get("submitted_at", t0), 1), **fields)
    except Rejected as exc:
        return state.update(knee.id, state=REJECTED, reason=f"{exc.code}: {exc.message}")


def submit_cohort(knees: list[Knee], api: Api, out: Path, options: dict, concurrency: int = 4, poll_s: float = 2.0,
                  on_done: Callable[[Knee, dict], None] | None = None,
                  on_progress: Callable[[Knee, str], None] | None = None) -> list[dict]:
    """Submit ``knees`` with at most ``concurrency`` in flight and bring each home; writes the state
    file and ``summary.csv`` in ``out``.  Returns one record per knee.  Transient failures that
    outlast the retries leave a knee unfinished (a rerun resumes it)."""
    out.mkdir(parents=True, exist_ok=True)
    state = State(out / STATE_FILE, str(api.http.base_url), options)
    records: dict[str, dict] = {}
    stop = threading.Event()
    pool = ThreadPoolExecutor(max_workers=max(1, concurrency))
    try:
        futures = {pool.submit(process, k, api, state, out, options, poll_s, stop, on_progress): k for k in knees}
        for fut in as_completed(futures):
            knee = futures[fut]
            try:
                records[knee.id] = fut.result()
            except Unreachable as exc:
                records[knee.id] = state.update(knee.id, last_error=str(exc))
            if on_done:
                on_done(knee, records[knee.id])
    except BaseException:  # Ctrl-C: stop polling, queue nothing new; a rerun resumes from the state file
        stop.set()
        pool.shutdown(wait=True, cancel_futures=True)
        write_summary(knees, state, out)
        raise
    pool.shutdown()
    write_summary(knees, state, out)
    return [records[k.id] for k in knees]


def _tissue_columns(report: dict) -> dict:
    cols = {}
    for t in BONES + CARTILAGES:
        r = report.get("tissues", {}).get(t, {})
        cols[f"{t}_status"] = r.get("status", "")
        if t in CARTILAGES:
            cols[f"{t}_element_size_mm"] = r.get("element_size_mm", "")
            cols[f"{t}_min_sj"] = r.get("min_scaled_jacobian", "")
            cols[f"{t}_coverage"] = r.get("coverage", "")
            cols[f"{t}_volume_error"] = r.get("volume_error", "")
        else:
            cols[f"{t}_distance_p95_mm"] = (r.get("surface_distance_mm") or {}).get("p95", "")
    return cols


def write_summary(knees: list[Knee], state: State, out: Path) -> Path:
    """``summary.csv``: knee, visit, side, state, verdict and reasons, per-tissue quality, timings,
    failure reason."""
    rows = []
    for k in knees:
        rec = state.get(k.id)
        report = {}
        if rec.get("state") == DONE and (out / k.id / REPORT_FILE).exists():
            report = json.loads((out / k.id / REPORT_FILE).read_text())
        rows.append({"knee": k.id, "visit": k.visit or "", "side": report.get("input", {}).get("side") or k.side or "",
                     "state": rec.get("state", "pending"), "job_id": rec.get("job_id", ""),
                     "verdict": rec.get("verdict") or "", "reasons": "; ".join(rec.get("reasons") or []),
                     "tissues_failed": " ".join(rec.get("tissues_failed") or []), **_tissue_columns(report),
                     "job_seconds": rec.get("job_seconds", ""), "client_seconds": rec.get("client_seconds", ""),
                     "failure": rec.get("reason") or rec.get("last_error") or ""})
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(rows[0]) if rows else ["knee"])
    writer.writeheader()
    writer.writerows(rows)
    path = out / SUMMARY_FILE
    atomic_write_text(path, buf.getvalue())
    return path

"""A small KneeMesh API client for a lab's machine: retries what is transient, never what is not.

Transient: the server cannot be reached (connection refused or reset, timeouts), a 5xx, a 429, or
503 ``queue_unavailable``; these are retried with exponential backoff and jitter.  A 4xx is the
server saying the request itself is wrong (a bad file, a bad option): it is raised at once as
:class:`Rejected` with the server's code and message, never retried.
"""

from __future__ import annotations

import hashlib
import random
import tempfile
import time
import zipfile
from pathlib import Path
from typing import Callable

import httpx

from kneemesh.cohort.discover import Knee


class Rejected(Exception):
    """The server refused a request (4xx): retrying the same request cannot help."""

    def __init__(self, status: int, code: str, message: str):
        super().__init__(f"{status} {code}: {message}")
        self.status, self.code, self.message = status, code, message


class Unreachable(Exception):
    """Transient failures went on past the retry budget."""


class Api:
    def __init__(self, server: str, key: str | None = None, *, retries: int = 8, backoff_s: float = 1.0,
                 max_backoff_s: float = 30.0, timeout_s: float = 120.0, sleep: Callable[[float], None] = time.sleep):
        headers = {"X-API-Key": key} if key else {}
        self.http = httpx.Client(base_url=server.rstrip("/"), headers=headers, timeout=timeout_s, follow_redirects=True)
        self.retries, self.backoff_s, self.max_backoff_s, self.sleep = retries, backoff_s, max_backoff_s, sleep

    def close(self) -> None:
        self.http.close()

    def request(self, method: str, url: str, **kw) -> httpx.Response:
        """One request with retries of transient failures; raises :class:`Rejected` on a 4xx and
        :class:`Unreachable` when the retries are spent."""
        last = ""
        for attempt in range(self.retries + 1):
            if attempt:
                self.sleep(min(self.backoff_s * 2 ** (attempt - 1), self.max_backoff_s) * random.uniform(0.5, 1.0))
            try:
                r = self.http.request(method, url, **kw)
            except (httpx.TransportError, OSError) as exc:  # refused, reset, timed out, DNS
                last = f"{type(exc).__name__}: {exc}"
                continue
            if r.status_code < 400:
                return r
            try:
                body = r.json()
            except ValueError:
                body = {}
            code, message = body.get("code", f"http_{r.status_code}"), body.get("message", r.text[:200])
            if r.status_code >= 500 or r.status_code == 429:
                last = f"{r.status_code} {code}: {message}"
                continue
            raise Rejected(r.status_code, code, message)
        raise Unreachable(f"{method} {url}: gave up after {self.retries + 1} tries ({last}).")

    def submit(self, knee: Knee, options: dict, idempotency_key: str) -> dict:
        """Upload one knee (a DICOM series as a zip) and queue its job.  The key makes a repeat of the
        same submission (after a crash between the upload and the client's record of it) return the
        job already queued instead of a second job."""
        data = {k: str(v).lower() if isinstance(v, bool) else str(v) for k, v in options.items() if v is not None}
        data["input_type"] = knee.input_type
        if knee.side and "side" not in options:
            data["side"] = knee.side
        headers = {"Idempotency-Key": idempotency_key}
        with tempfile.TemporaryDirectory(prefix="kneemesh-upload-") as tmp:
            path = knee.path
            if knee.files:  # a DICOM series: one zip of its files
                path = Path(tmp) / (Path(knee.id).name + ".zip")
                with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as z:
                    for f in knee.files:
                        z.write(f, f.name)
            with open(path, "rb") as fh:
                return self.request("POST", "/v1/jobs", data=data, files={"file": (path.name, fh)}, headers=headers).json()

    def job(self, job_id: str) -> dict:
        return self.request("GET", f"/v1/jobs/{job_id}").json()

    def artifacts(self, job_id: str) -> list[dict]:
        return self.request("GET", f"/v1/jobs/{job_id}/artifacts").json()["artifacts"]

    def download(self, url: str, dest: Path, sha256: str) -> None:
        """Stream ``url`` to ``dest`` (through a temporary name), checking its SHA-256."""
        dest.parent.mkdir(parents=True, exist_ok=True)
        part = dest.with_name(dest.name + ".part")
        for attempt in range(3):
            h = hashlib.sha256()
            try:
                with self.http.stream("GET", url) as r:
                    if r.status_code >= 400:
                        r.read()
                        raise Rejected(r.status_code, "download_failed", r.text[:200])
                    with open(part, "wb") as fh:
                        for chunk in r.iter_bytes(1 << 20):
                            h.update(chunk)
                            fh.write(chunk)
            except (httpx.TransportError, OSError):
                if attempt == 2:
                    raise
                self.sleep(self.backoff_s * 2 ** attempt)
                continue
            if h.hexdigest() == sha256:
                part.replace(dest)
                return
        part.unlink(missing_ok=True)
        raise Unreachable(f"{url}: the download's SHA-256 did not match the manifest three times.")

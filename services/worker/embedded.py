"""Embedded mode: the API runs jobs itself on a pool of processes, so one machine needs nothing else.

Jobs run one after another in submission order (one dispatcher thread); the
steps of each job share the pool, exactly as ``kneemesh mesh`` runs them.
Jobs left unfinished by a previous run of the server are resumed at start:
their finished steps are skipped.  The pool's processes end with the server however it
ends (a clean stop, a crash, ``kill -9``, the OOM killer): each watches its parent and
exits once it is gone, so no orphan keeps meshing or holding memory.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import queue
import threading
import time
from concurrent.futures import ProcessPoolExecutor

from kneemesh_core.job import JobCancelled, JobOptions, run
from services.jobs import FINISHED, Jobs

log = logging.getLogger("kneemesh.embedded")

#: How often a pool process checks that its server is still there, s.
PARENT_CHECK_S = 0.5


def _exit_with_parent(parent_pid: int) -> None:
    """Pool initializer: a daemon thread ends this process once ``parent_pid`` is no longer its
    parent (the server died, and this process was handed to init or a subreaper)."""

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(PARENT_CHECK_S)
        os._exit(0)

    threading.Thread(target=watch, name="kneemesh-parent-watch", daemon=True).start()


class EmbeddedRunner:
    name = "embedded"

    def __init__(self, workers: int = 2):
        self.workers = workers
        self._queue: queue.Queue[str | None] = queue.Queue()
        self._pool: ProcessPoolExecutor | None = None
        self._thread: threading.Thread | None = None

    def start(self, jobs: Jobs) -> None:
        self._jobs = jobs
        # spawn: the server has threads, and forking a threaded process can deadlock.
        self._pool = ProcessPoolExecutor(self.workers, mp_context=multiprocessing.get_context("spawn"),
                                         initializer=_exit_with_parent, initargs=(os.getpid(),))
        self._thread = threading.Thread(target=self._loop, name="kneemesh-embedded", daemon=True)
        self._thread.start()
        for rec in jobs.all():
            if not rec.deleted and jobs.state(rec, jobs.steps(rec)) not in FINISHED:
                self._queue.put(rec.id)

    def stop(self) -> None:
        self._queue.put(None)
        if self._thread is not None:
            self._thread.join(timeout=5)
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)

    def submit(self, rec) -> None:
        self._queue.put(rec.id)

    def cancel(self, rec, steps: list[dict]) -> None:
        """Steps not yet started are skipped; a step already on the pool runs to its end (its output is deleted)."""

    def ready(self) -> dict:
        alive = self._thread is not None and self._thread.is_alive()
        return {"ready": alive, "runner": self.name, "workers": self.workers if alive else 0,
                "detail": "ok" if alive else "the in-process worker is not running"}

    def _loop(self) -> None:
        while (job_id := self._queue.get()) is not None:
            rec = self._jobs.get(job_id)
            if rec is None or rec.cancelled or rec.deleted:
                continue
            try:
                run(self._jobs.input_path(rec), self._jobs.out_dir(rec), JobOptions.from_dict(rec.options),
                    pool=self._pool, workers=self.workers, fresh=False, cancelled=lambda: self._cancelled(job_id))
            except JobCancelled:
                log.info("job %s cancelled", job_id)
            except Exception:  # recorded in the job's step records; the loop serves the next job
                log.exception("job %s failed", job_id)

    def _cancelled(self, job_id: str) -> bool:
        rec = self._jobs.get(job_id)
        return rec is None or rec.cancelled or rec.deleted

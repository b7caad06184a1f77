"""The in-process runner: a whole job's plan in this process and a pool of workers
(the ``kneemesh`` command line and the service's embedded mode)."""

from __future__ import annotations

import os
import shutil
from concurrent.futures import Executor, ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Callable

from kneemesh_core.job.options import JobOptions
from kneemesh_core.job.outputs import REPORT_FILE, STEPS_DIR, read_json
from kneemesh_core.job.plan import plan, run_step

#: Called with (step, state) as each step starts ("running") and ends (a tissue's status, or "done").
Progress = Callable[[str, str], None]


class JobCancelled(Exception):
    """Raised by :func:`run` between stages when its ``cancelled`` callback says so."""


def run(
    input_path: str | os.PathLike,
    out_dir: str | os.PathLike,
    options: JobOptions = JobOptions(),
    *,
    workers: int = 2,
    pool: Executor | None = None,
    fresh: bool = True,
    progress: Progress | None = None,
    cancelled: Callable[[], bool] | None = None,
) -> dict:
    """Run the whole :func:`.plan.plan` in this process and return the report.

    Steps of a stage run on ``pool`` (or a new pool of ``workers`` processes;
    one worker runs them here). ``fresh`` forgets the step records of an
    earlier run into ``out_dir``; without it, steps already done are skipped
    (the embedded service resumes jobs whose ingest the API has done).
    ``cancelled`` is asked before each stage; it raises :class:`JobCancelled`.
    """
    say = progress or (lambda step, state: None)
    if fresh:
        shutil.rmtree(Path(out_dir) / STEPS_DIR, ignore_errors=True)
    opts = options.to_dict()
    own_pool = pool is None and workers > 1
    if own_pool:
        pool = ProcessPoolExecutor(max_workers=workers)
    try:
        for stage in plan(options):
            if cancelled is not None and cancelled():
                raise JobCancelled(str(out_dir))
            if pool is None or len(stage) == 1:
                for step in stage:
                    say(step, "running")
                    say(step, _outcome(run_step(out_dir, step, opts, input_path)))
                continue
            for step in stage:
                say(step, "running")
            futures = {pool.submit(run_step, str(out_dir), step, opts): step for step in stage}
            for fut in as_completed(futures):
                say(futures[fut], _outcome(fut.result()))
    finally:
        if own_pool:
            pool.shutdown()
    return read_json(Path(out_dir) / REPORT_FILE)


def _outcome(record: dict) -> str:
    """What a progress line shows for a finished step: a tissue's status, else 'done'."""
    return record.get("result", {}).get("status", "done") if isinstance(record.get("result"), dict) else "done"

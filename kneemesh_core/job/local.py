"""The in-process runner: a whole job's plan in this process and a pool of workers
(the ``kneemesh`` command line and the service's embedded mode)."""

from __future__ import annotations

import os
import shutil
from concurrent.futures import FIRST_COMPLETED, Executor, Future, ProcessPoolExecutor, wait
from pathlib import Path
from typing import Callable

from kneemesh_core.job.options import JobOptions
from kneemesh_core.job.outputs import REPORT_FILE, STEPS_DIR, read_json
from kneemesh_core.job.plan import needs, plan, run_step, start_order
from kneemesh_core.job.stages import STAGES
from kneemesh_core.job.steps import warm_up

#: Called with (step, state) as each step starts ("running") and ends (a tissue's status, or "done").
Progress = Callable[[str, str], None]


class JobCancelled(Exception):
    """Raised by :func:`run` before a step when its ``cancelled`` callback says so."""


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

    Each step starts as soon as the steps it waits for (:func:`.plan.needs`) are done and one of
    ``workers`` is free, the cartilages' meshes first (:func:`.plan.start_order`): on ``pool`` (or a
    new pool of ``workers`` processes, started at once to warm up (:func:`.steps.warm_up`) while
    the input is read; one worker runs them here).  ``fresh`` forgets the step records of an
    earlier run into ``out_dir``; without it, steps already done are skipped
    (the embedded service resumes jobs whose ingest the API has done).
    ``cancelled`` is asked before each step starts; it raises :class:`JobCancelled`.
    """
    say = progress or (lambda step, state: None)
    if fresh:
        shutil.rmtree(Path(out_dir) / STEPS_DIR, ignore_errors=True)
    opts = options.to_dict()
    stages = plan(options)
    waits = needs(options)
    reads_input = {s for stage in STAGES if stage.input for s in stage.planned_steps(options)}
    order = start_order(stages)
    own_pool = pool is None and workers > 1
    if own_pool:
        pool = ProcessPoolExecutor(max_workers=workers, initializer=warm_up)
        pool.submit(int)  # the workers start now and warm up while this process reads the input
    done: set[str] = set()
    running: dict[Future, str] = {}
    try:
        while len(done) < len(order):
            if cancelled is not None and cancelled():
                raise JobCancelled(str(out_dir))
            ready = [s for s in order if s not in done and s not in running.values() and waits[s] <= done]
            for step in ready[: workers - len(running)]:  # a step goes to a free worker, not to a queue
                say(step, "running")
                if pool is None or step in reads_input:  # alone by the plan: ingest and segment start a job
                    say(step, _outcome(run_step(out_dir, step, opts, input_path)))
                    done.add(step)
                    break  # what it unlocks is scheduled on the next turn
                running[pool.submit(run_step, str(out_dir), step, opts)] = step
            if running:
                finished, _ = wait(running, return_when=FIRST_COMPLETED)
                for fut in finished:
                    step = running.pop(fut)
                    say(step, _outcome(fut.result()))
                    done.add(step)
    finally:
        if own_pool:
            pool.shutdown()
    return read_json(Path(out_dir) / REPORT_FILE)


def _outcome(record: dict) -> str:
    """What a progress line shows for a finished step: a tissue's status, else 'done'."""
    return record.get("result", {}).get("status", "done") if isinstance(record.get("result"), dict) else "done"

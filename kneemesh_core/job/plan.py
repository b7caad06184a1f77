"""The plan of a job, and :func:`run_step`, which runs and records one step of it.

A job is a list of stages run in order (:func:`plan`), from the declarations of :mod:`.stages`: each
stage comes after the stages it reads, and the steps of one stage are independent of each other, so a
runner may run them in parallel, or start each step as soon as those it reads from are done
(:func:`needs`), in :func:`start_order`.

:func:`run_step` records each step in ``steps/<step>.json`` (running, done or failed, with times), which
is what status pages read; a step already done is not run again, so a queue may deliver a step twice.
The CLI and the embedded pool (:mod:`.local`) and the Celery canvas (``services.worker``) all run this
plan.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

from kneemesh_core.errors import KneeMeshError
from kneemesh_core.job.options import JobOptions
from kneemesh_core.job.outputs import read_step, utc_now, write_step
from kneemesh_core.job.stages import ANATOMY, EARLIER, INGEST, STAGES, Stage
from kneemesh_core.job.steps import Step, hex_step
from kneemesh_core.tissues import BONES, CARTILAGES


def _present(options: JobOptions) -> list[tuple[Stage, tuple[str, ...]]]:
    """The stages a job with ``options`` has, in declaration order, each with its steps."""
    return [(stage, steps) for stage in STAGES if (steps := stage.planned_steps(options))]


def _after(stage: Stage, earlier: list[Stage]) -> list[Stage]:
    """The stages of ``earlier`` (declared before ``stage``, in the job's plan) that ``stage`` follows."""
    declared = [s.name for s in STAGES]
    wrong = [a for a in stage.after if a != EARLIER and (a not in declared or declared.index(a) > declared.index(stage.name))]
    if wrong:
        raise KneeMeshError("internal", f"stage {stage.name!r} comes after {wrong}: not declared before it.")
    return list(earlier) if EARLIER in stage.after else [s for s in earlier if s.name in stage.after]


def plan(options: JobOptions) -> list[tuple[str, ...]]:
    """The stages of a job, in order: a stage's steps come one stage after the last of the stages they
    read; the steps of one stage may run in parallel (ordered by :data:`FIRST`)."""
    present = _present(options)
    level: dict[str, int] = {}
    for i, (stage, _) in enumerate(present):
        level[stage.name] = 1 + max((level[s.name] for s in _after(stage, [s for s, _ in present[:i]])), default=-1)
    stages: list[list[str]] = [[] for _ in range(max(level.values()) + 1)]
    for stage, steps in present:
        stages[level[stage.name]].extend(steps)
    return [tuple(sorted(stage, key=_first)) for stage in stages]


def needs(options: JobOptions) -> dict[str, set[str]]:
    """The steps each step of a job's plan waits for: those of the stages it comes after (where it reads
    only some of them, those), and what they wait for in turn.  A runner that starts each step as soon as
    these are done (:mod:`.local`) lets the anatomy and the short blends run while the femoral cartilage
    is still meshed; one that runs stage after stage (Celery) meets them too."""
    present = _present(options)
    waits: dict[str, set[str]] = {}
    for i, (stage, steps) in enumerate(present):
        before = {s.name: st for s, st in present[:i]}
        direct = [step for s in _after(stage, [s for s, _ in present[:i]]) for step in before[s.name]]
        for step in steps:
            reads = [d for d in direct if stage.reads is None or d in stage.reads(step)]
            waits[step] = set(reads).union(*(waits[d] for d in reads))
    return waits


def run_step(
    out_dir: str | os.PathLike,
    step: str,
    options: dict,
    input_path: str | os.PathLike | None = None,
    context: dict | None = None,
) -> dict:
    """Run one step of a job's plan and return its record; a step already done is not run again.

    ``context`` (who runs it: task id, host, pid) is kept in the record.  Tissue steps never raise:
    their failures are report entries.  The other steps raise on failure after recording it, except
    that a failed ingest writes nothing at all (bad input leaves no half-written job).
    """
    done = read_step(out_dir, step)
    if done is not None and done["state"] == "done":
        return done
    opts = JobOptions.from_dict(options)
    try:
        stage = STAGES.of(opts, step)
    except KeyError:
        raise KneeMeshError("bad_option", f"unknown step {step!r}.") from None
    work = Step(step, Path(out_dir), opts, None if input_path is None else Path(input_path))
    who = dict(context or {})
    started, t0 = utc_now(), time.perf_counter()
    if step == INGEST:
        result = stage.run(work)
    else:
        write_step(out_dir, step, {"state": "running", "started_at": started, **who})
        try:
            result = stage.run(work)
        except Exception as exc:
            code, reason = (exc.code, exc.message) if isinstance(exc, KneeMeshError) else ("internal", f"{type(exc).__name__}: {exc}")
            write_step(out_dir, step, {"state": "failed", "started_at": started, "finished_at": utc_now(),
                                       "seconds": round(time.perf_counter() - t0, 3), "code": code, "reason": reason, **who})
            raise
    record = {"state": "done", "started_at": started, "finished_at": utc_now(),
              "seconds": round(time.perf_counter() - t0, 3), "result": result, **who}
    write_step(out_dir, step, record)
    return {"step": step, **record}


#: Which steps start first when several could (after the plan's stage order): each cartilage's mesh,
#: the femoral first, since their times are the longest and the least predictable (an OAI knee's
#: femoral cartilage takes 3-9 s, any cartilage's fallback chain can multiply its time); then the
#: bones, the femur first (its cartilage's blend waits for it); then the femoral blend (1.5 s) and
#: the anatomy (1.4 s) before the short blends (0.3 s).  Scheduled this way on the step times of the
#: 40 OAI maps, a job takes median 9.8 s (max 21.0) after its start-up, against 10.0 (25.1) with the
#: longest typical chain first and 10.3 (25.7) stage after stage.
FIRST = (*(hex_step(c) for c in CARTILAGES), *BONES, "femoral_cartilage", ANATOMY)


def _first(step: str) -> int:
    """Where a step stands among those of its stage: those of :data:`FIRST` first, in its order."""
    return FIRST.index(step) if step in FIRST else len(FIRST)


def start_order(stages: list[tuple[str, ...]]) -> list[str]:
    """Every step of ``stages`` (a :func:`plan`, which orders each stage by :data:`FIRST`), in the
    order a runner starts those that are ready: stage by stage."""
    return [step for stage in stages for step in stage]

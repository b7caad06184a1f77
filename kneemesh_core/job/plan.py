"""The plan of a job, and :func:`run_step`, which runs and records one step of it.

A job is a list of stages run in order; the steps of one stage are independent of each
other, so a runner may run them in parallel, or start each step as soon as those it reads
from are done (:func:`needs`), in :func:`start_order`:

1. ``ingest`` reads the input, decides the label convention and the side, and writes
   canonical labels and ``job.json``; for an image, ``segment`` then writes the labels;
2. one step per bone and, beside them, one per cartilage that meshes it (``hex_<cartilage>``:
   a cartilage's mesh needs only the labels); then one per cartilage that blends and fuses its
   mesh onto its bone's;
3. ``conform`` (with blending, when bones and cartilages are both meshed) lets each bone
   give way where a fused cartilage still dips into it;
4. ``anatomy`` (when the bones are meshed) places the knee's frames and the ligament and
   tendon attachment sites on the bone meshes; ``decks`` (when every tissue is meshed) writes the
   Abaqus and CalculiX decks, and beside them ``overlaps`` measures where the final meshes
   overlap; ``simulate`` (on request) runs CalculiX on the decks;
5. ``report`` gathers the entries into ``report.json``;
6. ``bundle`` (optional) zips the outputs and lists every artifact.

:func:`run_step` records each step in ``steps/<step>.json`` (running, done or failed, with
times), which is what status pages read; a step already done is not run again, so a queue
may deliver a step twice.  The CLI and the embedded pool (:mod:`.local`) and the Celery
canvas (``services.worker``) all run this plan.  A new stage is a name here, a function in
:mod:`.steps` and a branch in :func:`run_step`.
"""

from __future__ import annotations

import os
import time

from kneemesh_core.errors import KneeMeshError
from kneemesh_core.job.options import JobOptions
from kneemesh_core.job.outputs import bundle, read_step, utc_now, write_report, write_step
from kneemesh_core.job.steps import (conform_bones, hex_cartilage, hex_step, ingest, measure_overlaps, mesh_tissue,
                                    place_anatomy, run_simulation, segment_input, write_decks)
from kneemesh_core.tissues import BONE_OF, BONES, CARTILAGES, TISSUES

INGEST, SEGMENT, CONFORM, ANATOMY, DECKS, OVERLAPS, SIMULATE, REPORT, BUNDLE = (
    "ingest", "segment", "conform", "anatomy", "decks", "overlaps", "simulate", "report", "bundle")
#: the step that meshes each cartilage before its own step blends it, and the cartilage it meshes
HEX_STEPS = {hex_step(c): c for c in CARTILAGES}


def plan(options: JobOptions) -> list[tuple[str, ...]]:
    """The stages of a job, in order; the steps of one stage may run in parallel."""
    tissues = options.tissues()
    stages: list[tuple[str, ...]] = [(INGEST,)] + ([(SEGMENT,)] if options.input_type == "image" else [])
    # the anatomy needs only the bones and the labels: it runs beside the cartilages' blends (or after
    # the bones when no cartilage is asked for)
    anatomy = (ANATOMY,) if set(tissues) >= set(BONES) else ()
    cartilages = tuple(t for t in tissues if t in CARTILAGES)
    meshing = tuple([t for t in tissues if t in BONES] + [hex_step(c) for c in cartilages])
    if meshing:
        stages.append(meshing)
    if cartilages or anatomy:
        stages.append(cartilages + anatomy)
    if options.blend is not None and set(tissues) >= set(BONES) | set(CARTILAGES):
        stages.append((CONFORM,))
    # the final meshes: the decks (of a whole knee) beside the measurement of their overlaps
    final = ((DECKS,) if set(tissues) == set(TISSUES) else ()) + ((OVERLAPS,) if cartilages else ())
    if final:
        stages.append(final)
    if DECKS in final and options.simulate != "none":
        stages.append((SIMULATE,))
    stages.append((REPORT,))
    if options.bundle:
        stages.append((BUNDLE,))
    return [tuple(sorted(stage, key=_first)) for stage in stages]


def needs(stages: list[tuple[str, ...]]) -> dict[str, set[str]]:
    """The steps each step of ``stages`` (a :func:`plan`) waits for: every step of the stages before
    its own, except that of the stage just before, a cartilage's blend waits only for its own mesh
    and its bone's, and the anatomy only for the bones.  A runner that starts each step as soon as
    these are done (:mod:`.local`) lets the anatomy and the short blends run while the femoral
    cartilage is still meshed; one that runs stage after stage (Celery) meets them too."""
    reads = {c: {hex_step(c), BONE_OF[c]} for c in CARTILAGES} | {ANATOMY: set(BONES)}
    waits: dict[str, set[str]] = {}
    before: set[str] = set()
    for i, stage in enumerate(stages):
        last = set(stages[i - 1]) if i else set()
        for step in stage:
            waits[step] = (before - last) | (last & reads[step]) if step in reads else set(before)
        before |= set(stage)
    return waits


def run_step(
    out_dir: str | os.PathLike,
    step: str,
    options: dict,
    input_path: str | os.PathLike | None = None,
    context: dict | None = None,
) -> dict:
    """Run one step of a job's plan and return its record; a step already done is not run again.

    ``context`` (who runs it: task id, host, pid) is kept in the record. Tissue
    steps never raise: their failures are report entries. ``ingest``,
    ``report`` and ``bundle`` raise on failure after recording it, except that a
    failed ingest writes nothing at all (bad input leaves no half-written job).
    """
    done = read_step(out_dir, step)
    if done is not None and done["state"] == "done":
        return done
    who = dict(context or {})
    started, t0 = utc_now(), time.perf_counter()
    if step == INGEST:
        if input_path is None:
            raise KneeMeshError("bad_option", "the ingest step needs the input file.")
        ingest(input_path, out_dir, JobOptions.from_dict(options))
        result: dict = {"status": "ok"}
    else:
        write_step(out_dir, step, {"state": "running", "started_at": started, **who})
        try:
            result = _run(out_dir, step, options, input_path)
        except Exception as exc:
            code, reason = (exc.code, exc.message) if isinstance(exc, KneeMeshError) else ("internal", f"{type(exc).__name__}: {exc}")
            write_step(out_dir, step, {"state": "failed", "started_at": started, "finished_at": utc_now(),
                                       "seconds": round(time.perf_counter() - t0, 3), "code": code, "reason": reason, **who})
            raise
    record = {"state": "done", "started_at": started, "finished_at": utc_now(),
              "seconds": round(time.perf_counter() - t0, 3), "result": result, **who}
    write_step(out_dir, step, record)
    return {"step": step, **record}


def _run(out_dir: str | os.PathLike, step: str, options: dict, input_path: str | os.PathLike | None) -> dict:
    """The work of one step after ingest; returns its result."""
    if step in TISSUES:
        return mesh_tissue(out_dir, step, options)
    if step in HEX_STEPS:
        return hex_cartilage(out_dir, HEX_STEPS[step], options)
    if step == SEGMENT:
        if input_path is None:
            raise KneeMeshError("bad_option", "the segment step needs the input image.")
        return segment_input(input_path, out_dir, JobOptions.from_dict(options))
    if step == CONFORM:
        return conform_bones(out_dir, options)
    if step == ANATOMY:
        return place_anatomy(out_dir, options)
    if step == DECKS:
        return write_decks(out_dir, options)
    if step == OVERLAPS:
        return measure_overlaps(out_dir)
    if step == SIMULATE:
        return run_simulation(out_dir, options)
    if step == REPORT:
        opts = JobOptions.from_dict(options)
        entries = {t: read_step(out_dir, t)["result"] for t in opts.tissues()}
        planned = sum(plan(opts), ())
        conformed = read_step(out_dir, CONFORM)["result"] if CONFORM in planned else None
        segmentation, anatomy, fe, simulation, overlaps = (read_step(out_dir, s)["result"] if s in planned else None
                                                           for s in (SEGMENT, ANATOMY, DECKS, SIMULATE, OVERLAPS))
        return write_report(out_dir, entries, conformed, anatomy, fe, simulation, overlaps, segmentation)["summary"]
    if step == BUNDLE:
        return {"artifacts": len(bundle(out_dir))}
    raise KneeMeshError("bad_option", f"unknown step {step!r}.")


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

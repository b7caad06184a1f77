"""The plan of a job, and :func:`run_step`, which runs and records one step of it.

A job is a list of stages run in order; the steps of one stage are independent of each
other, so a runner may run them in parallel:

1. ``ingest`` reads the input, decides the label convention and the side, and writes
   canonical labels and ``job.json``; for an image, ``segment`` then writes the labels;
2. one step per bone and, beside them, one per cartilage that meshes it (``hex_<cartilage>``:
   a cartilage's mesh needs only the labels); then one per cartilage that blends and fuses its
   mesh onto its bone's;
3. ``conform`` (with blending, when bones and cartilages are both meshed) lets each bone
   give way where a fused cartilage still dips into it;
4. ``anatomy`` (when the bones are meshed) places the knee's frames and the ligament and
   tendon attachment sites on the bone meshes; ``decks`` (when every tissue is meshed) writes the
   Abaqus and CalculiX decks; ``simulate`` (on request) runs CalculiX on them;
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
from pathlib import Path
from typing import Iterable

from kneemesh_core.errors import KneeMeshError
from kneemesh_core.job.options import JobOptions
from kneemesh_core.job.outputs import MESHES_DIR, bundle, read_step, utc_now, write_report, write_step
from kneemesh_core.job.steps import (conform_bones, hex_cartilage, hex_step, ingest, mesh_tissue, place_anatomy,
                                    run_simulation, segment_input, write_decks)
from kneemesh_core.metrics.overlap import knee_overlaps
from kneemesh_core.tissues import BONES, CARTILAGES, TISSUES

INGEST, SEGMENT, CONFORM, ANATOMY, DECKS, SIMULATE, REPORT, BUNDLE = (
    "ingest", "segment", "conform", "anatomy", "decks", "simulate", "report", "bundle")
#: the step that meshes each cartilage before its own step blends it, and the cartilage it meshes
HEX_STEPS = {hex_step(c): c for c in CARTILAGES}


def plan(options: JobOptions) -> list[tuple[str, ...]]:
    """The stages of a job, in order; the steps of one stage may run in parallel."""
    tissues = options.tissues()
    stages: list[tuple[str, ...]] = [(INGEST,)] + ([(SEGMENT,)] if options.input_type == "image" else [])
    # the anatomy needs only the bones and the labels: it runs beside the cartilages' blends (or after
    # the bones when no cartilage is asked for)
    anatomy = (ANATOMY,) if set(tissues) >= set(BONES) else ()
    cartilages = tuple(_longest_first(t for t in tissues if t in CARTILAGES))
    meshing = tuple(_longest_first([t for t in tissues if t in BONES] + [hex_step(c) for c in cartilages]))
    if meshing:
        stages.append(meshing)
    if cartilages or anatomy:
        stages.append(cartilages[:1] + anatomy + cartilages[1:])  # the longest first, the anatomy next
    if options.blend is not None and set(tissues) >= set(BONES) | set(CARTILAGES):
        stages.append((CONFORM,))
    if set(tissues) == set(TISSUES):
        stages.append((DECKS,))
        if options.simulate != "none":
            stages.append((SIMULATE,))
    stages.append((REPORT,))
    if options.bundle:
        stages.append((BUNDLE,))
    return stages


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
    if step == SIMULATE:
        return run_simulation(out_dir, options)
    if step == REPORT:
        opts = JobOptions.from_dict(options)
        entries = {t: read_step(out_dir, t)["result"] for t in opts.tissues()}
        planned = sum(plan(opts), ())
        conformed = read_step(out_dir, CONFORM)["result"] if CONFORM in planned else None
        segmentation, anatomy, fe, simulation = (read_step(out_dir, s)["result"] if s in planned else None
                                                 for s in (SEGMENT, ANATOMY, DECKS, SIMULATE))
        overlaps = knee_overlaps(Path(out_dir) / MESHES_DIR) if any(t in CARTILAGES for t in entries) else None
        return write_report(out_dir, entries, conformed, anatomy, fe, simulation, overlaps, segmentation)["summary"]
    if step == BUNDLE:
        return {"artifacts": len(bundle(out_dir))}
    raise KneeMeshError("bad_option", f"unknown step {step!r}.")


def _longest_first(steps: Iterable[str]) -> list[str]:
    """Schedule the long steps first so the pool finishes together (an OAI knee's seconds:
    femoral cartilage 4-12, femur 1.3, each plate and the patellar cartilage about 1, tibia 0.8,
    patella 0.3; blending the femoral cartilage 1.1, each other 0.3)."""
    cost = {hex_step("femoral_cartilage"): 0, "femur": 1, "femoral_cartilage": 2, "tibia": 8, "patella": 9}
    return sorted(steps, key=lambda t: cost.get(t, 5))

"""The one definition of a KneeMesh job, shared by the CLI (in-process) and the workers.

A job is a :func:`plan`: stages run in order, and the steps of one stage are
independent of each other, so a runner may run them in parallel:

1. ``ingest`` reads the input, decides the label convention and the side, and
   writes canonical labels ``labels.nrrd`` and ``job.json``; for an image
   (``input_type="image"``) it checks the image and ``segment`` then writes the
   labels with the ONNX network (:mod:`kneemesh_core.segmentation`);
2. one step per bone, then one per cartilage (later stages such as blending
   need the bone surfaces); each writes that tissue's mesh and returns its
   report entry (a failure is an entry with ``status: "failed"`` and a reason,
   never an exception);
3. ``conform`` (with blending, when bones and cartilage are both meshed) lets
   each bone surface give way where a fused cartilage still dips into it
   (:mod:`kneemesh_core.hexmesh.conform`), rewriting that bone's files;
4. ``report`` gathers the entries into ``report.json``;
5. ``bundle`` (optional) zips the outputs into ``bundle.zip`` and lists every
   artifact with its size and SHA-256 in ``artifacts.json``.

:func:`run_step` runs one step and records it in ``steps/<step>.json``
(running, done or failed, with times), which is what status pages read. It is
idempotent: a step already done returns its record, so a queue may deliver a
step twice. Every argument is a path, a name or a plain dict, so a queue can
carry it. :func:`run` is the in-process runner; the Celery canvas in
``services.worker`` is the other one, built from the same plan.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import hashlib
import json
import os
import shutil
import tempfile
import time
import traceback
import zipfile
from concurrent.futures import Executor, ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Callable, Iterable

import pyvista as pv

from kneemesh_core import __version__
from kneemesh_core.errors import KneeMeshError
from kneemesh_core.io import read_label_map, read_volume, write_image
from kneemesh_core.knee import canonicalise, describe, describe_image
from kneemesh_core.hexmesh import BlendOptions, HexOptions, blend_cartilage, mesh_cartilage
from kneemesh_core.hexmesh.conform import conform_bone
from kneemesh_core.surfaces.tissue import SurfaceOptions, reconstruct
from kneemesh_core.tissues import BONE_OF, BONES, CARTILAGES, TISSUES, resolve_convention

LABELS_FILE = "labels.nrrd"
JOB_FILE = "job.json"
REPORT_FILE = "report.json"
BUNDLE_FILE = "bundle.zip"
MANIFEST_FILE = "artifacts.json"
STEPS_DIR = "steps"
INGEST, SEGMENT, CONFORM, REPORT, BUNDLE = "ingest", "segment", "conform", "report", "bundle"
INPUT_TYPES = ("labels", "image")
GROUPS = {"bones": BONES, "cartilage": CARTILAGES, "all": TISSUES}
# What the bundle carries: labels used, meshes, surfaces, the report (later: attachments, decks).
BUNDLED = (LABELS_FILE, JOB_FILE, REPORT_FILE, "meshes/*", "surfaces/*")

Progress = Callable[[str, str], None]


class JobCancelled(Exception):
    """Raised by :func:`run` between stages when its ``cancelled`` callback says so."""


@dataclasses.dataclass(frozen=True)
class JobOptions:
    """What the user can set for one job."""

    input_type: str = "labels"  # or "image": a DESS volume, segmented first
    model: str | None = None  # segmentation model (default: the shipped one)
    preset: str | None = None
    labels: str | None = None
    side: str | None = None
    only: str = "all"
    stl: bool = False
    bundle: bool = False
    surface: SurfaceOptions = SurfaceOptions()
    hex: HexOptions = HexOptions()
    blend: BlendOptions | None = BlendOptions()  # None: keep the step at the cartilage edge

    def tissues(self) -> tuple[str, ...]:
        if self.only not in GROUPS:
            raise KneeMeshError("bad_option", f"--only {self.only!r}: expected one of {', '.join(GROUPS)}.")
        return GROUPS[self.only]

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "JobOptions":
        d = dict(d)
        d["surface"] = SurfaceOptions(**d.get("surface", {}))
        d["hex"] = HexOptions(**d.get("hex", {}))
        if "blend" in d:
            d["blend"] = None if d["blend"] is None else BlendOptions(**d["blend"])
        return cls(**d)


def _atomic_write_text(path: Path, text: str) -> None:
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", dir=path.parent)
    with os.fdopen(fd, "w") as fh:
        fh.write(text)
    os.replace(tmp, path)


def _atomic_save_mesh(mesh: pv.DataSet, path: Path) -> None:
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        mesh.save(tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def ingest(input_path: str | os.PathLike, out_dir: str | os.PathLike, options: JobOptions) -> dict:
    """Stage 1: validate the input and write canonical labels and ``job.json``.

    Nothing is written unless the input is valid.
    """
    options.tissues()
    if options.input_type not in INPUT_TYPES:
        raise KneeMeshError("bad_option", f"input type {options.input_type!r}: expected one of {', '.join(INPUT_TYPES)}.")
    knee = None
    if options.input_type == "image":  # checked here, segmented by the segment step
        from kneemesh_core.segmentation.infer import SegmentationModel

        vol = read_volume(input_path)
        SegmentationModel.load(options.model)  # a missing or foreign model fails here, before anything is queued
        description = describe_image(vol.image, vol.source)
    else:
        knee = canonicalise(read_label_map(input_path), resolve_convention(options.preset, options.labels), options.side)
        description = describe(knee)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if knee is not None:
        write_image(knee.labels, out / LABELS_FILE)
    job = {"kneemesh_version": __version__, "input": description, "options": options.to_dict()}
    _atomic_write_text(out / JOB_FILE, json.dumps(job, indent=2))
    return job


def segment_input(input_path: str | os.PathLike, out_dir: str | os.PathLike, options: JobOptions) -> dict:
    """Stage 1b (image inputs): segment the image into canonical labels ``labels.nrrd``; ``job.json``
    gains the knee's description and the segmentation's facts."""
    from kneemesh_core.segmentation.infer import SegmentationModel, segment

    out = Path(out_dir)
    model = SegmentationModel.load(options.model)
    result = segment(read_volume(input_path), model, side=options.side)
    write_image(result.knee.labels, out / LABELS_FILE)
    job = json.loads((out / JOB_FILE).read_text())
    facts = {"model": model.path.name, "model_version": model.meta.get("version"), "seconds": result.seconds,
             "image": job["input"]}
    job["input"] = {**describe(result.knee), "preset": "segmented", "segmentation": facts}
    _atomic_write_text(out / JOB_FILE, json.dumps(job, indent=2))
    return {"status": "ok", "side": result.knee.side, "seconds": result.seconds["total"],
            "tissues_ml": job["input"]["tissues"]}


def mesh_tissue(out_dir: str | os.PathLike, tissue: str, options: dict) -> dict:
    """Stage 2: mesh one tissue of an ingested job; returns its report entry, never raises."""
    t0 = time.perf_counter()
    opts = JobOptions.from_dict(options)
    out = Path(out_dir)
    try:
        labels = read_label_map(out / LABELS_FILE).image
        folder = out / "meshes"
        folder.mkdir(exist_ok=True)
        if tissue in BONES:
            mesh, facts = reconstruct(labels, tissue, opts.surface)
            files = [folder / f"{tissue}.vtp"]
            _atomic_save_mesh(mesh, files[0])
            if opts.stl:
                files.append(folder / f"{tissue}.stl")
                _atomic_save_mesh(mesh, files[-1])
            entry = {"status": "ok", **facts}
        else:
            cm = mesh_cartilage(labels, tissue, opts.hex)
            ok = cm.facts["gate_passed"]
            if ok and opts.blend is not None:  # the bone stage ran first: fuse onto the bone mesh it wrote
                bone_file = folder / f"{BONE_OF[tissue]}.vtp"
                cm = blend_cartilage(cm, pv.read(bone_file) if bone_file.exists() else None, opts.blend)
            facts = cm.facts
            (out / "surfaces").mkdir(exist_ok=True)
            files = [folder / f"{tissue}{'' if ok else '.rejected'}.vtu", out / "surfaces" / f"{tissue}.vtp"]
            _atomic_save_mesh(cm.grid(), files[0])
            _atomic_save_mesh(cm.surface, files[1])
            entry = {"status": "ok" if ok else "failed", **facts}
            if not ok:
                entry["code"] = "quality_gate"
                entry["reason"] = (f"quality gate not met after {len(facts['attempts'])} attempts: min scaled Jacobian "
                                   f"{facts['min_scaled_jacobian']}, {facts['inverted']} inverted, "
                                   f"{facts['frac_edge_ratio_above_6']:.4%} with edge ratio > 6, "
                                   f"{facts['self_intersections']} boundary edges crossing; best mesh kept as {files[0].name}")
        entry["files"] = [str(f.relative_to(out)) for f in files]
    except KneeMeshError as exc:
        entry = {"status": "failed", "reason": exc.message, "code": exc.code}
    except Exception as exc:  # a failed tissue never sinks the rest of the knee
        entry = {"status": "failed", "reason": f"{type(exc).__name__}: {exc}", "code": "internal",
                 "traceback": traceback.format_exc(limit=5)}
    entry["seconds"] = round(time.perf_counter() - t0, 3)
    return entry


def conform_bones(out_dir: str | os.PathLike, options: dict) -> dict:
    """Stage 3: each bone surface gives way where the accepted meshes of its cartilages still lie
    inside it (:func:`.hexmesh.conform.conform_bone`); the bone's files are rewritten (atomically)
    only where it changed.  Returns what was done per bone.  Idempotent: a second run finds no
    cartilage inside and changes nothing."""
    opts = JobOptions.from_dict(options)
    folder = Path(out_dir) / "meshes"
    done = {}
    for bone in BONES:
        files = [folder / f"{bone}.vtp"] + ([folder / f"{bone}.stl"] if opts.stl else [])
        grids = {t: pv.read(folder / f"{t}.vtu") for t in CARTILAGES
                 if BONE_OF[t] == bone and (folder / f"{t}.vtu").exists()}
        if not files[0].exists() or not grids:
            continue
        try:
            surface, facts = conform_bone(pv.read(files[0]), grids)
        except Exception as exc:  # the bone stays as meshed; the knee goes on
            done[bone] = {"applied": False, "reason": f"{type(exc).__name__}: {exc}", "cartilages": {}}
            continue
        if facts["applied"]:
            for f in files:
                _atomic_save_mesh(surface, f)
        done[bone] = facts
    return done


def write_report(out_dir: str | os.PathLike, entries: dict[str, dict], conformed: dict | None = None) -> dict:
    """Stage 4: ``report.json`` from ``job.json``, the tissue entries and what :func:`conform_bones`
    did (each bone's entry gains ``conformed``, each of its cartilages' ``bone_conform``)."""
    out = Path(out_dir)
    job = json.loads((out / JOB_FILE).read_text())
    entries = {t: dict(e) for t, e in entries.items()}
    for bone, facts in (conformed or {}).items():
        per = facts["cartilages"]
        if bone in entries:
            entries[bone]["conformed"] = {k: v for k, v in facts.items() if k != "cartilages"}
        for t, f in per.items():
            if t in entries:
                entries[t]["bone_conform"] = f
    report = {
        **job,
        "tissues": {t: entries[t] for t in TISSUES if t in entries},
        "summary": {
            "ok": sorted(t for t, e in entries.items() if e["status"] == "ok"),
            "failed": sorted(t for t, e in entries.items() if e["status"] != "ok"),
        },
    }
    _atomic_write_text(out / REPORT_FILE, json.dumps(report, indent=2))
    return report


def plan(options: JobOptions) -> list[tuple[str, ...]]:
    """The stages of a job, in order; the steps of one stage may run in parallel."""
    tissues = options.tissues()
    stages: list[tuple[str, ...]] = [(INGEST,)] + ([(SEGMENT,)] if options.input_type == "image" else [])
    for group in (BONES, CARTILAGES):
        steps = tuple(_longest_first(t for t in tissues if t in group))
        if steps:
            stages.append(steps)
    if options.blend is not None and set(tissues) >= set(BONES) | set(CARTILAGES):
        stages.append((CONFORM,))
    stages.append((REPORT,))
    if options.bundle:
        stages.append((BUNDLE,))
    return stages


def _now() -> str:
    return dt.datetime.now(dt.timezone.utc).isoformat(timespec="milliseconds")


def read_step(out_dir: str | os.PathLike, step: str) -> dict | None:
    """The record of one step (``state``: running, done or failed), or None if it never started."""
    try:
        return json.loads((Path(out_dir) / STEPS_DIR / f"{step}.json").read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return None


def write_step(out_dir: str | os.PathLike, step: str, record: dict) -> None:
    folder = Path(out_dir) / STEPS_DIR
    folder.mkdir(exist_ok=True)
    _atomic_write_text(folder / f"{step}.json", json.dumps({"step": step, **record}, indent=1))


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
    started, t0 = _now(), time.perf_counter()
    if step == INGEST:
        if input_path is None:
            raise KneeMeshError("bad_option", "the ingest step needs the input file.")
        ingest(input_path, out_dir, JobOptions.from_dict(options))
        result: dict = {"status": "ok"}
    else:
        write_step(out_dir, step, {"state": "running", "started_at": started, **who})
        try:
            if step in TISSUES:
                result = mesh_tissue(out_dir, step, options)
            elif step == SEGMENT:
                if input_path is None:
                    raise KneeMeshError("bad_option", "the segment step needs the input image.")
                result = segment_input(input_path, out_dir, JobOptions.from_dict(options))
            elif step == CONFORM:
                result = conform_bones(out_dir, options)
            elif step == REPORT:
                opts = JobOptions.from_dict(options)
                entries = {t: read_step(out_dir, t)["result"] for t in opts.tissues()}
                conformed = read_step(out_dir, CONFORM) if CONFORM in sum(plan(opts), ()) else None
                result = write_report(out_dir, entries, conformed and conformed["result"])["summary"]
            elif step == BUNDLE:
                result = {"artifacts": len(bundle(out_dir))}
            else:
                raise KneeMeshError("bad_option", f"unknown step {step!r}.")
        except Exception as exc:
            code, reason = (exc.code, exc.message) if isinstance(exc, KneeMeshError) else ("internal", f"{type(exc).__name__}: {exc}")
            write_step(out_dir, step, {"state": "failed", "started_at": started, "finished_at": _now(),
                                       "seconds": round(time.perf_counter() - t0, 3), "code": code, "reason": reason, **who})
            raise
    record = {"state": "done", "started_at": started, "finished_at": _now(),
              "seconds": round(time.perf_counter() - t0, 3), "result": result, **who}
    write_step(out_dir, step, record)
    return {"step": step, **record}


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def bundle(out_dir: str | os.PathLike) -> list[dict]:
    """Zip the job's outputs into ``bundle.zip`` and list every artifact in ``artifacts.json``.

    Returns the list: ``name`` (path relative to ``out_dir``, '/'-separated), ``size`` (bytes)
    and ``sha256``, the bundle last.
    """
    out = Path(out_dir)
    files = sorted({f for pattern in BUNDLED for f in out.glob(pattern) if f.is_file() and not f.name.startswith(".tmp-")})
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=".zip", dir=out)
    os.close(fd)
    try:
        # Level 1: meshes are binary and barely compress further; speed matters more.
        with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
            for f in files:
                zf.write(f, f.relative_to(out).as_posix())
        os.replace(tmp, out / BUNDLE_FILE)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    manifest = [{"name": f.relative_to(out).as_posix(), "size": f.stat().st_size, "sha256": _sha256(f)}
                for f in [*files, out / BUNDLE_FILE]]
    _atomic_write_text(out / MANIFEST_FILE, json.dumps(manifest, indent=1))
    return manifest


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
    """Run the whole :func:`plan` in this process and return the report.

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
    return json.loads((Path(out_dir) / REPORT_FILE).read_text())


def _outcome(record: dict) -> str:
    """What a progress line shows for a finished step: a tissue's status, else 'done'."""
    return record.get("result", {}).get("status", "done") if isinstance(record.get("result"), dict) else "done"


def _longest_first(tissues: Iterable[str]) -> list[str]:
    """Schedule the big tissues first so the pool finishes together."""
    cost = {"femur": 0, "tibia": 1, "femoral_cartilage": 2, "patella": 3}
    return sorted(tissues, key=lambda t: cost.get(t, 9))

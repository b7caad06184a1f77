"""The one definition of a KneeMesh job, shared by the CLI (in-process) and the workers.

A job is three stages over a job folder:

1. :func:`ingest` reads the input, decides the label convention and the side,
   and writes canonical labels ``labels.nrrd`` and ``job.json``;
2. :func:`mesh_tissue`, once per tissue and independent of the others, writes
   that tissue's mesh and returns its report entry (a failure is an entry with
   ``status: "failed"`` and a reason, never an exception);
3. :func:`write_report` gathers the entries into ``report.json``.

Every argument is a path, a name or a plain dict, so a queue can carry it.
"""

from __future__ import annotations

import dataclasses
import json
import os
import tempfile
import time
import traceback
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Callable, Iterable

import pyvista as pv

from kneemesh_core import __version__
from kneemesh_core.errors import KneeMeshError
from kneemesh_core.io import read_label_map, write_image
from kneemesh_core.knee import canonicalise, describe
from kneemesh_core.hexmesh import HexOptions, mesh_cartilage
from kneemesh_core.surfaces.tissue import SurfaceOptions, reconstruct
from kneemesh_core.tissues import BONES, CARTILAGES, TISSUES, resolve_convention

LABELS_FILE = "labels.nrrd"
JOB_FILE = "job.json"
REPORT_FILE = "report.json"
GROUPS = {"bones": BONES, "cartilage": CARTILAGES, "all": TISSUES}

Progress = Callable[[str, str], None]


@dataclasses.dataclass(frozen=True)
class JobOptions:
    """What the user can set for one job."""

    preset: str | None = None
    labels: str | None = None
    side: str | None = None
    only: str = "all"
    stl: bool = False
    surface: SurfaceOptions = SurfaceOptions()
    hex: HexOptions = HexOptions()

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
    vol = read_label_map(input_path)
    knee = canonicalise(vol, resolve_convention(options.preset, options.labels), options.side)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_image(knee.labels, out / LABELS_FILE)
    job = {"kneemesh_version": __version__, "input": describe(knee), "options": options.to_dict()}
    _atomic_write_text(out / JOB_FILE, json.dumps(job, indent=2))
    return job


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
            facts = cm.facts
            ok = facts["gate_passed"]
            (out / "surfaces").mkdir(exist_ok=True)
            files = [folder / f"{tissue}{'' if ok else '.rejected'}.vtu", out / "surfaces" / f"{tissue}.vtp"]
            _atomic_save_mesh(cm.grid(), files[0])
            _atomic_save_mesh(cm.surface, files[1])
            entry = {"status": "ok" if ok else "failed", **facts}
            if not ok:
                entry["code"] = "quality_gate"
                entry["reason"] = (f"quality gate not met after {len(facts['attempts'])} attempts: min scaled Jacobian "
                                   f"{facts['min_scaled_jacobian']}, {facts['inverted']} inverted, "
                                   f"{facts['frac_edge_ratio_above_6']:.4%} with edge ratio > 6; best mesh kept as {files[0].name}")
        entry["files"] = [str(f.relative_to(out)) for f in files]
    except KneeMeshError as exc:
        entry = {"status": "failed", "reason": exc.message, "code": exc.code}
    except Exception as exc:  # a failed tissue never sinks the rest of the knee
        entry = {"status": "failed", "reason": f"{type(exc).__name__}: {exc}", "code": "internal",
                 "traceback": traceback.format_exc(limit=5)}
    entry["seconds"] = round(time.perf_counter() - t0, 3)
    return entry


def write_report(out_dir: str | os.PathLike, entries: dict[str, dict]) -> dict:
    """Stage 3: ``report.json`` from ``job.json`` and the tissue entries."""
    out = Path(out_dir)
    job = json.loads((out / JOB_FILE).read_text())
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


def run(
    input_path: str | os.PathLike,
    out_dir: str | os.PathLike,
    options: JobOptions = JobOptions(),
    *,
    workers: int = 2,
    progress: Progress | None = None,
) -> dict:
    """The whole job in this process (tissues on a pool of ``workers`` processes)."""
    say = progress or (lambda stage, state: None)
    say("ingest", "running")
    ingest(input_path, out_dir, options)
    say("ingest", "done")
    tissues = options.tissues()
    entries: dict[str, dict] = {}
    opts = options.to_dict()
    if workers <= 1:
        for t in tissues:
            say(t, "running")
            entries[t] = mesh_tissue(out_dir, t, opts)
            say(t, entries[t]["status"])
    else:
        with ProcessPoolExecutor(max_workers=workers) as pool:
            futures = {pool.submit(mesh_tissue, str(out_dir), t, opts): t for t in _longest_first(tissues)}
            for t in tissues:
                say(t, "queued")
            for fut in as_completed(futures):
                t = futures[fut]
                entries[t] = fut.result()
                say(t, entries[t]["status"])
    return write_report(out_dir, entries)


def _longest_first(tissues: Iterable[str]) -> list[str]:
    """Schedule the big tissues first so the pool finishes together."""
    cost = {"femur": 0, "tibia": 1, "femoral_cartilage": 2, "patella": 3}
    return sorted(tissues, key=lambda t: cost.get(t, 9))

"""The job folder: its file names, the step records, the unblended meshes kept between steps, and the bundle.

Every file here is written atomically (:mod:`kneemesh_core.io.files`): a status page or a
client reading the folder mid-job sees each file whole or not at all.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import os
import zipfile
from pathlib import Path

import numpy as np
import pyvista as pv

from kneemesh_core.io.files import TMP_PREFIX, atomic_path, atomic_write_json

LABELS_FILE = "labels.nrrd"
JOB_FILE = "job.json"
REPORT_FILE = "report.json"
ATTACHMENTS_FILE = "attachments.json"
ATTACHMENTS_FIGURE = "attachments.png"
BUNDLE_FILE = "bundle.zip"
MANIFEST_FILE = "artifacts.json"
STEPS_DIR = "steps"
MESHES_DIR = "meshes"
SURFACES_DIR = "surfaces"
#: What one step leaves for a later one and nobody else reads: a cartilage's unblended mesh
WORK_DIR = "work"
#: What the bundle carries: labels used, meshes, surfaces, attachment sites and frames, the decks and
#: any simulation's results, contact pressure maps and ccx's result file (.frd; not its .dat log), the report.
BUNDLED = (LABELS_FILE, JOB_FILE, REPORT_FILE, ATTACHMENTS_FILE, ATTACHMENTS_FIGURE, f"{MESHES_DIR}/*", f"{SURFACES_DIR}/*",
           *(f"fe/{sub}*.{ext}" for sub in ("", "smoke/") for ext in ("inp", "json", "png", "vtu", "frd")))


def utc_now() -> str:
    """The time now, UTC, ISO 8601 to the millisecond (the stamps of step and job records)."""
    return dt.datetime.now(dt.timezone.utc).isoformat(timespec="milliseconds")


def save_mesh(mesh: pv.DataSet, path: Path) -> None:
    """Write a mesh atomically; the format follows the suffix (.vtp, .vtu, .stl)."""
    with atomic_path(path) as tmp:
        mesh.save(tmp)


def save_unblended(cm, path: Path) -> None:
    """Keep a meshed cartilage before its blend (:class:`kneemesh_core.hexmesh.CartilageMesh`
    without its surface, which the step writes to ``surfaces/``) for the step that blends it:
    its mesh and quality arrays and its report entry, in one ``.npz``."""
    arrays = {f"mesh.{k}": v for k, v in vars(cm.mesh).items()}
    arrays.update({f"quality.{k}": v for k, v in cm.quality.items()})
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, facts=np.array(json.dumps(cm.facts)), **arrays)


def load_unblended(path: Path, surface: pv.PolyData):
    """The :class:`kneemesh_core.hexmesh.CartilageMesh` that :func:`save_unblended` kept, bit for bit,
    with its ``surface``."""
    from kneemesh_core.hexmesh import CartilageMesh
    from kneemesh_core.hexmesh.extrude import HexMesh

    with np.load(path) as z:
        part = {prefix: {k.split(".", 1)[1]: z[k] for k in z.files if k.startswith(prefix + ".")}
                for prefix in ("mesh", "quality")}
        return CartilageMesh(HexMesh(**part["mesh"]), part["quality"], json.loads(str(z["facts"])), surface)


def read_json(path: Path) -> dict:
    return json.loads(Path(path).read_text())


def write_json(path: Path, data: dict) -> None:
    atomic_write_json(path, data, indent=2)


def read_step(out_dir: str | os.PathLike, step: str) -> dict | None:
    """The record of one step (``state``: running, done or failed), or None if it never started."""
    try:
        return read_json(Path(out_dir) / STEPS_DIR / f"{step}.json")
    except (FileNotFoundError, json.JSONDecodeError):
        return None


def write_step(out_dir: str | os.PathLike, step: str, record: dict) -> None:
    folder = Path(out_dir) / STEPS_DIR
    folder.mkdir(exist_ok=True)
    atomic_write_json(folder / f"{step}.json", {"step": step, **record})


def sha256(path: Path) -> str:
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
    files = sorted({f for pattern in BUNDLED for f in out.glob(pattern) if f.is_file() and not f.name.startswith(TMP_PREFIX)})
    with atomic_path(out / BUNDLE_FILE) as tmp:
        # Level 1: meshes are binary and barely compress further; speed matters more.
        with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
            for f in files:
                zf.write(f, f.relative_to(out).as_posix())
    manifest = [{"name": f.relative_to(out).as_posix(), "size": f.stat().st_size, "sha256": sha256(f)}
                for f in [*files, out / BUNDLE_FILE]]
    atomic_write_json(out / MANIFEST_FILE, manifest)
    return manifest

"""Finding the knees of a cohort: an OAI-style tree of DICOM folders, a folder of volumes, or a CSV
manifest.  Each knee gets an id that mirrors where it sits in the cohort (its relative path), so
results land in a tree shaped like the cohort's."""

from __future__ import annotations

import csv
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from kneemesh_core.errors import KneeMeshError
from kneemesh_core.io import dicom
from kneemesh_core.io.volumes import IMAGE_SUFFIXES, volume_suffix

#: A volume with an integer type and at most this many distinct values is a label map.
MAX_LABELS = 32
#: OAI visits as written in names: 00m, 12m (months), M12 (after a subject id too: 9003406M12), V01.
_VISIT = re.compile(r"(?:^|[_/\-])(\d{2,3})m(?=$|[_/\-.])|(?:^|[_/\-]|(?<=\d))M(\d{2})(?=$|[_/\-.])"
                    r"|(?:^|[_/\-])(V\d{2})(?=$|[_/\-.])", re.IGNORECASE)
_SIDE = re.compile(r"(?:^|[_/\-\s])(LEFT|RIGHT|L|R)(?:$|[_/\-\s.])", re.IGNORECASE)


@dataclass(frozen=True)
class Knee:
    """One knee to submit: ``id`` is its relative path in the cohort (posix, no suffix)."""

    id: str
    path: Path  # a volume, or the folder of a DICOM series
    input_type: str  # "labels" or "image"
    side: str | None = None
    visit: str | None = None
    files: tuple[Path, ...] = field(default=(), compare=False)  # a DICOM series' files, uploaded as a zip


def _stem(path: Path) -> str:
    """A volume's path without its volume suffix (``.nii.gz`` whole), posix."""
    return path.as_posix()[: -len(volume_suffix(path))]


def visit_of(text: str) -> str | None:
    """The visit a name carries, as months ('00m', '12m') or an OAI visit code ('V01'), else None."""
    m = _VISIT.search(text)
    if not m:
        return None
    months = m.group(1) or m.group(2)
    return f"{int(months):02d}m" if months else m.group(3).upper()


def side_of(text: str) -> str | None:
    """'left' or 'right' from a name or series description such as SAG_3D_DESS_RIGHT, else None."""
    hits = {m.group(1).upper()[0] for m in _SIDE.finditer(text)}
    return {"L": "left", "R": "right"}[hits.pop()] if len(hits) == 1 else None


def input_type_of(path: Path) -> str:
    """'labels' for an integer volume with few distinct values, else 'image'; a file that cannot be
    read is sent as labels, and the server's refusal says what is wrong with it."""
    try:
        img = sitk.ReadImage(str(path))
    except RuntimeError:
        return "labels"
    if "float" in img.GetPixelIDTypeAsString():
        return "image"
    return "labels" if len(np.unique(sitk.GetArrayViewFromImage(img))) <= MAX_LABELS else "image"


def _files(root: Path) -> list[Path]:
    """Every file under ``root``, following linked folders (cohorts are often trees of links), each
    real folder once."""
    seen, out = set(), []
    for folder, dirs, names in os.walk(root, followlinks=True):
        real = os.path.realpath(folder)
        if real in seen:
            dirs[:] = []
            continue
        seen.add(real)
        dirs.sort()
        out += [Path(folder) / n for n in sorted(names)]
    return out


def _dicom_knees(root: Path) -> list[Knee]:
    """One knee per folder that holds DICOM files: its sagittal 3D DESS series (by the headers)."""
    knees = []
    folders = sorted({p.parent for p in _files(root) if dicom.looks_like_dicom(p)})
    for folder in folders:
        dess = [s for s in dicom.series_in(folder) if dicom.is_sagittal_3d_dess(s[2])]
        if not dess:
            continue
        _, files, meta = max(dess, key=lambda s: len(s[1]))  # a localiser repeat is shorter
        rel = folder.relative_to(root).as_posix() or folder.name
        text = f"{rel} {meta.get('series_description', '')}"
        side = {"L": "left", "R": "right"}.get(meta.get("laterality", "")[:1].upper()) or side_of(text)
        knees.append(Knee(rel, folder, "image", side, visit_of(rel), tuple(Path(f) for f in files)))
    return knees


def from_manifest(csv_path: Path) -> list[Knee]:
    """A CSV with columns id, path (relative to the CSV or absolute), and optionally side
    (left/right), input_type (labels/image) and visit."""
    rows = list(csv.DictReader(csv_path.read_text().splitlines()))
    if not rows or not {"id", "path"} <= set(rows[0]):
        raise KneeMeshError("bad_manifest", f"{csv_path}: expected a CSV with a header row holding at least "
                                            "'id' and 'path' (and optionally side, input_type, visit).")
    knees, seen = [], set()
    for n, row in enumerate(rows, start=2):
        kid, path = row["id"].strip(), Path(row["path"].strip())
        path = path if path.is_absolute() else csv_path.parent / path
        side = (row.get("side") or "").strip().lower() or None
        kind = (row.get("input_type") or "").strip().lower() or None
        problems = [f"id {kid!r} repeats" if kid in seen else None, None if path.exists() else f"{path} does not exist",
                    None if side in (None, "left", "right") else f"side {side!r} is not left or right",
                    None if kind in (None, "labels", "image") else f"input_type {kind!r} is not labels or image",
                    None if kid and not kid.startswith("/") and ".." not in kid.split("/") else f"id {kid!r} is not a relative name"]
        problems = [p for p in problems if p]
        if problems:
            raise KneeMeshError("bad_manifest", f"{csv_path} line {n}: {'; '.join(problems)}.")
        seen.add(kid)
        if path.is_dir():
            found = _dicom_knees(path)
            if len(found) != 1:
                raise KneeMeshError("bad_manifest", f"{csv_path} line {n}: {path} holds {len(found)} sagittal 3D DESS "
                                                    "series; expected one.")
            knees.append(Knee(kid, path, "image", side or found[0].side, row.get("visit") or found[0].visit, found[0].files))
        else:
            knees.append(Knee(kid, path, kind or input_type_of(path), side or side_of(path.name),
                              (row.get("visit") or "").strip() or visit_of(kid)))
    return knees


def find_knees(cohort: Path, input_type: str | None = None) -> list[Knee]:
    """The knees of ``cohort``: a CSV manifest, or a folder searched for volumes and DICOM series.
    ``input_type`` forces labels or image for volumes (default: judged from each volume)."""
    cohort = Path(cohort)
    if cohort.is_file() and cohort.suffix.lower() == ".csv":
        return from_manifest(cohort)
    if not cohort.is_dir():
        raise KneeMeshError("not_found", f"{cohort}: expected a cohort folder (DICOM series or NIfTI/NRRD/MHA volumes) "
                                         "or a CSV manifest with columns id, path[, side, input_type, visit].")
    volumes = [p for p in _files(cohort) if volume_suffix(p) in IMAGE_SUFFIXES]
    knees = [Knee(_stem(p.relative_to(cohort)), p, input_type or input_type_of(p), side_of(_stem(Path(p.name))),
                  visit_of(p.relative_to(cohort).as_posix())) for p in volumes]
    knees += _dicom_knees(cohort)
    if not knees:
        raise KneeMeshError("no_knees", f"{cohort}: no volumes ({', '.join(IMAGE_SUFFIXES)}) and no sagittal 3D DESS "
                                        "DICOM series were found.")
    return sorted(knees, key=lambda k: k.id)

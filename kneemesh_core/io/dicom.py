"""DICOM series: pick the 3D DESS series and keep the header facts we need."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from kneemesh_core.errors import KneeMeshError

_TAGS = {
    "series_description": "0008|103e",
    "laterality": "0020|0060",
    "image_laterality": "0020|0062",
    "modality": "0008|0060",
    "body_part": "0018|0015",
    "protocol_name": "0018|1030",
    "acquisition_type": "0018|0023",
    "orientation": "0020|0037",
}


def looks_like_dicom(path: Path) -> bool:
    """True if the file carries the DICM preamble magic or a DICOM suffix."""
    if path.suffix.lower() in (".dcm", ".ima"):
        return True
    try:
        with open(path, "rb") as fh:
            fh.seek(128)
            return fh.read(4) == b"DICM"
    except OSError:
        return False


def meta_from_reader(reader) -> dict:
    """Header facts from a SimpleITK reader that has read a DICOM file's information."""
    meta = {}
    for key, tag in _TAGS.items():
        if reader.HasMetaDataKey(tag):
            meta[key] = reader.GetMetaData(tag).strip()
    return meta


def series_meta(first_file: str) -> dict:
    r = sitk.ImageFileReader()
    r.SetFileName(first_file)
    r.LoadPrivateTagsOn()
    try:
        r.ReadImageInformation()
    except RuntimeError:
        return {}
    return meta_from_reader(r)


def _is_dess(meta: dict) -> bool:
    text = " ".join([meta.get("series_description", ""), meta.get("protocol_name", "")]).upper()
    return bool(re.search(r"DESS", text))


def is_sagittal_3d_dess(meta: dict) -> bool:
    """A DESS series acquired in 3D with sagittal slices (the slice normal, row x column direction,
    within 35 deg of the patient's left-right axis); a header that omits a fact does not rule it out."""
    if not _is_dess(meta) or meta.get("acquisition_type", "3D").upper() not in ("3D", ""):
        return False
    try:
        row_col = [float(v) for v in meta.get("orientation", "").split("\\")]
    except ValueError:
        return True
    if len(row_col) != 6:
        return True
    normal = np.cross(row_col[:3], row_col[3:])
    return bool(abs(normal[0]) >= np.cos(np.radians(35.0)) * np.linalg.norm(normal))


def series_in(folder: Path) -> list[tuple[str, list[str], dict]]:
    """The DICOM series directly in ``folder``: (series id, its files in order, header facts)."""
    out = []
    for sid in sitk.ImageSeriesReader.GetGDCMSeriesIDs(str(folder)) or ():
        files = list(sitk.ImageSeriesReader.GetGDCMSeriesFileNames(str(folder), sid))
        if files:
            out.append((sid, files, series_meta(files[0])))
    return out


def read_series(folder: Path, label: str | None = None) -> tuple[sitk.Image, dict]:
    """Read one DICOM series from a folder tree.

    When the tree holds several series, the 3D DESS one is chosen; if that is
    not unique a :class:`KneeMeshError` (``dicom_ambiguous``) lists them all.
    """
    name = label or folder.name
    dirs = [folder] + sorted(p for p in folder.rglob("*") if p.is_dir())
    series = [s for d in dirs for s in series_in(d)]
    if not series:
        raise KneeMeshError(
            "not_an_image",
            f"{name}: no DICOM series found; expected a folder or .zip of DICOM files, or a NIfTI/NRRD/MHA volume.",
        )
    if len(series) > 1:
        dess = [s for s in series if _is_dess(s[2])]
        if len(dess) != 1:
            listing = "; ".join(
                f"{s[0][-12:]} '{s[2].get('series_description', '?')}' ({len(s[1])} files)" for s in series
            )
            raise KneeMeshError(
                "dicom_ambiguous",
                f"{name}: {len(series)} DICOM series and {'no' if not dess else 'several'} 3D DESS among them "
                f"({listing}); keep only the series to process.",
            )
        series = dess
    sid, files, meta = series[0]
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames(files)
    try:
        image = reader.Execute()
    except RuntimeError as exc:
        raise KneeMeshError("corrupt", f"{name}: the DICOM series could not be read ({exc}).") from exc
    meta["n_files"] = len(files)
    return image, meta

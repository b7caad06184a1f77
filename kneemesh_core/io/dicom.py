"""DICOM series: pick the 3D DESS series and keep the header facts we need."""

from __future__ import annotations

import re
from pathlib import Path

import SimpleITK as sitk

from kneemesh_core.errors import KneeMeshError

_TAGS = {
    "series_description": "0008|103e",
    "laterality": "0020|0060",
    "image_laterality": "0020|0062",
    "modality": "0008|0060",
    "body_part": "0018|0015",
    "protocol_name": "0018|1030",
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


def _series_meta(first_file: str) -> dict:
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


def read_series(folder: Path, label: str | None = None) -> tuple[sitk.Image, dict]:
    """Read one DICOM series from a folder tree.

    When the tree holds several series, the 3D DESS one is chosen; if that is
    not unique a :class:`KneeMeshError` (``dicom_ambiguous``) lists them all.
    """
    name = label or folder.name
    series: list[tuple[str, list[str], dict]] = []
    dirs = [folder] + sorted(p for p in folder.rglob("*") if p.is_dir())
    for d in dirs:
        for sid in sitk.ImageSeriesReader.GetGDCMSeriesIDs(str(d)) or ():
            files = list(sitk.ImageSeriesReader.GetGDCMSeriesFileNames(str(d), sid))
            if files:
                series.append((sid, files, _series_meta(files[0])))
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

"""Volume I/O: NIfTI, NRRD, MHA/MHD and DICOM series (folder or .zip), in LPS mm.

SimpleITK is the reader and writer throughout: it keeps spacing, origin and
direction in double precision in memory.  Internally the pipeline hands images
on as NRRD, whose header stores the geometry as decimal text without the
float32 rounding of a NIfTI qform/sform.
"""

from __future__ import annotations

import gzip
import os
import struct
import tempfile
import zlib
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from kneemesh_core.errors import KneeMeshError
from kneemesh_core.io import dicom
from kneemesh_core.io.files import atomic_path

#: Largest volume accepted, in voxels (about 2 GB as float32).
MAX_VOXELS = 512 * 1024 * 1024
#: Plausible voxel spacing range for knee MRI, mm.
SPACING_RANGE_MM = (0.05, 10.0)

#: The volume formats read (a DICOM series is a folder or a .zip).
IMAGE_SUFFIXES = (".nii.gz", ".nii", ".nrrd", ".nhdr", ".mha", ".mhd")


@dataclass
class Volume:
    """A 3-D image with its geometry and the metadata the pipeline needs.

    Attributes
    ----------
    image : SimpleITK.Image
        3-D scalar image; ``image.GetSpacing()`` in mm, origin in LPS mm,
        direction cosines as columns of the index-to-LPS rotation.
    source : str
        The path it was read from.
    meta : dict
        Header facts that help later steps: ``series_description``,
        ``laterality`` (from DICOM tags), ``modality``.
    """

    image: sitk.Image
    source: str
    meta: dict = field(default_factory=dict)


def volume_suffix(path: Path) -> str:
    """The file's volume suffix in lower case (``.nii.gz`` whole), else its last suffix."""
    name = path.name.lower()
    for s in IMAGE_SUFFIXES:
        if name.endswith(s):
            return s
    return path.suffix.lower()


def read_volume(path: str | os.PathLike, *, max_voxels: int = MAX_VOXELS) -> Volume:
    """Read a 3-D image from a file, a DICOM folder or a zip of a DICOM series.

    Parameters
    ----------
    path : path-like
        NIfTI (``.nii``/``.nii.gz``), NRRD, MHA/MHD, a folder holding one DICOM
        series (or several, one of them a 3D DESS), or a ``.zip`` of such a folder.
    max_voxels : int
        Reject larger volumes with a clear error.

    Returns
    -------
    Volume

    Raises
    ------
    KneeMeshError
        ``not_found``, ``not_an_image``, ``corrupt``, ``not_3d``, ``bad_spacing``,
        ``too_large``, ``dicom_ambiguous``.
    """
    p = Path(path)
    if not p.exists():
        raise KneeMeshError("not_found", f"{p}: no such file or folder.")
    if p.is_dir():
        image, meta = dicom.read_series(p)
    elif zipfile.is_zipfile(p):
        with tempfile.TemporaryDirectory(prefix="kneemesh-zip-") as tmp:
            _safe_extract(p, Path(tmp))
            image, meta = dicom.read_series(Path(tmp), label=p.name)
    else:
        image, meta = _read_file(p)
    _check_geometry(image, str(p), max_voxels)
    return Volume(image=image, source=str(p), meta=meta)


def _safe_extract(archive: Path, dest: Path) -> None:
    """Extract a zip, refusing members that would land outside ``dest``."""
    with zipfile.ZipFile(archive) as zf:
        for member in zf.infolist():
            target = (dest / member.filename).resolve()
            if not str(target).startswith(str(dest.resolve()) + os.sep):
                raise KneeMeshError("corrupt", f"{archive.name}: zip member {member.filename!r} escapes the archive.")
        try:
            zf.extractall(dest)
        except (zipfile.BadZipFile, OSError, EOFError) as exc:
            raise KneeMeshError("corrupt", f"{archive.name}: the zip archive is truncated or corrupt ({exc}).") from exc


def _read_file(p: Path) -> tuple[sitk.Image, dict]:
    if p.stat().st_size == 0:
        raise KneeMeshError("not_an_image", f"{p.name}: the file is empty; expected a NIfTI, NRRD, MHA or DICOM volume.")
    try:
        reader = sitk.ImageFileReader()
        reader.SetFileName(str(p))
        reader.ReadImageInformation()
    except RuntimeError as exc:
        raise KneeMeshError(
            "not_an_image",
            f"{p.name}: not a readable image; expected NIfTI (.nii/.nii.gz), NRRD, MHA/MHD, "
            "or a DICOM series as a folder or .zip.",
        ) from exc
    try:
        image = reader.Execute()
    except RuntimeError as exc:
        raise KneeMeshError(
            "corrupt", f"{p.name}: the header was read but the voxel data is truncated or corrupt."
        ) from exc
    if volume_suffix(p) in (".nii", ".nii.gz"):
        _check_nifti_complete(p)
    meta: dict = {}
    if dicom.looks_like_dicom(p):
        meta = dicom.meta_from_reader(reader)
    return image, meta


def _check_nifti_complete(p: Path) -> None:
    """Raise ``corrupt`` if a NIfTI file holds fewer voxel bytes than its header promises.

    ITK's NIfTI reader pads a truncated file silently, so the byte count is
    checked here from the header (NIfTI-1 and NIfTI-2, either endianness).
    """
    opener = gzip.open if p.name.lower().endswith(".gz") else open
    try:
        with opener(p, "rb") as fh:
            head = fh.read(540)
            for endian in "<>":
                size = struct.unpack(endian + "i", head[:4])[0]
                if size in (348, 540):
                    break
            else:
                return
            if size == 348:
                dims = struct.unpack(endian + "8h", head[40:56])
                bitpix = struct.unpack(endian + "h", head[72:74])[0]
                offset = int(struct.unpack(endian + "f", head[108:112])[0])
            else:
                bitpix = struct.unpack(endian + "h", head[14:16])[0]
                dims = struct.unpack(endian + "8q", head[16:80])
                offset = struct.unpack(endian + "q", head[168:176])[0]
            need = offset + int(np.prod([max(d, 1) for d in dims[1 : 1 + max(dims[0], 1)]])) * bitpix // 8
            have = len(head)
            while chunk := fh.read(1 << 22):
                have += len(chunk)
    except (OSError, EOFError, struct.error, zlib.error) as exc:
        raise KneeMeshError("corrupt", f"{p.name}: the NIfTI file is truncated or corrupt ({exc}).") from exc
    if have < need:
        raise KneeMeshError(
            "corrupt", f"{p.name}: the NIfTI file is truncated ({have:,} of {need:,} bytes); re-export or re-copy it."
        )


def _check_geometry(image: sitk.Image, name: str, max_voxels: int) -> None:
    dim = image.GetDimension()
    size = image.GetSize()
    if dim != 3 or min(size) < 2:
        flat = dim == 3 and sorted(size)[0] == 1
        what = (f"a single slice ({' x '.join(str(n) for n in size if n > 1)} pixels)" if flat or dim == 2
                else f"{dim}-D, size {size}")
        raise KneeMeshError(
            "not_3d",
            f"{Path(name).name}: the image is {what}; expected one 3-D volume: every slice of a sagittal acquisition "
            "(a DICOM series as a folder or a zip of all its files, not one file of it; a 4-D series cannot be meshed).",
        )
    if image.GetNumberOfComponentsPerPixel() != 1:
        raise KneeMeshError("not_3d", f"{Path(name).name}: the image has vector pixels; expected a scalar 3-D volume.")
    sp = np.asarray(image.GetSpacing())
    lo, hi = SPACING_RANGE_MM
    if not np.all(np.isfinite(sp)) or sp.min() < lo or sp.max() > hi:
        raise KneeMeshError(
            "bad_spacing",
            f"{Path(name).name}: voxel spacing {tuple(np.round(sp, 4))} mm is implausible; "
            f"expected each spacing between {lo} and {hi} mm.",
        )
    n = int(np.prod(size))
    if n > max_voxels:
        raise KneeMeshError(
            "too_large",
            f"{Path(name).name}: {n:,} voxels exceeds the limit of {max_voxels:,}; crop or resample the volume.",
        )


def read_label_map(path: str | os.PathLike, *, max_voxels: int = MAX_VOXELS) -> Volume:
    """Read a segmentation label map and check that it is one.

    The voxels must be integers (integral-valued float images are accepted and
    converted) and at least one must be non-zero.

    Raises
    ------
    KneeMeshError
        Everything :func:`read_volume` raises, plus ``float_labels`` and
        ``empty_labels``.
    """
    vol = read_volume(path, max_voxels=max_voxels)
    image = vol.image
    name = Path(vol.source).name
    arr = sitk.GetArrayViewFromImage(image)
    if np.issubdtype(arr.dtype, np.floating):
        finite = np.isfinite(arr).all()
        if not finite or not np.all(np.mod(arr, 1) == 0):
            raise KneeMeshError(
                "float_labels",
                f"{name}: the voxels are non-integer floats (a probability map, an interpolated label map, an MRI?); "
                "expected integer tissue labels. An MRI is sent as an image: `kneemesh run` (the API: input_type=image).",
            )
    if arr.min() < 0:
        raise KneeMeshError("unknown_labels", f"{name}: negative label values; expected labels >= 0.")
    if arr.max() > 255:
        raise KneeMeshError(
            "unknown_labels", f"{name}: label values up to {int(arr.max())}; expected small integer tissue labels. An MRI, not "
            "a label map? Send it as an image: `kneemesh run` (the API: input_type=image)."
        )
    if not arr.any():
        raise KneeMeshError("empty_labels", f"{name}: the label map is empty (all voxels 0); expected tissue labels.")
    if arr.dtype != np.uint8:
        cast = sitk.Cast(image, sitk.sitkUInt8)
        cast.CopyInformation(image)
        vol.image = cast
    return vol


def write_image(image: sitk.Image, path: str | os.PathLike) -> Path:
    """Write an image atomically (:func:`.files.atomic_path`), compressed.

    Use ``.nrrd`` for hand-offs inside the pipeline: it keeps the geometry exact.
    """
    with atomic_path(path) as tmp:
        sitk.WriteImage(image, tmp, useCompression=True)
    return Path(path)


def voxel_to_lps(image: sitk.Image, ijk: np.ndarray) -> np.ndarray:
    """Map voxel indices to physical LPS coordinates.

    Parameters
    ----------
    image : SimpleITK.Image
    ijk : (N, 3) array
        Continuous indices in ITK order (i fastest, i.e. reversed numpy order).

    Returns
    -------
    (N, 3) float64 array, LPS mm.
    """
    d = np.asarray(image.GetDirection(), dtype=float).reshape(3, 3)
    s = np.asarray(image.GetSpacing(), dtype=float)
    o = np.asarray(image.GetOrigin(), dtype=float)
    return o + (np.asarray(ijk, dtype=float) * s) @ d.T


def voxel_volume_ml(image: sitk.Image) -> float:
    """Volume of one voxel in ml (1 ml = 1000 mm^3)."""
    return float(np.prod(image.GetSpacing())) / 1000.0

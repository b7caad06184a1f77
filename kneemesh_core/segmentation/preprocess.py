"""Between a volume in any orientation and the network's sagittal slices, and back.

The network sees sagittal slices in one orientation (``PIR``: columns run
anterior to posterior, rows superior to inferior, slices across the knee) at
its training pixel spacing, with intensities scaled by robust percentiles.
:func:`to_slices` does that to an image and remembers how; :func:`from_slices`
puts a label array back on the input's exact grid (size, spacing, origin and
direction copied, not recomputed).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import SimpleITK as sitk

from kneemesh_core.errors import KneeMeshError

#: Orientation of the network's slices (ITK code: index axes point towards P, I and R).
NET_ORIENTATION = "PIR"
#: The network's classes: the tibial plates are one class, split by anatomy afterwards.
NET_CLASSES: tuple[str, ...] = ("background", "femur", "tibia", "patella", "femoral_cartilage",
                                "tibial_cartilage", "patellar_cartilage")
#: Canonical label value (0..7) -> network class.
CANONICAL_TO_NET = np.array([0, 1, 2, 3, 4, 5, 5, 6], dtype=np.uint8)
#: Intensity percentiles mapped to 0 and 1.
PERCENTILES = (0.5, 99.5)
#: Slice sizes are padded to a multiple of this (the network halves them five times).
MULTIPLE = 32


def normalise(arr: np.ndarray, percentiles: tuple[float, float] = PERCENTILES) -> np.ndarray:
    """Intensities (any shape) mapped so the volume's low and high percentiles are 0 and 1 (float32).

    Percentiles rather than min/max or mean/SD: a few bright vessels or a fat
    rim must not rescale the knee (whole-volume z-scores fail on odd fields of view).
    """
    a = np.asarray(arr, dtype=np.float32)
    sample = a.ravel()[:: max(1, a.size // 2_000_000)]
    lo, hi = np.percentile(sample, percentiles)
    if not hi > lo:
        raise KneeMeshError("flat_image", "the image has no contrast (its intensities are all but constant).")
    return np.clip((a - lo) / (hi - lo), -0.5, 2.0).astype(np.float32)


@dataclass
class SliceGeometry:
    """How an input image became network slices: enough to undo it exactly."""

    reference: sitk.Image  # the input (its grid is the output's)
    oriented: sitk.Image  # the input reoriented to NET_ORIENTATION
    resampled: bool  # whether the oriented image was resampled to the network's pixel spacing
    shape: tuple[int, int]  # in-plane shape before padding (rows, columns)


def to_slices(image: sitk.Image, pixel_mm: float | None) -> tuple[np.ndarray, SliceGeometry]:
    """Sagittal slices (S, H, W) float32, normalised and padded to multiples of 32, and their geometry.

    ``pixel_mm``: the network's in-plane spacing; an image more than 5 % off it is resampled
    (linear) in-plane.  ``None`` keeps the image's own spacing.
    """
    if image.GetDimension() != 3:
        raise KneeMeshError("not_3d", f"segmentation needs a 3-D image, got {image.GetDimension()}-D.")
    oriented = sitk.DICOMOrient(sitk.Cast(image, sitk.sitkFloat32), NET_ORIENTATION)
    sx, sy, sz = oriented.GetSpacing()
    resampled = pixel_mm is not None and (abs(sx / pixel_mm - 1) > 0.05 or abs(sy / pixel_mm - 1) > 0.05)
    grid = oriented
    if resampled:
        size = [max(1, int(round(n * s / pixel_mm))) for n, s in zip(oriented.GetSize()[:2], (sx, sy))]
        grid = sitk.Resample(oriented, size + [oriented.GetSize()[2]], sitk.Transform(), sitk.sitkLinear,
                             oriented.GetOrigin(), (pixel_mm, pixel_mm, sz), oriented.GetDirection(), 0.0)
    arr = normalise(sitk.GetArrayFromImage(grid))  # (S, H, W): slices, rows, columns
    h, w = arr.shape[1:]
    pad = ((0, 0), (0, -h % MULTIPLE), (0, -w % MULTIPLE))
    return np.pad(arr, pad, mode="edge"), SliceGeometry(image, oriented, resampled, (h, w))


def from_slices(classes: np.ndarray, geo: SliceGeometry) -> sitk.Image:
    """Per-slice class indices (S, H', W') back onto the input's grid (uint8, its exact geometry)."""
    h, w = geo.shape
    arr = np.ascontiguousarray(classes[:, :h, :w], dtype=np.uint8)
    img = sitk.GetImageFromArray(arr)
    if geo.resampled:
        o = geo.oriented
        sx, sy = (o.GetSize()[0] * o.GetSpacing()[0] / w, o.GetSize()[1] * o.GetSpacing()[1] / h)
        img.SetSpacing((sx, sy, o.GetSpacing()[2]))
        img.SetOrigin(o.GetOrigin())
        img.SetDirection(o.GetDirection())
        img = sitk.Resample(img, o, sitk.Transform(), sitk.sitkNearestNeighbor, 0, sitk.sitkUInt8)
    else:
        img.CopyInformation(geo.oriented)
    return reorient_like(img, geo.reference)


def reorient_like(image: sitk.Image, reference: sitk.Image) -> sitk.Image:
    """``image`` (on the grid of ``reference`` reoriented to any axis order) back in the reference's
    axis order, with the reference's size, spacing, origin and direction copied exactly."""
    code = sitk.DICOMOrientImageFilter.GetOrientationFromDirectionCosines(reference.GetDirection())
    back = sitk.DICOMOrient(image, code)
    out = sitk.GetImageFromArray(sitk.GetArrayViewFromImage(back).copy())
    out.CopyInformation(reference)
    return out

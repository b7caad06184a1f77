"""Agreement of two label maps of one knee: the one rule for their grids, and Dice per tissue.

``kneemesh compare`` (two results of one knee) and ``kneemesh evaluate-seg`` (a segmentation against
reference labels) both read them here.
"""

from __future__ import annotations

import itertools

import numpy as np
import SimpleITK as sitk

from kneemesh_core.errors import KneeMeshError
from kneemesh_core.tissues import LABEL

#: Grids agree when their sizes are equal and their spacing (mm), origin (mm) and direction agree within these.
SPACING_TOL_MM, ORIGIN_TOL_MM, DIRECTION_TOL = 1e-4, 1e-3, 1e-4


def same_grid(a: sitk.Image, b: sitk.Image) -> bool:
    return (a.GetSize() == b.GetSize() and np.allclose(a.GetSpacing(), b.GetSpacing(), atol=SPACING_TOL_MM)
            and np.allclose(a.GetOrigin(), b.GetOrigin(), atol=ORIGIN_TOL_MM)
            and np.allclose(a.GetDirection(), b.GetDirection(), atol=DIRECTION_TOL))


def _box_mm(image: sitk.Image) -> tuple[np.ndarray, np.ndarray]:
    """The axis-aligned box (LPS mm, lower and upper corners) of an image's voxel centres."""
    corners = [image.TransformContinuousIndexToPhysicalPoint([c * (n - 1) for c, n in zip(corner, image.GetSize())])
               for corner in itertools.product((0, 1), repeat=3)]
    return np.min(corners, axis=0), np.max(corners, axis=0)


def on_grid_of(reference: sitk.Image, labels: sitk.Image) -> sitk.Image:
    """``labels`` on ``reference``'s grid: as they are where the grids agree (:func:`same_grid`), else
    resampled by nearest neighbour (a label map of the same knee written on another grid).

    Raises ``grid_mismatch`` when the two maps share no space at all (not the same knee's)."""
    if same_grid(reference, labels):
        return labels
    (lo_a, hi_a), (lo_b, hi_b) = _box_mm(reference), _box_mm(labels)
    if np.any(np.minimum(hi_a, hi_b) < np.maximum(lo_a, lo_b)):
        raise KneeMeshError("grid_mismatch", "the two label maps share no space (their grids do not overlap): "
                            "expected two label maps of the same knee.")
    return sitk.Resample(labels, reference, sitk.Transform(), sitk.sitkNearestNeighbor, 0)


def dice(a: sitk.Image, b: sitk.Image) -> dict[str, float | None]:
    """Dice of each canonical tissue between two label maps (``b`` on ``a``'s grid, :func:`on_grid_of`);
    None where neither has the tissue."""
    x, y = sitk.GetArrayViewFromImage(a), sitk.GetArrayViewFromImage(on_grid_of(a, b))
    out = {}
    for tissue, value in LABEL.items():
        ia, ib = x == value, y == value
        total = int(ia.sum()) + int(ib.sum())
        out[tissue] = 2.0 * int((ia & ib).sum()) / total if total else None
    return out

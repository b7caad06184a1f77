"""Segmentation accuracy per tissue: Dice, average symmetric surface distance and 95 % Hausdorff (mm)."""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk
from scipy import ndimage as ndi

from kneemesh_core.metrics.labels import dice, on_grid_of
from kneemesh_core.tissues import LABEL, TISSUES


def _surface(mask: np.ndarray) -> np.ndarray:
    return mask & ~ndi.binary_erosion(mask)


def _surface_distances(a: np.ndarray, b: np.ndarray, spacing_zyx) -> np.ndarray:
    """Distances (mm) from the surface voxels of ``a`` to the surface of ``b``, within their common bounding box."""
    box = ndi.find_objects((a | b).astype(np.uint8))[0]
    box = tuple(slice(max(s.start - 2, 0), s.stop + 2) for s in box)
    a, b = a[box], b[box]
    dist = ndi.distance_transform_edt(~_surface(b), sampling=spacing_zyx)
    return dist[_surface(a)]


def compare(pred: sitk.Image, truth: sitk.Image) -> dict[str, dict]:
    """Per canonical tissue present in either map: ``dice``, ``assd_mm``, ``hd95_mm`` (None where a map
    lacks it), and the volumes in ml, on the prediction's grid (the reference on it:
    :func:`kneemesh_core.metrics.labels.on_grid_of`)."""
    truth = on_grid_of(pred, truth)
    dices = dice(pred, truth)
    p, t = sitk.GetArrayViewFromImage(pred), sitk.GetArrayViewFromImage(truth)
    spacing = pred.GetSpacing()[::-1]
    voxel_ml = float(np.prod(spacing)) / 1000.0
    out = {}
    for tissue in TISSUES:
        a, b = p == LABEL[tissue], t == LABEL[tissue]
        if not a.any() and not b.any():
            continue
        row = {"dice": round(dices[tissue], 4),
               "pred_ml": round(float(a.sum() * voxel_ml), 3), "truth_ml": round(float(b.sum() * voxel_ml), 3),
               "assd_mm": None, "hd95_mm": None}
        if a.any() and b.any():
            d = np.concatenate([_surface_distances(a, b, spacing), _surface_distances(b, a, spacing)])
            row["assd_mm"] = round(float(d.mean()), 3)
            row["hd95_mm"] = round(float(np.percentile(d, 95)), 3)
        out[tissue] = row
    return out

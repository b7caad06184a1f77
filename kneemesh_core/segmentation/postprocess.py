"""Clean the network's class map before it becomes canonical labels.

Per tissue: keep the largest connected component (for a bone: the one with
the most contact with its cartilage, so a dark region read as bone away from
the joint is dropped; the patellar cartilage), or the components at least 5 %
the size of the largest
(femoral cartilage, which lesions and full-thickness defects may cut in
pieces; the tibial class, which is two plates); fill holes smaller than
``max_hole_ml`` inside each bone; dropped voxels become background.  The tibial
class is then split into medial and lateral plates by the same anatomy the
label-map path uses (:func:`kneemesh_core.knee.canonicalise`).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi

#: Bone class -> the cartilage class on it.
CARTILAGE_OF = {1: 4, 2: 5, 3: 6}
#: Network class -> keep only the largest component (True) or every piece >= 5 % of it (False).
LARGEST_ONLY = {1: True, 2: True, 3: True, 4: False, 5: False, 6: True}


def clean_classes(classes: np.ndarray, spacing_zyx: tuple[float, float, float], max_hole_ml: float = 1.0) -> np.ndarray:
    """A cleaned copy of a class map (Z, Y, X) uint8 in network classes (spacing in mm, numpy order).

    Each class is cleaned within its own bounding box (a few per cent of the volume for most),
    which keeps this a fraction of the inference time.
    """
    out = classes.copy()
    voxel_ml = float(np.prod(spacing_zyx)) / 1000.0
    boxes = ndi.find_objects(out, max_label=max(LARGEST_ONLY))
    for c, largest_only in LARGEST_ONLY.items():
        box = boxes[c - 1]
        if box is None:
            continue
        view = out[box]  # a view: changes land in ``out``
        mask = view == c
        comp, n = ndi.label(mask)
        if n > 1:
            sizes = np.bincount(comp.ravel())[1:]
            if c in CARTILAGE_OF:  # a bone is the piece its cartilage lies on, whatever else looks like bone
                touch = np.bincount(comp[ndi.binary_dilation(view == CARTILAGE_OF[c]) & mask], minlength=n + 1)[1:]
                sizes = np.where(touch.max() > 0, touch, sizes)
            keep = sizes == sizes.max() if largest_only else sizes >= 0.05 * sizes.max()
            view[mask & ~np.concatenate([[False], keep])[comp]] = 0
        if c in (1, 2, 3):  # bones are solid: fill their small holes (marrow lesions read as other tissue)
            kept = ndi.find_objects((view == c).astype(np.uint8))
            if not kept:
                continue
            bone = view[kept[0]]  # the kept bone's own box: stray voxels dropped above no longer widen it
            solid = bone == c
            holes, m = ndi.label(ndi.binary_fill_holes(solid) & ~solid)
            if m:
                small = np.bincount(holes.ravel())[1:] * voxel_ml <= max_hole_ml
                bone[np.concatenate([[False], small])[holes]] = c
    return out

"""Is a segmentation a plausible knee?  Checked after the network, before anything is meshed.

A network can return labels that mesh without complaint and are still not a knee: air read as
femur, calf muscle read as patella, a cartilage floating with no bone beneath it.  Each check
compares one figure of the labels with the range measured on the 126 real label maps in
``../shared/data/real`` (``bench/plausibility.py`` prints them), widened so that every real map
passes with room to spare:

* each tissue present, its volume within :data:`VOLUME_ML`;
* each bone one piece (its largest component at least :data:`MIN_LARGEST_COMPONENT` of it);
* each cartilage on its bone (at least :data:`MIN_ON_BONE` of its voxels within
  :data:`ON_BONE_MM` of the bone);
* the patella in front of the femoral cartilage (centroids, within :data:`PATELLA_ANTERIOR_MM`);
* the patellar cartilage on the patella's femoral side, facing the trochlea: its centroid nearer the
  femoral cartilage's than the patella's is, by at least :data:`MIN_PATELLAR_CARTILAGE_FACING_MM`
  (patella bone or tissue in front of it read as patellar cartilage pulls it away).

Bones swapped or misplaced show as cartilage off its bone.  (Which bone lies higher is not
checked: label maps cropped to the joint, and frames that are not LPS-superior, make it
unreliable on real maps.)

A failed check makes the knee ``review`` with its reason, never a silent ``ok``.
"""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk
from scipy import ndimage as ndi

from kneemesh_core.tissues import BONE_OF, BONES, LABEL, TISSUES

#: Tissue volume, ml: the real maps' range (femur 129-294, tibia 86-189, patella 10-32, femoral
#: cartilage 7.5-31, tibial plates 1.2-5.6, patellar cartilage 1.3-7.0) from half the smallest to
#: 1.5 times the largest.
VOLUME_ML = {
    "femur": (64.0, 440.0), "tibia": (43.0, 283.0), "patella": (5.2, 48.0), "femoral_cartilage": (3.7, 46.0),
    "medial_tibial_cartilage": (0.58, 7.5), "lateral_tibial_cartilage": (0.58, 8.5), "patellar_cartilage": (0.63, 10.6),
}
#: A bone's largest connected piece is at least this fraction of it.
MIN_LARGEST_COMPONENT = 0.95
#: A cartilage voxel counts as on its bone within this distance of it, mm ...
ON_BONE_MM = 3.0
#: ... and at least this fraction of the cartilage's voxels must be (real maps: 0.70-1.0, median 0.95;
#: a cartilage with no bone beneath it: 0).
MIN_ON_BONE = 0.5
#: Patella centroid in front of the femoral cartilage's along the anterior axis (LPS -y), mm (real
#: maps: 9-55).
PATELLA_ANTERIOR_MM = (4.0, 80.0)
#: The patellar cartilage's centroid nearer the femoral cartilage's than the patella's centroid is, by at least
#: this, mm (real maps: 3.1-7.8, median 5.4; half the smallest).
MIN_PATELLAR_CARTILAGE_FACING_MM = 1.5


def figures(labels: sitk.Image) -> dict:
    """The figures the checks read, from canonical labels in LPS mm."""
    a = sitk.GetArrayViewFromImage(labels)
    spacing_zyx = np.array(labels.GetSpacing())[::-1]
    voxel_ml = float(np.prod(spacing_zyx)) / 1000.0
    boxes = ndi.find_objects(np.asarray(a), max_label=len(TISSUES))
    out: dict = {"volumes_ml": {}, "largest_component": {}, "on_bone": {}, "centroids_mm": {}}
    for t in TISSUES:
        box = boxes[LABEL[t] - 1]
        mask = a[box] == LABEL[t] if box is not None else np.zeros((0,), bool)
        out["volumes_ml"][t] = round(float(mask.sum()) * voxel_ml, 3)
        if box is None:
            continue
        idx = np.argwhere(mask).mean(0) + [s.start for s in box]
        out["centroids_mm"][t] = [round(float(c), 2) for c in labels.TransformContinuousIndexToPhysicalPoint(idx[::-1].tolist())]
        if t in BONES:
            comp, n = ndi.label(mask)
            sizes = np.bincount(comp.ravel())[1:]
            out["largest_component"][t] = round(float(sizes.max() / sizes.sum()), 4) if n else 0.0
    for cart, bone in BONE_OF.items():
        cbox, bbox = boxes[LABEL[cart] - 1], boxes[LABEL[bone] - 1]
        if cbox is None:
            continue
        if bbox is None:  # a cartilage with no bone at all floats
            out["on_bone"][cart] = 0.0
            continue
        pad = np.ceil(ON_BONE_MM / spacing_zyx).astype(int) + 1  # the cartilage's box, padded: its bone within reach
        box = tuple(slice(max(s.start - p, 0), min(s.stop + p, n)) for s, p, n in zip(cbox, pad, a.shape))
        near = ndi.distance_transform_edt(a[box] != LABEL[bone], sampling=spacing_zyx) <= ON_BONE_MM
        out["on_bone"][cart] = round(float(near[a[box] == LABEL[cart]].mean()), 4)
    c = out["centroids_mm"]
    if "patella" in c and "femoral_cartilage" in c:
        out["patella_anterior_mm"] = round(c["femoral_cartilage"][1] - c["patella"][1], 2)
    if {"patella", "patellar_cartilage", "femoral_cartilage"} <= set(c):
        fc = np.array(c["femoral_cartilage"])
        out["patellar_cartilage_facing_mm"] = round(float(np.linalg.norm(np.array(c["patella"]) - fc)
                                                          - np.linalg.norm(np.array(c["patellar_cartilage"]) - fc)), 2)
    return out


def check(f: dict) -> tuple[str, list[str]]:
    """(``ok`` or ``review``, reasons) of :func:`figures`."""
    reasons = []
    for t, (lo, hi) in VOLUME_ML.items():
        v = f["volumes_ml"].get(t, 0.0)
        if not lo <= v <= hi:
            reasons.append(f"{t.replace('_', ' ')}: {v:.2f} ml, outside the {lo:g}-{hi:g} ml of real knees"
                           + (" (missing)" if v == 0 else ""))
    for b, frac in f["largest_component"].items():
        if frac < MIN_LARGEST_COMPONENT:
            reasons.append(f"{b}: in pieces (the largest is {frac:.0%} of it; a bone is one piece)")
    for cart, frac in f["on_bone"].items():
        if frac < MIN_ON_BONE:
            reasons.append(f"{cart.replace('_', ' ')}: only {frac:.0%} of it lies within {ON_BONE_MM:g} mm of the "
                           f"{BONE_OF[cart]} (a cartilage rests on its bone; target {MIN_ON_BONE:.0%})")
    lo, hi = PATELLA_ANTERIOR_MM
    if "patella_anterior_mm" in f and not lo <= f["patella_anterior_mm"] <= hi:
        reasons.append(f"the patella's centre in front of the femoral cartilage's: {f['patella_anterior_mm']:.0f} mm, "
                       f"outside the {lo:g}-{hi:g} mm of real knees")
    facing = f.get("patellar_cartilage_facing_mm")
    if facing is not None and facing < MIN_PATELLAR_CARTILAGE_FACING_MM:
        reasons.append(f"patellar cartilage: its centre lies {facing:.1f} mm nearer the femoral cartilage's than the "
                       f"patella's, under the {MIN_PATELLAR_CARTILAGE_FACING_MM:g} mm of real knees (a patellar cartilage "
                       "covers the patella's femoral side, facing the trochlea)")
    return ("review" if reasons else "ok"), reasons

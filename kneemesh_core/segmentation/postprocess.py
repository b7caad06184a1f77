"""Clean the network's class map before it becomes canonical labels, by anatomy.

Per tissue, in order:

1. **Bones are opened before their piece is chosen.**  A bone class is eroded by
   :data:`OPENING_MM`; of the cores left, the one against its cartilage is kept and grown back
   within the class by :data:`REGROW_MM`.  Bridges thinner than twice the opening, through which
   a network's bone class leaks into air, fat or muscle beside the knee, are cut (the real
   pyKNEEr DESS: a 538 ml "femur" of which 137 ml is the femur).
2. **The patella is the piece against the femoral cartilage** (within :data:`PATELLA_REACH_MM`),
   or none: not the piece its own cartilage touches, because on the real DESS the network read calf
   muscle as patellar cartilage and patella behind the femur.  (Not "in front of the femur" by the header's axes: the
   Gibbons maps' headers do not put the patella in front.)
3. **Each slice's bone lies near its cartilage.**  The network reads slices one at a time, and its
   errors are slice-shaped: on the real pyKNEEr DESS, 6 ml of quadriceps above the condyles was
   labelled femur over 16 slices, joined to the true shaft through the slices beside it, so no
   opening cuts it.  In each sagittal slice, a bone's in-plane pieces farther than
   :data:`SLICE_REACH_MM` from every voxel of its cartilage (in 3-D) are dropped.  The condyles are
   wider than the shaft, so every slice of true femur meets its condyles' cartilage within that
   reach; on 16 manual OAI, pymskt and Gibbons maps the rule drops at most 0.04 % of a bone.
4. Femoral and tibial cartilage keep every piece at least 5 % the size of the largest (lesions
   and full-thickness defects cut them in pieces; the tibial class is two plates); then every
   cartilage keeps only the pieces that rest on its kept bone (within :data:`OPENING_MM`; the
   largest piece if the bone is missing): on the real DESS, three 0.16-0.19 ml "tibial
   cartilage" specks lay 29-48 mm from the tibia, in muscle and fluid.
5. Small holes inside each bone (marrow lesions read as another tissue) are filled.

Dropped voxels become background.  The tibial class is then split into medial and lateral plates
by the same anatomy the label-map path uses (:func:`kneemesh_core.knee.canonicalise`).

Arrays are the network's slices, (S, H, W) (:mod:`.preprocess`).
"""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk
from scipy import ndimage as ndi

FEMUR, TIBIA, PATELLA, FC, TC, PC = 1, 2, 3, 4, 5, 6
#: A bone is eroded by this much (mm) before its piece is chosen ...
OPENING_MM = 2.0
#: ... and the chosen core grown back within the class by this much (twice the erosion: a thin
#: osteophyte or spine up to this long survives the opening).
REGROW_MM = 4.0
#: The patella's core must lie within this distance (mm) of the femoral cartilage.
PATELLA_REACH_MM = 10.0
#: A bone's piece in a sagittal slice is kept only within this distance (mm) of its cartilage.
SLICE_REACH_MM = 20.0
#: In-plane connectivity of (S, H, W) arrays: pieces within one slice.
_IN_SLICE = np.zeros((3, 3, 3), bool)
_IN_SLICE[1] = True


def _edt(mask: np.ndarray, spacing) -> np.ndarray:
    """Distance (mm) of each True voxel to the nearest False one (0 on False voxels).

    SimpleITK's Maurer transform (multithreaded): the same figures as scipy's
    ``distance_transform_edt`` to 1e-4 mm, 4x faster on a DESS volume.
    """
    image = sitk.GetImageFromArray((~mask).astype(np.uint8))
    image.SetSpacing(tuple(float(s) for s in spacing[::-1]))
    d = sitk.GetArrayFromImage(sitk.SignedMaurerDistanceMap(image, insideIsPositive=False, squaredDistance=False,
                                                            useImageSpacing=True))
    return np.maximum(d, 0.0)


def _pick(labels: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """The voxels of the components ``keep`` (boolean over components 1..n) of a label array."""
    return np.concatenate([[False], keep])[labels]


def _largest(values: np.ndarray) -> np.ndarray:
    """Boolean over components 1..n: the one with the largest value (ties: the first)."""
    keep = np.zeros(len(values), bool)
    if len(values) and values.max() > 0:
        keep[int(values.argmax())] = True
    return keep


def _box(mask: np.ndarray, margin_mm: float, spacing) -> tuple[slice, ...]:
    """The bounding box of ``mask`` grown by ``margin_mm`` (clipped to the array)."""
    box = ndi.find_objects(mask.astype(np.uint8))[0]
    return tuple(slice(max(0, b.start - int(np.ceil(margin_mm / s))), min(n, b.stop + int(np.ceil(margin_mm / s))))
                 for b, s, n in zip(box, spacing, mask.shape))


def _coarse_step(spacing) -> int:
    """In-plane stride of a grid of about half :data:`OPENING_MM` (a DESS's 0.36 mm pixels: 2)."""
    return max(1, int(OPENING_MM / 2 / min(spacing[1:])))


def _distance_to(mask: np.ndarray, box: tuple[slice, ...], spacing) -> np.ndarray:
    """Distance (mm) of each voxel of ``box`` to the nearest True voxel of ``mask`` within it, on a
    grid :func:`_coarse_step` times coarser in-plane and repeated back to the box's shape (4x
    fewer voxels; within about a millimetre, which the reaches it is compared with do not need)."""
    sub = mask[box]
    k = _coarse_step(spacing)
    d = _edt(~sub[:, ::k, ::k], (spacing[0], spacing[1] * k, spacing[2] * k))
    return np.repeat(np.repeat(d, k, 1), k, 2)[:, :sub.shape[1], :sub.shape[2]]


def _bone(out: np.ndarray, c: int, spacing, anchor: np.ndarray | None = None, reach_mm: float = REGROW_MM,
          strict: bool = False) -> np.ndarray:
    """Keep one piece of bone class ``c`` in ``out`` (in place); returns its mask (whole array).

    ``anchor``: the tissue the bone lies against (its cartilage; the femoral cartilage for the
    patella); of the bone's cores, the one with the most voxels within ``reach_mm`` of it is kept,
    else the largest core (``strict``: else none).
    """
    whole = out == c
    if not whole.any():
        return whole
    box = _box(whole, reach_mm + REGROW_MM, spacing)
    mask, view = whole[box], out[box]
    # the cores on a grid of about half the opening in-plane (a DESS's 0.3 mm pixels: 4x fewer voxels)
    k = _coarse_step(spacing)
    coarse = (spacing[0], spacing[1] * k, spacing[2] * k)
    core, n = ndi.label(_edt(mask[:, ::k, ::k], coarse) > OPENING_MM)
    if n == 0:  # thinner than the opening everywhere: its largest piece as it is
        comp, m = ndi.label(mask)
        kept = _pick(comp, _largest(np.bincount(comp.ravel(), minlength=m + 1)[1:]))
    else:
        score = np.bincount(core.ravel(), minlength=n + 1)[1:].astype(float)
        near_anchor = None if anchor is None else anchor[box][:, ::k, ::k]
        near = np.zeros(n)
        if near_anchor is not None and near_anchor.any():
            around = _box(near_anchor, reach_mm, coarse)  # distances only near the anchor
            near = np.bincount(core[around][_edt(~near_anchor[around], coarse) <= reach_mm],
                               minlength=n + 1)[1:].astype(float)
        if near.max() > 0 or strict:
            score = near
        chosen = _pick(core, _largest(score))
        kept = np.repeat(np.repeat(chosen, k, 1), k, 2)[:, :mask.shape[1], :mask.shape[2]] & mask
        if kept.any():
            grow = _box(kept, REGROW_MM, spacing)
            kept[grow] = (_edt(~kept[grow], spacing) <= REGROW_MM) & mask[grow]
    view[mask & ~kept] = 0
    whole[box] = kept
    return whole


def _near_in_each_slice(out: np.ndarray, c: int, anchor: np.ndarray, spacing) -> None:
    """Drop the in-slice pieces of class ``c`` farther than :data:`SLICE_REACH_MM` from every
    ``anchor`` voxel (in place; nothing is dropped when there is no anchor)."""
    bone = out == c
    if not (bone.any() and anchor.any()):
        return
    box = _box(bone, 0.0, spacing)
    pieces, n = ndi.label(bone[box], _IN_SLICE)
    reach = _box(bone, SLICE_REACH_MM, spacing)  # the anchor farther out cannot be within reach
    distance = _distance_to(anchor, reach, spacing)[tuple(slice(b.start - r.start, b.stop - r.start)
                                                          for b, r in zip(box, reach))]
    far = np.bincount(pieces[distance <= SLICE_REACH_MM], minlength=n + 1)[1:] == 0
    if far.any():
        out[box][_pick(pieces, far)] = 0


def _on_bone(out: np.ndarray, c: int, bone: np.ndarray, spacing) -> None:
    """Keep the pieces of cartilage class ``c`` that rest on ``bone`` (within :data:`OPENING_MM`),
    or its largest piece when there is no bone (in place)."""
    cart = out == c
    if not cart.any():
        return
    comp, n = ndi.label(cart)
    if bone.any():
        box = _box(cart, OPENING_MM, spacing)  # the bone farther out cannot be within the opening
        on = np.bincount(comp[box][_distance_to(bone, box, spacing) <= OPENING_MM], minlength=n + 1)[1:] > 0
    else:
        on = _largest(np.bincount(comp.ravel(), minlength=n + 1)[1:])
    out[cart & ~_pick(comp, on)] = 0


def _pieces(out: np.ndarray, c: int, min_share: float = 0.05) -> None:
    """Keep every piece of class ``c`` at least ``min_share`` the size of its largest (in place)."""
    mask = out == c
    comp, n = ndi.label(mask)
    if n > 1:
        sizes = np.bincount(comp.ravel())[1:]
        out[mask & ~_pick(comp, sizes >= min_share * sizes.max())] = 0


def _fill_holes(out: np.ndarray, c: int, max_voxels: float) -> None:
    box = ndi.find_objects((out == c).astype(np.uint8))
    if not box:
        return
    bone = out[box[0]]  # a view: the kept bone's own box
    solid = bone == c
    holes, m = ndi.label(ndi.binary_fill_holes(solid) & ~solid)
    if m:
        small = np.bincount(holes.ravel())[1:] <= max_voxels
        bone[_pick(holes, small)] = c


def clean_classes(classes: np.ndarray, spacing_zyx: tuple[float, float, float], max_hole_ml: float = 1.0) -> np.ndarray:
    """A cleaned copy of a class map (S, H, W) uint8 in network classes, ``PIR`` slices (spacing
    in mm, numpy order)."""
    out = classes.copy()
    spacing = tuple(float(s) for s in spacing_zyx)
    for cart in (FC, TC):
        _pieces(out, cart)
    fc = out == FC
    _bone(out, FEMUR, spacing, fc)
    _near_in_each_slice(out, FEMUR, fc, spacing)
    _bone(out, TIBIA, spacing, out == TC)
    _near_in_each_slice(out, TIBIA, out == TC, spacing)
    patella = _bone(out, PATELLA, spacing, fc, PATELLA_REACH_MM, strict=True)
    for cart, bone in ((FC, out == FEMUR), (TC, out == TIBIA), (PC, patella)):
        _on_bone(out, cart, bone, spacing)
    max_voxels = max_hole_ml * 1000.0 / float(np.prod(spacing))
    for bone in (FEMUR, TIBIA, PATELLA):
        _fill_holes(out, bone, max_voxels)
    return out

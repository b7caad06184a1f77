"""A knee's label map in the canonical convention, with its side and geometry.

:func:`load_knee` is the single entry point from a label map file (any preset)
to canonical labels 1..7 (:data:`kneemesh_core.tissues.TISSUES`) on the same
voxel grid, with spacing, origin and direction unchanged.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import SimpleITK as sitk
from scipy import ndimage as ndi

from kneemesh_core import side as side_mod
from kneemesh_core.anatomy.frames import coarse_axes
from kneemesh_core.errors import KneeMeshError
from kneemesh_core.io import Volume, read_label_map, voxel_to_lps, voxel_volume_ml
from kneemesh_core.surfaces.masks import boundary_voxels, label_box
from kneemesh_core.tissues import (
    LABEL,
    MERGED_TIBIAL,
    TISSUES,
    LabelConvention,
    check_convention,
    detect_convention,
    label_counts,
    resolve_convention,
)


@dataclass
class Knee:
    """Canonical labels of one knee.

    Attributes
    ----------
    labels : SimpleITK.Image
        uint8, values 0..7 (:data:`LABEL`), the input's grid and geometry.
    convention : LabelConvention
        The convention of the input file.
    side : str
        ``"left"`` or ``"right"``.
    side_method : str
        How the side was decided (``explicit``, ``dicom``, ``file_name``,
        ``labels_medial_lateral``, ``anatomy+scanner_position``, ...).
    side_evidence : dict
    source : str
    meta : dict
        Header facts from the input file.
    """

    labels: sitk.Image
    convention: LabelConvention
    side: str
    side_method: str
    side_evidence: dict = field(default_factory=dict)
    source: str = ""
    meta: dict = field(default_factory=dict)

    @property
    def array(self) -> np.ndarray:
        """(K, J, I) uint8 view in numpy (z, y, x) order."""
        return sitk.GetArrayViewFromImage(self.labels)

    def volumes_ml(self) -> dict[str, float]:
        """Label volume of each canonical tissue, ml."""
        counts = label_counts(self.array)
        vml = voxel_volume_ml(self.labels)
        return {t: float(counts.get(LABEL[t], 0) * vml) for t in TISSUES}

    def present(self) -> list[str]:
        return [t for t, v in self.volumes_ml().items() if v > 0]


def _lps_points(image: sitk.Image, mask: np.ndarray) -> np.ndarray:
    """LPS mm of the voxels of a (z, y, x) boolean mask, (N, 3)."""
    return voxel_to_lps(image, np.argwhere(mask)[:, ::-1])


def _centroids(image: sitk.Image, canon: np.ndarray) -> dict[int, np.ndarray]:
    """LPS mm (3,) of the centroid of each value present in a (z, y, x) label array, 0 (background)
    standing for the whole knee (every labelled voxel): SimpleITK's label statistics, one threaded
    pass over the image."""
    labels = sitk.GetImageFromArray(canon)
    labels.CopyInformation(image)
    stats = sitk.LabelShapeStatisticsImageFilter()
    stats.ComputePerimeterOff()  # the centroids and voxel counts only
    stats.Execute(labels)
    values = stats.GetLabels()
    if not values:
        return {}
    counts = np.array([stats.GetNumberOfPixels(v) for v in values], float)
    centres = np.array([stats.GetCentroid(v) for v in values])
    return {0: counts @ centres / counts.sum(), **{int(v): c for v, c in zip(values, centres)}}


#: Boundary voxels per bone that the side by shape fits (its four registrations' cost goes with them): on
#: the 40 OAI maps, whose side the shape decides, 1500 give every decision of 4000 with relative gaps of
#: 0.37-0.51 (4000: 0.38-0.50; a side needs 0.08) in 0.58 s of the ingest's canonicalisation, not 0.95 s.
SHAPE_POINTS = 1500


def _surface_points(image: sitk.Image, mask: np.ndarray, box: tuple[slice, ...], n: int = SHAPE_POINTS) -> np.ndarray:
    """LPS mm (<= n, 3) of the boundary voxels of a (z, y, x) mask that lies within ``box``, evenly
    subsampled."""
    edge = boundary_voxels(mask) + [s.start for s in box]
    return voxel_to_lps(image, edge[:: max(1, len(edge) // n), ::-1])


def _shape_side(image: sitk.Image, canon: np.ndarray, axes) -> dict:
    """Left or right from the bones' shape (:func:`kneemesh_core.anatomy.register.side_by_shape`)."""
    from kneemesh_core.anatomy.register import side_by_shape
    from kneemesh_core.anatomy.template import load

    template = load()
    boxes = ndi.find_objects(canon)  # every label's box in one pass
    subject = {b: _surface_points(image, canon[box] == LABEL[b], box)
               for b in ("tibia", "femur") if (box := boxes[LABEL[b] - 1]) is not None}
    return side_by_shape({b: template.points(b) for b in subject}, subject, axes)


def canonicalise(
    vol: Volume,
    convention: LabelConvention | None = None,
    side: str | None = None,
    require_knee: bool = False,
) -> Knee:
    """Map a label map of any convention to canonical labels, deciding the side.

    Parameters
    ----------
    vol : Volume
        A label map read by :func:`kneemesh_core.io.read_label_map`.
    convention : LabelConvention or None
        ``None`` to auto-detect (error if ambiguous).
    side : ``"left"``, ``"right"`` or None to detect.
    require_knee : refuse labels without a femur and a tibia (``not_a_knee``, :data:`REQUIRED`) before the
        side is decided.
    """
    image = vol.image
    arr = sitk.GetArrayViewFromImage(image)
    counts = label_counts(arr)
    if convention is None:
        convention = detect_convention(counts, voxel_volume_ml(image))
    check_convention(convention, counts, vol.source)
    canon = _canonical_values(arr, convention, vol.source)
    if require_knee:
        _check_is_knee(canon, image, convention, vol.source)
    evidence = _side_evidence(image, arr, canon, convention)
    decision = side_mod.decide(explicit=side, dicom_meta=vol.meta, filename=Path(vol.source).name,
                               **{k: v for k, v in evidence.items() if k not in ("merged", "coarse")})
    if evidence["merged"] is not None and evidence["merged"].any():
        _label_plates(canon, evidence["merged"], evidence["plates"], decision.side, evidence["axes"])
    out = sitk.GetImageFromArray(canon)
    out.CopyInformation(image)
    return Knee(labels=out, convention=convention, side=decision.side, side_method=decision.method,
                side_evidence=decision.evidence, source=vol.source, meta=vol.meta)


def _canonical_values(arr: np.ndarray, convention: LabelConvention, source: str) -> np.ndarray:
    """The label array (z, y, x) in canonical values, a merged tibial cartilage left at 0 (its plates are
    told apart once the side is known)."""
    lut = np.zeros(256, dtype=np.uint8)
    for tissue, vals in convention.tissues.items():
        if tissue != MERGED_TIBIAL:
            lut[list(vals)] = LABEL[tissue]
    canon = lut[arr]
    if not canon.any() and not convention.merged_tibial:
        raise KneeMeshError("empty_labels", f"{Path(source).name}: no tissue of the {convention.name!r} convention.")
    return canon


def _side_evidence(image: sitk.Image, arr: np.ndarray, canon: np.ndarray, convention: LabelConvention) -> dict:
    """What the labels tell of the knee's side (:func:`kneemesh_core.side.decide`'s keywords: its axes from
    where its bones lie, for a label map need not be in a scanner's frame; the plates' centroids where they
    are labelled apart; the fibula; the knee's position; a merged tibial cartilage split into two plates;
    the bones' shape), with the merged cartilage's mask and the coarse axes."""
    centre = _centroids(image, canon)  # by canonical label; 0: the whole knee
    knee_x = float(centre[0][0]) if 0 in centre else None
    femur, tibia, patella = (centre.get(LABEL[b]) for b in ("femur", "tibia", "patella"))
    coarse = axes = None
    if femur is not None and tibia is not None:
        coarse = coarse_axes(femur[None], tibia[None], patella[None] if patella is not None else None)
        axes = side_mod.KneeAxes(coarse.centre, coarse.right)
    mtc, ltc = (centre.get(LABEL[t]) for t in ("medial_tibial_cartilage", "lateral_tibial_cartilage"))
    labelled_ml = (mtc, ltc) if mtc is not None and ltc is not None else None
    fib_vals = convention.value_of("fibula")
    fibula = np.isin(arr, fib_vals) if fib_vals else None
    fibula_c = _centroids(image, fibula.view(np.uint8)).get(1) if fibula is not None else None
    plates = merged = None
    if convention.merged_tibial:
        merged = np.isin(arr, convention.tissues[MERGED_TIBIAL])
        if merged.sum() >= 40:
            box = label_box(merged)
            comp, _ = ndi.label(merged[box])
            pts = _lps_points(image, merged)
            plates = side_mod.split_plates(pts, comp[merged[box]])
            if knee_x is None:
                knee_x = float(pts[:, 0].mean())
    return {"axes": axes, "labelled_ml": labelled_ml, "fibula": fibula_c, "knee_x": knee_x, "plates": plates,
            "shape": (lambda: _shape_side(image, canon, coarse)) if coarse is not None else None,
            "merged": merged, "coarse": coarse}


def _label_plates(canon: np.ndarray, merged: np.ndarray, plates, side: str, axes) -> None:
    """A merged tibial cartilage's voxels (``merged``, (z, y, x) bool) labelled medial or lateral in
    ``canon``, by the plate each went to and the knee's side."""
    plus = np.ones(int(merged.sum()), dtype=bool) if plates is None else plates.plus_x  # too few to split: +x
    right = axes.right if axes is not None else np.array([-1.0, 0.0, 0.0])
    medial_is_plus = side_mod.medial_direction(side, right)[0] > 0
    values = np.where(plus == medial_is_plus, LABEL["medial_tibial_cartilage"], LABEL["lateral_tibial_cartilage"])
    canon[merged] = values.astype(np.uint8)


def load_knee(
    path: str | os.PathLike,
    *,
    preset: str | None = None,
    labels: str | None = None,
    side: str | None = None,
) -> Knee:
    """Read a label map file and return its canonical :class:`Knee`.

    Parameters
    ----------
    path : label map (NIfTI, NRRD, MHA, DICOM).
    preset : a name from :data:`kneemesh_core.tissues.PRESETS`, or None to detect.
    labels : custom mapping ``femur=5,tibia=6,...`` or a JSON file; overrides ``preset``.
    side : ``left``/``right`` or None to detect.
    """
    vol = read_label_map(path)
    return canonicalise(vol, resolve_convention(preset, labels), side)


def describe_image(image: sitk.Image, source: str) -> dict:
    """Geometry of an input image (before segmentation): source, shape, spacing, origin, orientation."""
    return {
        "source": source,
        "shape": list(image.GetSize()),
        "spacing_mm": [round(s, 6) for s in image.GetSpacing()],
        "origin_mm": [round(o, 4) for o in image.GetOrigin()],
        "orientation": sitk.DICOMOrientImageFilter.GetOrientationFromDirectionCosines(image.GetDirection()),
        "direction": [round(v, 6) for v in image.GetDirection()],
    }


#: What a label map must hold to be meshed as a knee: the cartilage is meshed on its bone, the knee's
#: frames and side come from the femur and the tibia.
REQUIRED = ("femur", "tibia")


def _check_is_knee(canon: np.ndarray, image: sitk.Image, convention: LabelConvention, source: str) -> None:
    """Refuse labels (canonical values, (z, y, x)) that are no knee (``not_a_knee``): the femur or the tibia
    missing, saying what was found."""
    counts, vml = label_counts(canon), voxel_volume_ml(image)
    volumes = {t: counts.get(LABEL[t], 0) * vml for t in TISSUES}
    missing = [t for t in REQUIRED if volumes[t] <= 0]
    if missing:
        found = ", ".join(f"{t.replace('_', ' ')} {v:.2f} ml" for t, v in volumes.items() if v > 0) or "no tissue"
        raise KneeMeshError("not_a_knee", f"{Path(source).name}: no {' and no '.join(missing)} among its labels as "
                            f"read with the {convention.name!r} convention (found: {found}); expected a knee label map "
                            "with at least the femur and the tibia labelled (another --preset or --labels mapping?).")


def describe(knee: Knee) -> dict:
    """The facts ``kneemesh inspect --json`` prints."""
    return {
        **describe_image(knee.labels, knee.source),
        "preset": knee.convention.name,
        "side": knee.side,
        "side_method": knee.side_method,
        "side_evidence": knee.side_evidence,
        "tissues": {t: round(v, 3) for t, v in knee.volumes_ml().items()},
    }

"""Left or right knee, and which tibial plate is medial.

Wrong medial/lateral silently ruins a study, so every decision records the
evidence it used, and conflicting evidence is an error that asks for
``--side`` rather than a guess.

Medial and lateral are read in the knee's own frame (:class:`KneeAxes`: the patient's right
is anterior x superior, from where the femur, tibia and patella lie), so a label map in a
frame of its own (not a scanner's) is read as truly as a scan.  In a scanner's LPS frame the
patient's right is -x, and a right knee's medial side faces +x.  Evidence, strongest first:

1. an explicit side;
2. DICOM laterality tags or the series description (OAI: ``SAG_3D_DESS_RIGHT``);
3. a ``left``/``right`` token in the file name;
4. labels that already separate medial and lateral tibial cartilage;
5. anatomy.  Strong: a fibula label (the fibula is lateral) and the whole bones' shape (which
   of the template knee or its mirror image fits the tibia and femur better,
   :func:`kneemesh_core.anatomy.register.side_by_shape`); these must agree with each other.
   Weak: the medial tibial plateau is longer antero-posteriorly than the lateral one (41 of 42
   real knees here, the 42nd within 2%; only a difference over 5% counts), and the scanner
   position of the knee (a knee coil sits off the isocentre on the knee's own side).  Weak
   evidence decides only when there is no strong evidence, and then only when it agrees; where
   it disagrees with strong evidence it is recorded as overruled.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from scipy import ndimage as ndi

from kneemesh_core.errors import KneeMeshError

SIDES = ("left", "right")
#: |log(AP_a / AP_b)| below this is no evidence.
_ANATOMY_MIN_LOG_RATIO = 0.05
#: |x| of the knee centre (LPS mm) below this says nothing about the side.
_POSITION_MIN_MM = 25.0


@dataclass(frozen=True)
class KneeAxes:
    """The knee's centre (LPS mm) and the patient's right as a unit vector, from its bones."""

    centre: np.ndarray
    right: np.ndarray


@dataclass
class SideDecision:
    side: str
    method: str
    evidence: dict = field(default_factory=dict)


def medial_direction(side: str, right: np.ndarray) -> np.ndarray:
    """The direction (3,) of a ``side`` knee's medial side: towards the patient's left in a right
    knee, towards the patient's right in a left knee."""
    return -np.asarray(right) if side == "right" else np.asarray(right)


def side_from_text(text: str | None) -> str | None:
    """``left``/``right`` from a DICOM description or a file name, or None."""
    if not text:
        return None
    t = text.lower()
    hits = set(re.findall(r"(?<![a-z])(left|right)(?![a-z])", t.replace("_", " ").replace("-", " ")))
    return hits.pop() if len(hits) == 1 else None


def side_from_dicom(meta: dict) -> str | None:
    for key in ("laterality", "image_laterality"):
        v = meta.get(key, "").strip().upper()
        if v in ("L", "R"):
            return "left" if v == "L" else "right"
    return side_from_text(meta.get("series_description")) or side_from_text(meta.get("protocol_name"))


def side_from_medial_lateral(medial: np.ndarray, lateral: np.ndarray, right: np.ndarray) -> str:
    """Side from the centroids (3,) of a medial and a lateral structure and the patient's right:
    a right knee's lateral side is the patient's right."""
    return "right" if (np.asarray(lateral) - np.asarray(medial)) @ right > 0 else "left"


def split_axis(points_xy: np.ndarray) -> np.ndarray:
    """Unit medial-lateral axis in the axial plane, pointing to LPS +x.

    The principal axis of the tibial cartilage footprint (the two plates side by
    side are wider than long); falls back to +x when that axis is more than 35
    degrees off the patient's left-right axis.

    Parameters
    ----------
    points_xy : (N, 2) LPS mm.
    """
    c = points_xy - points_xy.mean(0)
    w, v = np.linalg.eigh(c.T @ c)
    axis = v[:, np.argmax(w)]
    axis = axis if axis[0] >= 0 else -axis
    if axis[0] < np.cos(np.deg2rad(35)):
        axis = np.array([1.0, 0.0])
    return axis


def _gap_position(proj: np.ndarray) -> float:
    """Coordinate along the ML axis of the least cartilage between the plates (mm)."""
    lo, hi = np.percentile(proj, [1, 99])
    bins = np.arange(lo, hi + 0.5, 0.5)
    h, edges = np.histogram(proj, bins)
    h = ndi.uniform_filter1d(h.astype(float), 5)
    n = len(h)
    a, b = int(0.25 * n), max(int(0.75 * n), int(0.25 * n) + 1)
    k = a + int(np.argmin(h[a:b]))
    return float(0.5 * (edges[k] + edges[k + 1]))


@dataclass
class PlateSplit:
    """Two tibial plates, as boolean masks over the merged label's voxels."""

    plus_x: np.ndarray  # (N,) bool: the plate on the LPS +x side
    ap_ratio_log: float  # log(AP length of the +x plate / the -x plate)
    gap_mm: float


def split_plates(points: np.ndarray, component: np.ndarray) -> PlateSplit:
    """Split merged tibial cartilage voxels into the +x and -x plates.

    Parameters
    ----------
    points : (N, 3) LPS mm of the merged label's voxels.
    component : (N,) int, connected-component id of each voxel.

    Components lying >= 90% on one side of the gap go whole to that side (a
    plate stays in one piece); components spanning the gap (plates that touch)
    are cut at the gap.
    """
    axis = split_axis(points[:, :2])
    proj = points[:, :2] @ axis
    gap = _gap_position(proj)
    plus = proj > gap
    for cid in np.unique(component):
        m = component == cid
        frac = plus[m].mean()
        if frac >= 0.9 or frac <= 0.1:
            plus[m] = frac >= 0.5
    ap_axis = np.array([-axis[1], axis[0]])
    ap = points[:, :2] @ ap_axis

    def length(sel: np.ndarray) -> float:
        if sel.sum() < 20:
            return float("nan")
        lo, hi = np.percentile(ap[sel], [1, 99])
        return float(hi - lo)

    ratio = np.log(length(plus) / length(~plus))
    return PlateSplit(plus_x=plus, ap_ratio_log=float(ratio), gap_mm=float(gap))


def decide(
    *,
    explicit: str | None = None,
    dicom_meta: dict | None = None,
    filename: str | None = None,
    axes: KneeAxes | None = None,
    labelled_ml: tuple[np.ndarray, np.ndarray] | None = None,
    fibula: np.ndarray | None = None,
    knee_x: float | None = None,
    plates: PlateSplit | None = None,
    shape: Callable[[], dict] | None = None,
) -> SideDecision:
    """Weigh the evidence in order of strength and return the side.

    Parameters
    ----------
    axes : the knee's centre and the patient's right (without bones: the scanner's, -x).
    labelled_ml : centroids (3,) LPS mm of labelled medial and lateral tibial cartilage.
    fibula : the fibula's centroid (3,) LPS mm.
    knee_x : LPS x (mm) of the knee's centre (the scanner position).
    plates : the split of a merged tibial cartilage label.
    shape : asked only when the anatomy decides: the side by shape
        (:func:`kneemesh_core.anatomy.register.side_by_shape`'s result).
    """
    if explicit:
        if explicit not in SIDES:
            raise KneeMeshError("bad_side", f"side {explicit!r} is not one of left, right.")
        return SideDecision(explicit, "explicit")
    if dicom_meta and (s := side_from_dicom(dicom_meta)):
        return SideDecision(s, "dicom", {"series_description": dicom_meta.get("series_description")})
    if filename and (s := side_from_text(filename)):
        return SideDecision(s, "file_name", {"file_name": filename})
    axes = axes or KneeAxes(np.zeros(3), np.array([-1.0, 0.0, 0.0]))
    if labelled_ml is not None:
        return SideDecision(side_from_medial_lateral(*labelled_ml, axes.right), "labels_medial_lateral",
                            {"medial_mm": _round(labelled_ml[0]), "lateral_mm": _round(labelled_ml[1]),
                             "patient_right": _round(axes.right, 4)})
    strong, weak, evidence = _anatomical_evidence(axes, fibula, shape, plates, knee_x)
    return _weigh(strong, weak, evidence)


def _anatomical_evidence(axes: KneeAxes, fibula, shape, plates, knee_x) -> tuple[dict, dict, dict]:
    """The anatomy's votes: strong (the fibula's side, the bones' shape) and weak (the longer plate is
    medial, the scanner position), each {evidence: side}, and what each saw."""
    evidence: dict = {}
    strong: dict[str, str] = {}
    weak: dict[str, str] = {}
    if fibula is not None:
        # the fibula is lateral, and a right knee's lateral side is the patient's right
        strong["fibula"] = "right" if (np.asarray(fibula) - axes.centre) @ axes.right > 0 else "left"
        evidence["fibula_mm"] = _round(fibula)
    if shape is not None:
        found = shape()
        evidence["shape"] = found
        if found.get("side"):
            strong["shape"] = found["side"]
    if plates is not None and np.isfinite(plates.ap_ratio_log):
        evidence["plate_ap_log_ratio"] = round(plates.ap_ratio_log, 4)
        if abs(plates.ap_ratio_log) >= _ANATOMY_MIN_LOG_RATIO:
            # the longer plate is medial; the +x plate is medial in a right knee when the
            # patient's right is -x (a scanner frame)
            plus_x_medial = plates.ap_ratio_log > 0
            weak["anatomy"] = "right" if plus_x_medial == (axes.right[0] < 0) else "left"
    if knee_x is not None:
        evidence["knee_x_mm"] = round(knee_x, 2)
        if abs(knee_x) >= _POSITION_MIN_MM:
            weak["scanner_position"] = "right" if knee_x < 0 else "left"
    return strong, weak, evidence


def _conflict(votes: dict[str, str]) -> KneeMeshError:
    return KneeMeshError("side_conflict", "the evidence for left/right disagrees ("
                         + ", ".join(f"{k} says {v}" for k, v in votes.items()) + "); pass --side left or --side right.")


def _weigh(strong: dict[str, str], weak: dict[str, str], evidence: dict) -> SideDecision:
    """The side the votes give: strong evidence decides (and must agree; weak evidence against it is
    ``overruled``), else the weak evidence, which must agree; none at all is an error asking for ``--side``."""
    if strong:
        if len(set(strong.values())) > 1:
            raise _conflict(strong)
        side = next(iter(strong.values()))
        overruled = {k: v for k, v in weak.items() if v != side}
        if overruled:
            evidence["overruled"] = overruled
        votes = {**strong, **{k: v for k, v in weak.items() if v == side}}
        evidence["votes"] = votes
        return SideDecision(side, "+".join(votes), evidence)
    if not weak:
        raise KneeMeshError(
            "side_unknown",
            "cannot tell a left from a right knee here (no DICOM laterality, no left/right in the file name, "
            "no medial/lateral labels, unclear anatomy); pass --side left or --side right.",
        )
    if len(set(weak.values())) > 1:
        raise _conflict(weak)
    evidence["votes"] = weak
    return SideDecision(next(iter(weak.values())), "+".join(weak), evidence)


def _round(v, n: int = 2) -> list[float]:
    return [round(float(x), n) for x in v]

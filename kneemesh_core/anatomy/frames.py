"""Anatomical frames of a knee's bones, and the Grood-Suntay angles between femur and tibia.

Every frame is an origin and three named unit axes in LPS mm: ``lateral`` (towards the knee's
lateral side), ``anterior`` and ``proximal``.  Named axes, not x/y/z, because a left knee is the
mirror image of a right one: the same named frame is right-handed in one and left-handed in the
other, and every angle below is defined from the names, so it means the same on both sides.

- :func:`coarse_axes` - the knee's anterior, superior and patient-right directions from where its
  bones lie (femur above tibia, patella in front), whatever the image's own axes;
- :func:`femur_frame` - flexion axis through the centres of spheres fitted to the posterior
  condyles (the geometric centre axis), origin midway between them, and a long axis;
- :func:`tibia_frame` - medial-lateral axis through the centres of the two plateaus, origin
  between them, and a long axis;
- :func:`patella_frame` - centroid, the normal of the patella's plate, and the femur's lateral direction;
- :func:`grood_suntay` - flexion, varus and internal rotation of the tibia on the femur.

The long axes come from the anatomy template registered to the bone (``long_axis``, see
:mod:`.attachments`): an image's field of view shows 35-80 mm of each shaft, still in the
metaphysis, whose flare tilts the line through its cross-section centres by tens of degrees (on 39
OAI maps the flexion read that way ran from -23 to +26 deg and moved 2-20 deg between two visits of
one knee; through the template, -20 to +1 deg and 0-4.9 deg between visits).
The shaft's cross-section centres remain where no template axis is given.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kneemesh_core.errors import KneeMeshError


def _unit(v: np.ndarray) -> np.ndarray:
    n = float(np.linalg.norm(v))
    if n < 1e-9:
        raise KneeMeshError("frame_degenerate", "a knee axis has no direction: the bones overlap or are missing.")
    return np.asarray(v, float) / n


@dataclass(frozen=True)
class CoarseAxes:
    """The knee's own directions in LPS: unit ``anterior``, ``superior`` and ``right`` (the
    patient's right: anterior x superior, so the triple is a proper rotation of LPS's A, S, R),
    and a ``centre`` (mm) between femur and tibia."""

    centre: np.ndarray
    anterior: np.ndarray
    superior: np.ndarray
    right: np.ndarray

    def lateral(self, side: str) -> np.ndarray:
        """The lateral direction of a ``side`` knee: the patient's right in a right knee."""
        return self.right if side == "right" else -self.right

    def basis(self) -> np.ndarray:
        """(3, 3) proper rotation whose columns are anterior, superior, right."""
        return np.stack([self.anterior, self.superior, self.right], axis=1)


def coarse_axes(femur: np.ndarray, tibia: np.ndarray, patella: np.ndarray | None) -> CoarseAxes:
    """The knee's directions from its bones' points (N, 3) in LPS mm.

    Superior runs from the tibia's centroid to the femur's; anterior is where the patella lies
    off that line (without a patella: LPS anterior, -y, as in a scanner frame).  A scan in any
    orientation, or a label map in a frame of its own, gives the same anatomical axes.
    """
    cf, ct = femur.mean(0), tibia.mean(0)
    superior = _unit(cf - ct)
    centre = 0.5 * (cf + ct)
    toward = (patella.mean(0) - centre) if patella is not None and len(patella) else np.array([0.0, -1.0, 0.0])
    anterior = _unit(toward - (toward @ superior) * superior)
    return CoarseAxes(centre, anterior, superior, np.cross(anterior, superior))


@dataclass(frozen=True)
class Frame:
    """Origin (mm) and named unit axes of one bone, LPS."""

    origin: np.ndarray
    lateral: np.ndarray
    anterior: np.ndarray
    proximal: np.ndarray
    facts: dict

    def to_dict(self) -> dict:
        return {"origin_mm": _r(self.origin, 3),
                "axes": {"lateral": _r(self.lateral, 5), "anterior": _r(self.anterior, 5), "proximal": _r(self.proximal, 5)},
                **self.facts}


def _r(v: np.ndarray, n: int) -> list[float]:
    return [round(float(x), n) for x in v]


def _named(origin: np.ndarray, lateral: np.ndarray, proximal: np.ndarray, anterior_hint: np.ndarray, facts: dict) -> Frame:
    """A frame from a lateral axis and a proximal direction (made perpendicular to it)."""
    lateral = _unit(lateral)
    proximal = _unit(proximal - (proximal @ lateral) * lateral)
    anterior = np.cross(proximal, lateral)
    anterior = anterior if anterior @ anterior_hint >= 0 else -anterior
    return Frame(np.asarray(origin, float), lateral, anterior, proximal, facts)


def _sphere(points: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Least-squares sphere through points (N, 3): centre, radius, RMS residual (mm)."""
    a = np.hstack([2.0 * points, np.ones((len(points), 1))])
    b = (points ** 2).sum(1)
    sol, *_ = np.linalg.lstsq(a, b, rcond=None)
    centre = sol[:3]
    radius = float(np.sqrt(max(sol[3] + centre @ centre, 0.0)))
    resid = np.linalg.norm(points - centre, axis=1) - radius
    return centre, radius, float(np.sqrt((resid ** 2).mean()))


def _shaft_axis(points: np.ndarray, hint: np.ndarray, slab_mm: float = 5.0) -> np.ndarray | None:
    """The line through the centres of a shaft's cross-sections (surface points (N, 3) cut into
    slabs ``slab_mm`` thick along ``hint``), oriented along ``hint``; None where the field of view
    shows fewer than three slabs (15 mm) of it."""
    if len(points) < 60:
        return None
    h = points @ hint
    edges = np.arange(h.min(), h.max() + slab_mm, slab_mm)
    centres = [points[(h >= a) & (h < b)].mean(0) for a, b in zip(edges[:-1], edges[1:])
               if ((h >= a) & (h < b)).sum() >= 20]
    if len(centres) < 3:
        return None
    c = np.asarray(centres) - np.mean(centres, 0)
    axis = np.linalg.eigh(c.T @ c)[1][:, -1]
    if abs(axis @ hint) < np.cos(np.radians(30)):
        return None
    return axis if axis @ hint > 0 else -axis


def femur_frame(femur: np.ndarray, axes: CoarseAxes, side: str, long_axis: tuple[np.ndarray, str] | None = None) -> Frame:
    """Femoral frame from the femur's surface points (N, 3), LPS mm.

    The flexion axis runs through the centres of spheres fitted to the posterior parts of the
    two condyles (distal 35 mm, behind the condyles' middle); the origin lies midway; the long
    axis is ``long_axis`` (a unit vector (3,) towards the hip and where it comes from), else the
    line through the centres of the femur's cross-sections from 25 mm above the origin, where the
    field of view shows 15 mm or more of it, else the knee's superior direction.
    """
    lateral_dir = axes.lateral(side)
    rel = femur - axes.centre
    s, a, l = rel @ axes.superior, rel @ axes.anterior, rel @ lateral_dir
    distal = s < s.min() + 35.0
    notch = np.median(l[distal])
    back = distal & (a < np.median(a[distal]))
    centres, facts = {}, {}
    for name, sel in (("medial", back & (l < notch)), ("lateral", back & (l >= notch))):
        if sel.sum() < 30:
            raise KneeMeshError("frame_failed", f"femur: too few points on the posterior {name} condyle to fit it.")
        c, radius, rms = _sphere(femur[sel])
        centres[name] = c
        facts[f"{name}_condyle_radius_mm"] = round(radius, 2)
        facts[f"{name}_condyle_fit_rms_mm"] = round(rms, 3)
    origin = 0.5 * (centres["medial"] + centres["lateral"])
    lateral = centres["lateral"] - centres["medial"]
    facts["flexion_axis"] = "through the posterior condyle sphere centres"
    proximal, facts["long_axis"] = long_axis or _shaft_or_superior(
        femur[(femur - origin) @ axes.superior > 25.0], axes.superior, "from 25 mm above the origin")
    return _named(origin, lateral, proximal, axes.anterior, facts)


def _shaft_or_superior(shaft_points: np.ndarray, superior: np.ndarray, where: str) -> tuple[np.ndarray, str]:
    """A long axis towards ``superior`` through a shaft's cross-section centres, else ``superior``."""
    shaft = _shaft_axis(shaft_points, superior)
    if shaft is None:
        return superior, "knee superior (shaft too short in view)"
    return shaft, f"through the shaft's cross-section centres {where}"


def tibia_frame(tibia: np.ndarray, axes: CoarseAxes, side: str, plates: tuple[np.ndarray, np.ndarray] | None = None,
                long_axis: tuple[np.ndarray, str] | None = None) -> Frame:
    """Tibial frame from the tibia's surface points (N, 3), LPS mm.

    ``plates``: points of the medial and lateral tibial cartilage (their centroids are the
    plateau centres); without them, the two halves of the tibia's top 20 mm either side of its
    principal axis across the knee.  The medial-lateral axis joins the plateau centres, the
    origin lies midway; the long axis is ``long_axis`` (a unit vector (3,), proximal, and where it
    comes from), else the line through the centres of the tibia's cross-sections from 25 mm
    below the plateau (else the knee's superior direction).
    """
    lateral_dir = axes.lateral(side)
    top = (tibia - axes.centre) @ axes.superior
    if plates is not None and len(plates[0]) and len(plates[1]):
        medial_c, lateral_c = plates[0].mean(0), plates[1].mean(0)
        source = "tibial cartilage plates"
    else:  # the plateau is wider than deep: its principal axis across the knee, halves either side
        cap = tibia[top > top.max() - 20.0]
        flat = (cap - cap.mean(0)) - np.outer((cap - cap.mean(0)) @ axes.superior, axes.superior)
        w, v = np.linalg.eigh(flat.T @ flat)
        across = v[:, -1] if v[:, -1] @ lateral_dir > 0 else -v[:, -1]
        l = flat @ across
        medial_c, lateral_c = cap.mean(0) - across * abs(l[l < 0].mean()), cap.mean(0) + across * l[l >= 0].mean()
        source = "the principal axis of the tibia's top 20 mm"
    origin = 0.5 * (medial_c + lateral_c)
    proximal, how = long_axis or _shaft_or_superior(tibia[(tibia - origin) @ axes.superior < -25.0], axes.superior,
                                                   "from 25 mm below the plateau")
    return _named(origin, lateral_c - medial_c, proximal, axes.anterior, {"plateau_centres": source, "long_axis": how})


def patella_frame(patella: np.ndarray, axes: CoarseAxes, side: str, femur: Frame | None = None) -> Frame:
    """Patellar frame: the centroid; anterior along the patella's thinnest principal axis (the
    normal of its plate, towards the front); lateral the femur's (else the knee's) lateral
    direction made perpendicular to it; proximal completing the frame."""
    c = patella - patella.mean(0)
    w, v = np.linalg.eigh(c.T @ c)
    normal = v[:, 0] if v[:, 0] @ axes.anterior >= 0 else -v[:, 0]
    lateral = femur.lateral if femur is not None else axes.lateral(side)
    lateral = _unit(lateral - (lateral @ normal) * normal)
    proximal = np.cross(lateral, normal)
    proximal = proximal if proximal @ axes.superior >= 0 else -proximal
    return Frame(patella.mean(0), lateral, normal, proximal, {"anterior_axis": "the patella's thinnest principal axis"})


def grood_suntay(femur: Frame, tibia: Frame) -> dict:
    """Grood-Suntay angles of the tibia on the femur, deg (Grood & Suntay 1983): the flexion axis
    is the femur's lateral axis, the long-rotation axis the tibia's proximal axis, the floating axis
    perpendicular to both.  Positive: flexion (the tibia swings posteriorly), varus (the tibia's
    distal end towards the midline), internal rotation (the tibia's anterior towards medial)."""
    t = tibia.proximal
    # flexion: the tibia's long axis, seen along the flexion axis, against the femur's
    t_sag = t - (t @ femur.lateral) * femur.lateral
    flexion = np.degrees(np.arctan2(t_sag @ femur.anterior, t_sag @ femur.proximal))
    # varus-valgus: how far the tibia's long axis leans towards the femur's lateral side
    varus = np.degrees(np.arcsin(np.clip(t @ femur.lateral, -1.0, 1.0)))
    # rotation about the tibia's long axis: the femur's anterior against the tibia's
    f_ant = femur.anterior - (femur.anterior @ t) * t
    medial = -(tibia.lateral - (tibia.lateral @ t) * t)
    internal = np.degrees(np.arctan2(-(f_ant @ medial), f_ant @ tibia.anterior))
    return {"flexion": round(float(flexion), 2), "varus": round(float(varus), 2),
            "internal_rotation": round(float(internal), 2)}

"""Every ligament and tendon fibre end of the template on the subject's bones, with the knee's frames.

For each bone the template is registered onto the job's bone mesh (:mod:`.register`); each fibre
end goes through its bone's registration and onto the subject's bone surface: its position is
the nearest point of the surface, its ``node`` the nearest vertex of ``meshes/<bone>.vtp``.  Ends
that Lenhart's model puts on the fibula (LCL, popliteofibular ligament) move with the tibia and
stay on the registered template fibula (the job meshes no fibula): their ``node`` is null.

Slack lengths come from each fibre's **reference strain**: Lenhart's model states each fibre's
strain in its reference pose, full extension (``ReferenceStrain`` in its SIMM file), and the
subject's fibre is given that strain in the same pose, ``L0 = L / (1 + e_ref)`` along the straight
line between its ends (the calibration of Lenhart 2015 and OpenSim JAM), plus, for the ITB, the part
of its path beyond the knee (``path_beyond_mm``: to the pelvis, scaled with the femur), which the
knee's motion leaves unchanged but which sets how much strain a millimetre of it is.  Scaling the
template's slack length with the bones instead left a knee whose patella sits higher than the
template's with its patellar tendon 30-40 % stretched in the image pose (OAI 9357383: the seated
patella was pulled 14 mm down and off the trochlea).

The image is not that pose: OAI's knees lie in a coil at 4.5-24.7 deg of anatomical flexion (the
126 real maps, median 13: ``angles_deg``), where a fibre between femur and tibia is shorter or
longer than in extension by up to a few millimetres, a strain of several per cent on a 30 mm
ligament.  Given the image pose's reference strains, the sample knee (24 deg flexed in its image)
brought to extension under 1 kN carried 3.5 kN through its plateau, its collaterals and posterior
capsule at 300-960 N; given them in extension, 1.06 kN.  So
the **tibiofemoral fibres** (femur to tibia or fibula) are measured with the tibia at the knee's
anatomical extension (:func:`extension_motion`: the image pose's flexion taken out about the
femur's flexion axis, varus and rotation kept, the tibia moved along its axis to the cartilage
clearance it has in the image); the patellar fibres (patellar tendon, patellofemoral ligaments)
keep the image pose, since where the patella sits in extension is what the quadriceps decides.  A
fibre with an unplaced end keeps the scaled template slack length.

A registration whose residual is implausible (the bone is not what the template expects: a
cropped or broken segmentation, a foreign object) is reported, and its sites are flagged.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import pyvista as pv
from scipy.spatial import cKDTree

from kneemesh_core.anatomy import template as tmpl
from kneemesh_core.anatomy.frames import Frame, coarse_axes, femur_frame, grood_suntay, patella_frame, tibia_frame
from kneemesh_core.anatomy.register import Registration, register, shape_verdict
from kneemesh_core.geometry import evenly_spread
from kneemesh_core.surfaces.distance import SurfaceDistance

#: A registration residual (trimmed RMS, mm) above this is implausible for a bone of a knee: on the
#: 126 real maps here and their mirror images the largest were femur 1.3, tibia 1.6, patella 1.8 mm
#: (99th percentiles 1.2, 1.5, 1.7); these leave about 40 % of room above them.
MAX_PLAUSIBLE_RMS_MM = {"femur": 1.8, "tibia": 2.2, "patella": 2.5}
#: Where each bone's long axis comes from when its registration is plausible (else the shaft in view,
#: :mod:`.frames`): the template's (:data:`~.template.LONG_AXES`), so the flexion of two knees means the same.
LONG_AXIS_SOURCE = {"femur": "the registered template's distal anterior femoral cortex",
                    "tibia": "the registered template's (Lenhart 2015 tibial frame)"}
#: The spacing (mm) of the points the registrations and frames fit (:func:`~kneemesh_core.geometry.evenly_spread`):
#: the 3 mm of the even shells they were built on (a shell is 1 mm under its cartilage now).  The image pose's
#: flexion moves with the sampling by a few degrees (OAI 9031930_00m: -8 to -13 deg over 2-3 mm samplings of
#: one shell): the registration of a template tibia to the few centimetres of shaft in view is that loose.
FIT_SPACING_MM = 3.0
#: At most this many points of each tibial plate measure its clearance from the femur (:func:`extension_motion`).
CLEARANCE_POINTS = 4000


@dataclass
class Anatomy:
    """What :func:`place` found: the JSON document and what the report needs."""

    document: dict  # attachments.json
    report: dict  # the report's anatomy entry
    frames: dict[str, Frame]
    bones: dict[str, pv.PolyData]


def place(bones: dict[str, pv.PolyData], side: str, plates: tuple[np.ndarray, np.ndarray] | None = None) -> Anatomy:
    """Frames, angles and attachment sites of a knee.

    Parameters
    ----------
    bones : the job's bone meshes (``femur``, ``tibia``, ``patella``; LPS mm); a missing bone leaves
        its sites unplaced, with the reason.
    side : ``left`` or ``right`` (left knees take the mirrored template).
    plates : points (N, 3) of the medial and lateral tibial cartilage, for the plateau centres.
    """
    t0 = time.perf_counter()
    template = tmpl.load()
    vertices = {b: np.asarray(m.points, float) for b, m in bones.items() if m is not None and m.n_points}
    # the registrations and frames fit the surfaces evenly: a shell is finer under its cartilage
    pts = {b: evenly_spread(vertices[b], bones[b].regular_faces, FIT_SPACING_MM) for b in vertices}
    unplaced_bones = {b: f"no {b} mesh" for b in tmpl.BONES if b not in pts}
    if "femur" not in pts or "tibia" not in pts:
        return Anatomy({}, {"status": "failed", "reason": "the femur and the tibia are both needed for the knee's frames",
                            "code": "bone_missing"}, {}, bones)
    mirrored = side == "left"
    regs, frames, shape = _register(template, pts, side, plates)
    trees = {b: cKDTree(v) for b, v in vertices.items()}  # a site's node: the nearest vertex of the shell
    femur_scale = regs["femur"].similarity.scale if "femur" in regs else 1.0  # hip to knee scales with the femur
    unplaced: list[dict] = []
    angles = grood_suntay(frames["femur"], frames["tibia"])
    extension = extension_motion(frames["femur"], frames["tibia"], bones["femur"],
                                 _clearance_points(plates, vertices["tibia"]))
    fibres = [_fibre(fibre, regs, bones, trees, femur_scale, extension, unplaced_bones, unplaced)
              for fibre in template.fibres]
    residuals = {b: round(r.rms_mm, 3) for b, r in regs.items()}
    violations = rule_violations(fibres, frames)
    reasons = _reasons(residuals, unplaced_bones, unplaced, shape, side, violations)
    document = {
        "template": {**template.source, "mirrored_for_left_knee": mirrored},
        "side": side,
        "frames": {b: f.to_dict() for b, f in frames.items()},
        "angles_deg": angles,
        "extension": extension.facts,
        "residuals_mm": residuals,
        "registration": {b: r.facts() for b, r in regs.items()},
        "shape_side": shape,
        "fibres": fibres,
        "unplaced": unplaced,
    }
    report = {"status": "review" if reasons else "ok", "reasons": reasons, "residuals_mm": residuals,
              "site_rule_violations": violations,
              "angles_deg": angles, "fibres": len(fibres),
              "sites_placed": sum(e["lps_mm"] is not None for f in fibres for e in f["ends"]),
              "unplaced": unplaced, "shape_side": shape, "seconds": round(time.perf_counter() - t0, 3)}
    return Anatomy(document, report, frames, bones)


@dataclass(frozen=True)
class Motion:
    """A rigid motion ``x -> rotation @ x + shift`` (LPS mm) and what it is, for ``attachments.json``."""

    rotation: np.ndarray  # (3, 3)
    shift: np.ndarray  # (3,) mm
    facts: dict

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Points (..., 3), LPS mm, moved."""
        return np.asarray(points, float) @ self.rotation.T + self.shift


def extension_motion(femur: Frame, tibia: Frame, femur_mesh: pv.PolyData, plates: list[np.ndarray]) -> Motion:
    """The motion that takes the tibia from the image pose to the knee's anatomical extension.

    The tibia turns about the femur's flexion axis (``femur.lateral`` through ``femur.origin``) by
    the image pose's Grood-Suntay flexion, back to 0 (varus and rotation as in the image), then
    moves along its own turned long axis until its cartilage has the clearance from the femur's bone
    it has in the image: the plate that lost most keeps its image clearance, the other at least its
    own.  The condyles are not circles about the flexion axis (their distal radius is the larger), so
    the turn alone drives the plateau some millimetres into the femur, or lifts it off.

    Parameters
    ----------
    femur, tibia : the bones' frames in the image pose.
    femur_mesh : the femur's closed surface (LPS mm), for signed distances (negative inside).
    plates : points (N_i, 3), LPS mm, of each group whose clearance counts (each tibial plate's cartilage).
    """
    theta = np.radians(grood_suntay(femur, tibia)["flexion"])
    lat, ant, prox = femur.lateral, femur.anterior, femur.proximal
    # in the femur's sagittal plane, the angle from its proximal axis towards its anterior one falls by
    # theta (Grood-Suntay's flexion, so a left knee's left-handed frame turns the same anatomical way)
    rotation = (np.outer(lat, lat) + np.cos(theta) * (np.outer(prox, prox) + np.outer(ant, ant))
                + np.sin(theta) * (np.outer(prox, ant) - np.outer(ant, prox)))
    turned = femur.origin - rotation @ femur.origin
    axis = rotation @ tibia.proximal
    femur_distance = SurfaceDistance(femur_mesh)

    def clearance(rot: np.ndarray, shift: np.ndarray) -> np.ndarray:
        """Each group's least signed distance (mm) from the femur's bone, the tibia moved."""
        return np.array([float(np.min(femur_distance.signed(p @ rot.T + shift))) for p in plates])

    image = clearance(np.eye(3), np.zeros(3))
    drop = 0.0
    for _ in range(3):  # a move along the axis changes a plate's clearance by about as much: a few fixed-point steps
        drop += float(np.max(image - clearance(rotation, turned - drop * axis)))
    shift = turned - drop * axis
    facts = {"flexion_removed_deg": round(float(np.degrees(theta)), 2), "tibia_moved_distally_mm": round(drop, 2),
             "clearance_mm": [round(float(c), 2) for c in image],
             "how": "tibia turned about the femur's flexion axis to 0 deg of flexion, then along its axis to its "
                    "cartilage's image clearance from the femur"}
    return Motion(rotation, shift, facts)


def _clearance_points(plates: tuple[np.ndarray, np.ndarray] | None, tibia: np.ndarray) -> list[np.ndarray]:
    """The point groups whose clearance from the femur :func:`extension_motion` keeps: each tibial plate's
    cartilage (at most :data:`CLEARANCE_POINTS` of each, evenly strided), else the tibia's surface."""
    groups = [p for p in (plates or ()) if len(p)] or [tibia]
    return [np.asarray(p, float)[::max(1, len(p) // CLEARANCE_POINTS)] for p in groups]


def _register(template, pts: dict[str, np.ndarray], side: str, plates) -> tuple[dict, dict, dict]:
    """The template registered to each bone (points (N, 3), LPS mm), the knee's frames, and the shape
    check: the mirror image of the template fitted to the same bones, so a proper rotation that cannot
    turn a left bone into a right one tells the side."""
    axes = coarse_axes(pts["femur"], pts["tibia"], pts.get("patella"))
    mirrored = side == "left"
    regs: dict[str, Registration] = {b: register(b, template.points(b), pts[b], axes, mirrored) for b in pts}
    long = {b: (regs[b].direction(tmpl.LONG_AXES[b]), LONG_AXIS_SOURCE[b]) for b in ("femur", "tibia")
            if regs[b].rms_mm <= MAX_PLAUSIBLE_RMS_MM[b]}
    frames = {"femur": femur_frame(pts["femur"], axes, side, long.get("femur")),
              "tibia": tibia_frame(pts["tibia"], axes, side, plates, long.get("tibia"))}
    if "patella" in pts:
        frames["patella"] = patella_frame(pts["patella"], axes, side, frames["femur"])
    fit = sum(regs[b].rms_similarity_mm for b in ("tibia", "femur"))
    mirror = sum(register(b, template.points(b), pts[b], axes, not mirrored, refine=False).rms_mm
                 for b in ("tibia", "femur"))
    return regs, frames, shape_verdict(*((mirror, fit) if mirrored else (fit, mirror)))


def _fibre(fibre, regs: dict, bones: dict[str, pv.PolyData], trees: dict, femur_scale: float, extension: Motion,
           unplaced_bones: dict[str, str], unplaced: list[dict]) -> dict:
    """One fibre of the template on the subject's bones: each end mapped by its bone's registration and
    put on the bone's surface (the fibular ends move with the tibia), its slack length giving the
    subject's fibre the template's reference strain in extension (a tibiofemoral fibre: its tibial
    end moved by ``extension``; see the module's notes); an end on a missing bone is listed in ``unplaced``."""
    ends = []
    for end in fibre.ends:
        if end.bone not in regs:
            unplaced.append({"fibre": fibre.name, "bone": end.bone, "reason": unplaced_bones[end.bone]})
            ends.append({"bone": end.bone, "node": None, "lps_mm": None})
            continue
        mapped = regs[end.bone].place(end.point[None])[0]
        entry = {"bone": end.bone}
        if end.surface == "fibula":
            entry.update(node=None, lps_mm=_round(mapped), on="fibula (template, moved with the tibia)")
        else:
            _, closest = bones[end.bone].find_closest_cell(mapped[None], return_closest_point=True)
            entry.update(node=int(trees[end.bone].query(closest[0])[1]), lps_mm=_round(closest[0]),
                         snapped_mm=round(float(np.linalg.norm(closest[0] - mapped)), 3))
        ends.append(entry)
    strain = fibre.reference_strain
    beyond = fibre.path_beyond_mm * femur_scale
    item = {"name": fibre.name, "bundle": fibre.bundle, "stiffness_n": fibre.stiffness_n,
            "template_slack_length_mm": fibre.slack_length_mm, "reference_strain": round(strain, 4), "ends": ends}
    if all(e["lps_mm"] is not None for e in ends):
        points = {e["bone"]: np.asarray(e["lps_mm"], float) for e in ends}
        length = float(np.linalg.norm(np.subtract(ends[0]["lps_mm"], ends[1]["lps_mm"]))) + beyond
        item["length_mm"] = round(length, 3)
        if set(points) == {"femur", "tibia"}:
            length = float(np.linalg.norm(points["femur"] - extension.apply(points["tibia"]))) + beyond
            item["extension_length_mm"] = round(length, 3)
        item["slack_length_mm"] = round(length / (1.0 + strain), 3)
    else:
        scales = [regs[e.bone].similarity.scale for e in fibre.ends if e.bone in regs]
        item["slack_length_mm"] = round(fibre.slack_length_mm * float(np.mean(scales or [1.0])), 3)
    if beyond:
        item["path_beyond_mm"] = round(beyond, 3)
    if fibre.note:
        item["note"] = fibre.note
    return item


def _reasons(residuals: dict[str, float], unplaced_bones: dict[str, str], unplaced: list[dict], shape: dict, side: str,
             violations: list[str]) -> list[str]:
    """Why the anatomy is ``review``: implausible residuals, sites not placed, a shape that fits the other
    side better, sites off their anatomy."""
    reasons = [f"{b} registration residual {r} mm is implausible (> {MAX_PLAUSIBLE_RMS_MM[b]} mm): "
               "its sites are unreliable" for b, r in residuals.items() if r > MAX_PLAUSIBLE_RMS_MM[b]]
    for bone, why in unplaced_bones.items():
        n = sum(u["bone"] == bone for u in unplaced)
        reasons.append(f"{n} sites on the {bone} not placed: {why}")
    if shape.get("side") and shape["side"] != side:
        reasons.append(f"the bones' shape fits a {shape['side']} knee better (residuals right {shape['rms_right_mm']} mm, "
                       f"left {shape['rms_left_mm']} mm) than the {side} knee this job was given")
    return reasons + [f"site off its anatomy: {v}" for v in violations]


def _round(p: np.ndarray) -> list[float]:
    return [round(float(x), 3) for x in p]


def _local(frame: Frame, p) -> dict[str, float]:
    v = np.asarray(p, float) - frame.origin
    return {"lateral": float(v @ frame.lateral), "anterior": float(v @ frame.anterior), "proximal": float(v @ frame.proximal)}


def rule_violations(fibres: list[dict], frames: dict[str, Frame]) -> list[str]:
    """Where placed sites break what anatomy says, in the knee's own frames (so for either side):
    MCL ends medial, LCL and popliteofibular ends lateral, the patellar tendon from the patella's
    distal half to the tibial tuberosity (anterior, below the plateau), ACL femoral ends on the
    lateral condyle's notch wall and PCL ones on the medial's, femoral ends above tibial ones.
    Each violation names the fibre and the coordinate (mm) that breaks the rule."""
    out = []
    for f in fibres:
        ends = {e["bone"]: e["lps_mm"] for e in f["ends"] if e["lps_mm"] is not None}
        loc = {b: _local(frames[b], p) for b, p in ends.items() if b in frames}
        rules = []
        b = f["bundle"]
        if b in ("MCLs", "MCLd", "MCLp"):
            rules += [("femur", "lateral", "<", -15.0), ("tibia", "lateral", "<", -10.0)]
        if b in ("LCL", "PFL"):
            rules += [("femur", "lateral", ">", 15.0), ("tibia", "lateral", ">", 15.0)]
        if b == "PT":
            rules += [("patella", "proximal", "<", 0.0), ("tibia", "anterior", ">", 15.0), ("tibia", "proximal", "<", -10.0)]
        if b in ("ACLam", "ACLpl"):
            rules += [("femur", "lateral", ">", 0.0), ("femur", "lateral", "<", 22.0)]
        if b in ("PCLal", "PCLpm"):
            rules += [("femur", "lateral", "<", 0.0), ("femur", "lateral", ">", -22.0)]
        for bone, axis, op, limit in rules:
            if bone in loc:
                v = loc[bone][axis]
                if not (v < limit if op == "<" else v > limit):
                    out.append(f"{f['name']} {bone} end at {axis} {v:.1f} mm (expected {op} {limit:g})")
        if "femur" in ends and "tibia" in ends and "tibia" in frames:
            above = float((np.asarray(ends["femur"]) - ends["tibia"]) @ frames["tibia"].proximal)
            if above <= 0:
                out.append(f"{f['name']} femoral end {-above:.1f} mm below its tibial end")
    return out

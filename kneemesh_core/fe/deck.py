"""The decks of a knee: one shared include, ``knee_model.inp``, and a thin wrapper per solver,
``knee_ccx.inp`` (:mod:`.calculix`) and ``knee_abaqus.inp`` (:mod:`.abaqus`), plus ``model.json``, what
reading the results needs (``../shared/docs/fe-calculix-reference.md``, section 5: what must differ
between Abaqus/Explicit and CalculiX, and why).

``knee_model.inp`` (both dialects): nodes, the cartilage (a rigid cartilage's contact skin of C3D6 wedges,
:mod:`.contact_skin`; deformable cartilage's C3D8 hexahedra), named node and element sets, element-face
surfaces (articular S2, bone side S1), the ligament springs (SPRINGA, Blankevoort), the contact
interactions (linear pressure-overclosure, K stated), amplitudes.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from kneemesh_core import __version__
from kneemesh_core.fe import abaqus, calculix, inp
from kneemesh_core.fe.inp import PER_LINE, set_lines
from kneemesh_core.fe.model import PAIRS, Model, deck_rotation, deck_to_lps
from kneemesh_core.fe.pressure_map import slave_surface
from kneemesh_core.fe.physics import (CARTILAGE_DENSITY_T_MM3, CARTILAGE_ELEMENT, CARTILAGE_MODULUS_MPA, CARTILAGE_POISSON,
                                      CONFINED_MODULUS_MPA, DEFORMABLE_PENALTY, QUADRICEPS_SLACK_MM, TRANSITION_STRAIN,
                                      legs, ligament_table, neo_hooke, quadriceps_table, spring_stiffness)
from kneemesh_core.io.files import atomic_write_text
from kneemesh_core.tissues import BONES, CARTILAGES

MODEL_FILE, CCX_FILE, ABAQUS_FILE, META_FILE = "knee_model.inp", "knee_ccx.inp", "knee_abaqus.inp", "model.json"


def shared(m: Model) -> str:
    """``knee_model.inp``."""
    lc = m.load
    w: list[str] = [
        f"** KneeMesh {__version__}: knee model shared by knee_ccx.inp and knee_abaqus.inp",
        "** units: mm, N, MPa, s. Frame: origin at the femoral flexion axis's middle; X the flexion axis towards the",
        "** patient's right, Y anterior, Z superior. LPS of the deck frame:",
        f"**   origin {m.frame['origin_lps_mm']}",
        *(f"**   {k} {v}" for k, v in m.frame["axes_lps"].items()),
        f"** {m.side} knee; cartilage {lc.cartilage}"
        + (" (the articular layer's contact skin, rigid with the bone)" if lc.cartilage == "rigid" else
           f" ({CARTILAGE_ELEMENT} hexahedra, neo-Hookean; their bone-side nodes ride on the bone)"),
        "*NODE",
    ]
    w += [f"{i}, {p[0]:.6f}, {p[1]:.6f}, {p[2]:.6f}" for i, p in m.nodes.items()]
    for part in m.parts.values():
        w.append(f"*ELEMENT, TYPE={part.element_type}, ELSET={part.name.upper()}")
        w += [f"{e}, " + ", ".join(str(int(n)) for n in c) for e, c in zip(part.elements, part.connectivity)]
    w.append("*ELEMENT, TYPE=SPRINGA, ELSET=LIGAMENTS")
    w += [f"{s.element}, {s.nodes[0]}, {s.nodes[1]}" for s in m.springs]
    q = m.quadriceps
    if q is not None:
        w += ["*ELEMENT, TYPE=SPRINGA, ELSET=QUADRICEPS", f"{q.element}, {q.nodes[0]}, {q.nodes[1]}"]
    for bone in m.bone_nodes:
        w += set_lines("NSET", f"{bone.upper()}_BONE", m.bone_nodes[bone])
    for body, nodes in m.body_nodes.items():
        w += set_lines("NSET", f"{body.upper()}_BODY", sorted(set(nodes)))
    w += set_lines("NSET", "REFS", [m.ref[b] for b in BONES if b in m.ref])
    w += set_lines("NSET", "LIGAMENT_ENDS", sorted({n for s in [*m.springs, *([q] if q else [])] for n in s.nodes}
                                                   | set(m.anchors.values())))
    for part in m.parts.values():
        name = part.name.upper()
        w += set_lines("ELSET", f"{name}_ART", part.articular) + set_lines("ELSET", f"{name}_DEEP", part.bone_side)
        w += [f"*SURFACE, NAME={name}_ARTICULAR, TYPE=ELEMENT", f"{name}_ART, S2",
              f"*SURFACE, NAME={name}_BONE_SIDE, TYPE=ELEMENT", f"{name}_DEEP, S1"]
    for name, members in m.surfaces.items():
        w += [f"*SURFACE, NAME={name.upper()}_ARTICULAR, TYPE=ELEMENT", *(f"{p.upper()}_ART, S2" for p in members)]
    for s in m.springs:
        w += [f"*ELSET, ELSET=LIG_{s.name}", str(s.element)]
    bundles: dict[str, list[str]] = {}
    for s in m.springs:
        bundles.setdefault(s.bundle, []).append(f"LIG_{s.name}")
    for bundle, names in bundles.items():
        w += [f"*ELSET, ELSET=BUNDLE_{bundle}", *(", ".join(names[k:k + PER_LINE]) for k in range(0, len(names), PER_LINE))]
    w += ["*MATERIAL, NAME=CARTILAGE", *cartilage_law(lc.cartilage), "*DENSITY", f"{CARTILAGE_DENSITY_T_MM3!r}"]
    for part in m.parts.values():
        w.append(f"*SOLID SECTION, ELSET={part.name.upper()}, MATERIAL=CARTILAGE")
    w.append(f"** ligaments: Blankevoort 1991 (e = L/L0 - 1, e_t = {TRANSITION_STRAIN:g}), force (N) against elongation from the "
             "initial length (mm)")
    for s in m.springs:
        w += [f"** {s.name}: k {s.stiffness_n:g} N/strain, slack length {s.slack_length_mm:.3f} mm, "
              f"initial length {s.length_mm:.3f} mm" + (f" ({s.beyond_mm:.3f} mm of it beyond its nodes)" if s.beyond_mm else ""),
              f"*SPRING, ELSET=LIG_{s.name}, NONLINEAR", ""]
        w += [f"{f:.6e}, {d:.6e}" for f, d in ligament_table(s.stiffness_n, s.slack_length_mm, s.length_mm)]
    if q is not None:
        w += [f"** quadriceps (patella to the femoral shaft): {m.load.quadriceps_n:g} N at its initial length, +1 N/mm as it "
              f"lengthens, slack {QUADRICEPS_SLACK_MM:g} mm shorter", "*SPRING, ELSET=QUADRICEPS, NONLINEAR", ""]
        w += [f"{f:.6e}, {d:.6e}" for f, d in quadriceps_table(m.load.quadriceps_n, q.length_mm)]
    w += [f"** contact: a thin elastic layer on bone, M = (1 - nu) E / ((1 + nu)(1 - 2 nu)), E {CARTILAGE_MODULUS_MPA:g} MPa, "
          f"nu {CARTILAGE_POISSON:g}"]
    for name, (slave, master) in m.pairs.items():
        k = m.contact_k[name]
        if name in PAIRS:  # K from the two cartilages the pair stands for
            a, b = PAIRS[name]
            times = f"{DEFORMABLE_PENALTY:g} x " if lc.cartilage == "deformable" else ""
            why = (f"K = {times}M / (h_{a} + h_{b}) = {times}{CONFINED_MODULUS_MPA:.2f} MPa / ({m.parts[a].thickness_mm:.3f} + "
                   f"{m.parts[b].thickness_mm:.3f} mm)"
                   + (" (a penalty between deforming layers: they carry the compliance)" if times else "")
                   + ("; the master also the prefemoral sheet (rigid, with the femur; fe/prefemoral.py)" if master in m.surfaces else ""))
        else:
            why = "meniscus surrogate (rigid, with the tibia): K of its compartment's layers"
        w += [f"** {name}: {why} = {k:.4f} N/mm^3",
              f"*SURFACE INTERACTION, NAME=CONTACT_{name.upper()}", "*SURFACE BEHAVIOR, PRESSURE-OVERCLOSURE=LINEAR", f"{k:.6f}"]
    w += ["*AMPLITUDE, NAME=RAMP", "0.0, 0.0, 1.0, 1.0", "*AMPLITUDE, NAME=HOLD", "0.0, 1.0, 1.0, 1.0"]
    return "\n".join(w) + "\n"


def cartilage_law(cartilage: str) -> list[str]:
    """The cartilage material's lines: linear elastic where it is rigid (the constants behind the contact
    law), neo-Hookean with the same small-strain constants where it deforms (:func:`neo_hooke`)."""
    if cartilage == "rigid":
        return ["*ELASTIC", f"{CARTILAGE_MODULUS_MPA!r}, {CARTILAGE_POISSON!r}"]
    c10, d1 = neo_hooke()
    return [f"** neo-Hookean: E {CARTILAGE_MODULUS_MPA:g} MPa, nu {CARTILAGE_POISSON:g} at small strain (C10 = G / 2, D1 = 2 / K)",
            "*HYPERELASTIC, NEO HOOKE", f"{c10:.6f}, {d1:.6f}"]


def joint_load_line(m: Model) -> dict:
    """Where the joint load acts, in the input's LPS frame: its force (N), a point of its line of action
    at the knee's centre height (mm; ``medial_offset_mm`` medial of the femur's seated reference node),
    and the adduction moment it makes about that node (N m: the whole moment, which lies along the tibia's
    anterior axis, normal to the load and to the medial offset; the femur's anterior axis, deck Y, is the
    image pose's flexion away from it)."""
    direction = deck_rotation(m.frame) @ -m.tibial_axis
    return {"force_n": m.load.joint_load_n, "direction_lps": np.round(direction, 6).tolist(),
            "medial_offset_mm": m.load.medial_offset_mm,
            "through_lps_mm": np.round(deck_to_lps(m.frame, m.nodes[m.ref["femur"]] + m.load.medial_offset_mm * m.medial), 3).tolist(),
            "adduction_moment_nm": round(float(np.linalg.norm(inp.load_moment(m))) / 1000.0, 3)}


def meta(m: Model, flexion_deg: float, start_pose: calculix.StartPose | None = None) -> dict:
    """What reading the results needs: node and element ids, fibres, loads, when the loads are on with the
    bodies free (``loaded_at``, ccx's total time) and the deforming cartilages' element ranges (``model.json``)."""
    femur_nodes = set(m.body_nodes["femur"])
    return {
        "frame": m.frame, "side": m.side, "joint_load_n": m.load.joint_load_n, "loaded_at": calculix.loaded_at(start_pose),
        "start_pose": None if start_pose is None else {b: {"translation_mm": np.round(u, 6).tolist(),
                                                           "rotation_rad": np.round(r, 8).tolist()}
                                                       for b, (u, r) in start_pose.items()},
        "deformable_elements": {p.name: [int(p.elements[0]), int(p.elements[-1])] for p in m.parts.values() if p.deformable},
        "joint_load_direction": (-m.tibial_axis).round(6).tolist(), "quadriceps_n": m.load.quadriceps_n,
        "joint_load": joint_load_line(m),
        "flexion_deg": flexion_deg, "activity": m.load.activity, "peak_load_n": m.load.peak_load_n,
        "joint_load_schedule": load_schedule(m, flexion_deg, start_pose),
        "cartilage": m.load.cartilage, "contact_k": m.contact_k, "seating": m.seating,
        "pairs": {name: f"{slave.upper()}_ARTICULAR" for name, (slave, _) in m.pairs.items()},
        "slave_elements": {name: [int(m.parts[slave].elements[0]), int(m.parts[slave].elements[-1])]
                           for name, (slave, _) in m.pairs.items()},
        "slave_surfaces": {slave: _slave_surface(m, slave) for slave, _ in m.pairs.values() if slave in CARTILAGES},
        "ref": {b: m.ref[b] for b in BONES if b in m.ref}, "rot": calculix.rot_nodes(m),
        "femur_springs_n_mm": spring_stiffness("femur", "translation").tolist(),
        "patella_springs_n_mm": spring_stiffness("patella", "translation", to="femur").tolist(),
        "patella_anchor": m.anchors.get("patella"),
        "quadriceps": None if m.quadriceps is None else {
            "nodes": list(m.quadriceps.nodes), "start": [m.nodes[n].tolist() for n in m.quadriceps.nodes],
            "law": quadriceps_table(m.load.quadriceps_n, m.quadriceps.length_mm)},
        "fibres": [{"name": s.name, "bundle": s.bundle, "k": s.stiffness_n, "slack": s.slack_length_mm, "beyond": s.beyond_mm,
                    "nodes": list(s.nodes), "start": [m.nodes[s.nodes[0]].tolist(), m.nodes[s.nodes[1]].tolist()],
                    "femur_end": 0 if s.nodes[0] in femur_nodes else 1 if s.nodes[1] in femur_nodes else None}
                   for s in m.springs],
    }


def load_schedule(m: Model, flexion_deg: float, start_pose: calculix.StartPose | None = None) -> list[list[float]]:
    """The joint load over ccx's total time, [[time, N], ...]: the load case's from the seating on, then each
    leg's (:func:`kneemesh_core.fe.physics.legs`: one step each, linear in between)."""
    at = calculix.loaded_at(start_pose)
    return [[at, m.load.joint_load_n]] + [[at + k, leg.joint_load_n] for k, leg in enumerate(
        legs(m.load, flexion_deg, m.frame.get("image_flexion_deg")), start=1)]


def _slave_surface(m: Model, tissue: str) -> dict:
    """The articular surface of a slave cartilage for its pressure maps (:func:`pressure_map.slave_surface`)."""
    part = m.parts[tissue]
    faces = part.articular_faces()
    ids = np.unique(faces)
    return slave_surface(deck_to_lps(m.frame, np.stack([m.nodes[int(i)] for i in ids])), np.searchsorted(ids, faces),
                         part.articular)


def write(m: Model, folder: Path, flexion_deg: float | None = None, max_increment_deg: float | None = None,
          include: str | None = None, start_pose: calculix.StartPose | None = None) -> list[Path]:
    """Write the decks into ``folder``; with ``include`` (the path of an existing shared model, from
    ``folder``) only the CalculiX wrapper and ``model.json``, for a run of another flexion beside the
    job's decks; ``start_pose`` where the CalculiX run starts from (:func:`calculix.deck`).  Returns their
    paths."""
    folder.mkdir(parents=True, exist_ok=True)
    flex = m.load.flexion_deg if flexion_deg is None else flexion_deg
    step = m.load.max_increment_deg if max_increment_deg is None else max_increment_deg
    files = {CCX_FILE: calculix.deck(m, flex, step, include or MODEL_FILE, start_pose),
             META_FILE: json.dumps(meta(m, flex, start_pose), indent=1)}
    if include is None:
        files = {MODEL_FILE: shared(m), **files, ABAQUS_FILE: abaqus.deck(m, MODEL_FILE)}
    for name, text in files.items():
        atomic_write_text(folder / name, text)
    return [folder / n for n in files]

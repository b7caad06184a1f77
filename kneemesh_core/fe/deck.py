"""The decks: one shared include and a thin wrapper per solver (``../shared/docs/fe-calculix-reference.md``,
section 5: what must differ between Abaqus/Explicit and CalculiX, and why).

``knee_model.inp`` (both dialects): nodes, C3D8 cartilage, named node and element sets,
element-face surfaces (articular S2, bone side S1), the ligament springs (SPRINGA, Blankevoort),
the contact interactions (linear pressure-overclosure, K stated), amplitudes.
``knee_ccx.inp``: rigid bodies as node sets with REF and ROT nodes, face-to-face contact pairs,
stabilising springs, ``*STATIC`` seating and flexion steps, print requests.
``knee_abaqus.inp``: R3D3 bone surfaces, rigid bodies on element sets (and pin nodes for
deformable cartilage), masses and inertias, penalty contact pairs, ``*DYNAMIC, EXPLICIT`` steps.

Rules kept (each a silent trap of ccx): at most 16 entries a data line; no keyword or parameter
ccx skips (no ``*PART``, no ``NAME=`` on steps, no ``ENCASTRE``, numeric DOFs only); rotations of
a ccx rigid body on its ROT node's DOFs 1-3; a blank first data line for each ``*SPRING``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from kneemesh_core import __version__
from kneemesh_core.fe.model import (AP_RESTRAINT_N_MM, CARTILAGE_MODULUS_MPA, CARTILAGE_POISSON, CONFINED_MODULUS_MPA,
                                    IE_RESTRAINT_NMM_RAD, PAIRS, PATELLA_ROTATION_NMM_RAD,
                                    QUADRICEPS_SLACK_MM, STABILISER_N_MM, STABILISER_NMM_RAD, Model, blankevoort,
                                    quadriceps_law)
from kneemesh_core.io.files import atomic_write_text
from kneemesh_core.tissues import BONES

MODEL_FILE, CCX_FILE, ABAQUS_FILE, META_FILE = "knee_model.inp", "knee_ccx.inp", "knee_abaqus.inp", "model.json"
#: ccx and Abaqus read at most 16 entries on a data line.
PER_LINE = 16
#: ccx's equilibrium check: residual forces below 0.5 % of a reference force of 100 N (0.5 N, on a
#: joint load of hundreds to thousands of N).  ccx's default reference is the average force over
#: every node, which thousands of unloaded rigid-body nodes drive to 1e-2 N, and the default
#: tolerance to 1e-5 N: far more iterations for no better answer.
CONTROLS = ("*CONTROLS, PARAMETERS=FIELD", "0.005, 0.01, 100.0, 100.0")


def rot_nodes(m: Model) -> dict[str, int]:
    """The ROT node of each moving rigid body in the ccx deck (the tibia is held, not a rigid body)."""
    return {b: m.next_id + i for i, b in enumerate(("femur", "patella"))}


def femur_springs() -> tuple[float, float, float]:
    """The femur's translational springs to the ground along deck X, Y, Z, N/mm: weak, but for the
    anterior-posterior restraint."""
    return STABILISER_N_MM, AP_RESTRAINT_N_MM, STABILISER_N_MM


def _ids(ids) -> list[str]:
    ids = [int(i) for i in ids]
    return [", ".join(str(i) for i in ids[k:k + PER_LINE]) for k in range(0, len(ids), PER_LINE)]


def _set(kind: str, name: str, ids) -> list[str]:
    return [f"*{kind}, {kind}={name}", *_ids(ids)]


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
        + (" (articular layer of hexahedra only: deeper layers move with the bone)" if lc.cartilage == "rigid" else ""),
        "*NODE",
    ]
    w += [f"{i}, {p[0]:.6f}, {p[1]:.6f}, {p[2]:.6f}" for i, p in m.nodes.items()]
    for part in m.parts.values():
        w.append(f"*ELEMENT, TYPE=C3D8, ELSET={part.name.upper()}")
        w += [f"{e}, " + ", ".join(str(int(n)) for n in c) for e, c in zip(part.elements, part.connectivity)]
    w.append("*ELEMENT, TYPE=SPRINGA, ELSET=LIGAMENTS")
    w += [f"{s.element}, {s.nodes[0]}, {s.nodes[1]}" for s in m.springs]
    q = m.quadriceps
    w += ["*ELEMENT, TYPE=SPRINGA, ELSET=QUADRICEPS", f"{q.element}, {q.nodes[0]}, {q.nodes[1]}"]
    for bone in BONES:
        w += _set("NSET", f"{bone.upper()}_BONE", m.bone_nodes[bone])
    for body, nodes in m.body_nodes.items():
        w += _set("NSET", f"{body.upper()}_BODY", sorted(set(nodes)))
    w += _set("NSET", "REFS", [m.ref[b] for b in BONES])
    w += _set("NSET", "LIGAMENT_ENDS", sorted({n for s in [*m.springs, m.quadriceps] for n in s.nodes} | {m.patella_anchor}))
    for part in m.parts.values():
        name = part.name.upper()
        w += _set("ELSET", f"{name}_ART", part.articular) + _set("ELSET", f"{name}_DEEP", part.bone_side)
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
    w += ["*MATERIAL, NAME=CARTILAGE", "*ELASTIC", "10.0, 0.45", "*DENSITY", "1.1e-9"]
    for part in m.parts.values():
        w.append(f"*SOLID SECTION, ELSET={part.name.upper()}, MATERIAL=CARTILAGE")
    w.append("** ligaments: Blankevoort 1991 (e = L/L0 - 1, e_t = 0.06), force (N) against elongation from the initial length (mm)")
    for s in m.springs:
        w += [f"** {s.name}: k {s.stiffness_n:g} N/strain, slack length {s.slack_length_mm:.3f} mm, "
              f"initial length {s.length_mm:.3f} mm" + (f" ({s.beyond_mm:.3f} mm of it beyond its nodes)" if s.beyond_mm else ""),
              f"*SPRING, ELSET=LIG_{s.name}, NONLINEAR", ""]
        w += [f"{f:.6e}, {d:.6e}" for f, d in blankevoort(s.stiffness_n, s.slack_length_mm, s.length_mm)]
    w += [f"** quadriceps (patella to the femoral shaft): {m.load.quadriceps_n:g} N at its initial length, +1 N/mm as it "
          f"lengthens, slack {QUADRICEPS_SLACK_MM:g} mm shorter", "*SPRING, ELSET=QUADRICEPS, NONLINEAR", ""]
    w += [f"{f:.6e}, {d:.6e}" for f, d in quadriceps_law(m.load.quadriceps_n, q.length_mm)]
    w += [f"** contact: a thin elastic layer on bone, M = (1 - nu) E / ((1 + nu)(1 - 2 nu)), E {CARTILAGE_MODULUS_MPA:g} MPa, "
          f"nu {CARTILAGE_POISSON:g}"]
    for name, (slave, master) in m.pairs.items():
        k = m.contact_k[name]
        if name in PAIRS:  # K from the two cartilages the pair stands for
            a, b = PAIRS[name]
            why = (f"K = M / (h_{a} + h_{b}) = {CONFINED_MODULUS_MPA:.2f} MPa / ({m.parts[a].thickness_mm:.3f} + "
                   f"{m.parts[b].thickness_mm:.3f} mm)"
                   + ("; the master also the prefemoral sheet (rigid, with the femur; fe/prefemoral.py)" if master in m.surfaces else ""))
        else:
            why = "meniscus surrogate (rigid, with the tibia): K of its compartment"
        w += [f"** {name}: {why} = {k:.4f} N/mm^3",
              f"*SURFACE INTERACTION, NAME=CONTACT_{name.upper()}", "*SURFACE BEHAVIOR, PRESSURE-OVERCLOSURE=LINEAR", f"{k:.6f}"]
    w += ["*AMPLITUDE, NAME=RAMP", "0.0, 0.0, 1.0, 1.0", "*AMPLITUDE, NAME=HOLD", "0.0, 1.0, 1.0, 1.0"]
    return "\n".join(w) + "\n"


def joint_load(m: Model) -> list[str]:
    """The joint load on the femur's reference node: ``joint_load_n`` down the tibial axis."""
    force = -m.load.joint_load_n * m.tibial_axis
    return [f"{m.ref['femur']}, {dof}, {f:.3f}" for dof, f in enumerate(force, 1) if abs(f) > 1e-3]


def _pair_lines(m: Model, contact_keyword: str) -> list[str]:
    out = []
    for name, (slave, master) in m.pairs.items():
        out += [f"*CONTACT PAIR, INTERACTION=CONTACT_{name.upper()}, {contact_keyword}",
                f"{slave.upper()}_ARTICULAR, {master.upper()}_ARTICULAR"]
    return out


def calculix(m: Model, flexion_deg: float | None = None, max_increment_deg: float | None = None,
             include: str = MODEL_FILE) -> str:
    """``knee_ccx.inp``: seat under the joint load, then flex the femur about X."""
    flex = m.load.flexion_deg if flexion_deg is None else flexion_deg
    step = m.load.max_increment_deg if max_increment_deg is None else max_increment_deg
    rot = rot_nodes(m)
    w = ["*HEADING", f"KneeMesh {__version__} knee, CalculiX dialect: rigid bodies, {flex:g} deg flexion under "
         f"{m.load.joint_load_n:g} N", f"*INCLUDE, INPUT={include}", "*NODE"]
    w += [f"{n}, " + ", ".join(f"{c:.6f}" for c in m.nodes[m.ref[b]]) for b, n in rot.items()]
    for b, n in rot.items():
        w.append(f"*RIGID BODY, NSET={b.upper()}_BODY, REF NODE={m.ref[b]}, ROT NODE={n}")
    w += _pair_lines(m, "TYPE=SURFACE TO SURFACE")
    # weak springs on the free degrees of freedom: the femur's to the ground (with its internal-external
    # restraint), the patella's to the femur (grounded, they would pull back a patella that follows the
    # femur 30-50 mm through flexion: 150-250 N on the sample at 50 deg), its tilt and spin held as by the
    # retinacula
    eid = m.next_element

    def spring(nodes: tuple[int, ...], dof: int, k: float) -> list[str]:
        """A linear spring on ``dof`` of one node (to the ground, SPRING1) or between two (SPRING2)."""
        kind, dofs = ("SPRING1", str(dof)) if len(nodes) == 1 else ("SPRING2", f"{dof}, {dof}")
        return [f"*ELEMENT, TYPE={kind}, ELSET=STAB_{eid}", f"{eid}, " + ", ".join(map(str, nodes)),
                f"*SPRING, ELSET=STAB_{eid}", dofs, f"{k:.6e}"]

    for nodes, stiffness in (((m.ref["femur"],), femur_springs()),
                             ((rot["femur"],), (0.0, STABILISER_NMM_RAD, IE_RESTRAINT_NMM_RAD)),
                             ((m.ref["patella"], m.patella_anchor), (STABILISER_N_MM,) * 3),
                             ((rot["patella"], rot["femur"]), (STABILISER_NMM_RAD, PATELLA_ROTATION_NMM_RAD, PATELLA_ROTATION_NMM_RAD))):
        for dof, k in enumerate(stiffness, 1):
            if k > 0:  # the femur's flexion (its ROT node's dof 1) is driven, not sprung
                w += spring(nodes, dof, k)
                eid += 1
    w += [f"*NSET, NSET=FEMUR_REF\n{m.ref['femur']}", f"*NSET, NSET=ROTS\n{', '.join(str(n) for n in rot.values())}"]
    outputs = ["*NODE PRINT, NSET=REFS", "U", "*NODE PRINT, NSET=ROTS", "U", "*NODE PRINT, NSET=TIBIA_BODY, TOTALS=ONLY", "RF",
               "*NODE PRINT, NSET=LIGAMENT_ENDS", "U"]
    for name, (slave, master) in m.pairs.items():
        outputs += [f"*CONTACT PRINT, SLAVE={slave.upper()}_ARTICULAR, MASTER={master.upper()}_ARTICULAR", "CF"]
    outputs += ["*CONTACT PRINT", "CSTR"]
    # step 1: the femur, seated at the depth that carries the joint load (model.seat), takes the whole
    # load and the quadriceps force at once; flexion held at the image pose.  The tibia is fixed: its
    # nodes are held (a rigid body held still, without ccx's three MPCs a node)
    w += ["** step 1: settle under the joint load and the quadriceps force from the seated pose",
          "*STEP, NLGEOM, INC=200", "*STATIC", "1.0, 1.0, 1e-6, 1.0", *CONTROLS, "*BOUNDARY",
          "TIBIA_BODY, 1, 3, 0.0", f"{m.ref['tibia']}, 1, 3, 0.0", f"{rot['femur']}, 1, 1, 0.0",
          "*CLOAD, AMPLITUDE=HOLD", *joint_load(m), *outputs, "*END STEP"]
    # step 2: flex the femur about X, the joint load held; whole increments (rounded up, so that
    # ccx adds no sliver of an increment at the end)
    n = int(np.ceil(flex / min(step, flex) - 1e-9))
    dt = np.ceil(1e10 / n) / 1e10
    w += [f"** step 2: flex the femur {flex:g} deg about the flexion axis (X), at most {step:g} deg an increment",
          "*STEP, NLGEOM, INC=1000", "*STATIC", f"{dt:.10f}, 1.0, 1e-6, {dt:.10f}",
          *CONTROLS,
          "*BOUNDARY, AMPLITUDE=RAMP", f"{rot['femur']}, 1, 1, {np.radians(flex):.6f}",
          *outputs, "*END STEP"]
    return "\n".join(w) + "\n"


def abaqus(m: Model) -> str:
    """``knee_abaqus.inp`` (Abaqus/Explicit; not run here: no Abaqus licence)."""
    lc = m.load
    w = ["*HEADING", f"KneeMesh {__version__} knee, Abaqus/Explicit dialect: {lc.flexion_deg:g} deg flexion under "
         f"{lc.joint_load_n:g} N, cartilage {lc.cartilage}", f"*INCLUDE, INPUT={MODEL_FILE}"]
    eid = m.next_element
    for b in BONES:
        tris = m.bone_triangles[b]
        w.append(f"*ELEMENT, TYPE=R3D3, ELSET={b.upper()}_SHELL")
        w += [f"{eid + i}, {t[0]}, {t[1]}, {t[2]}" for i, t in enumerate(tris)]
        eid += len(tris)
    members = {b: [p.name.upper() for p in m.parts.values() if p.body == b] for b in BONES}
    for b in BONES:
        if lc.cartilage == "rigid":
            w += [f"*ELSET, ELSET={b.upper()}_RIGID", ", ".join([f"{b.upper()}_SHELL", *members[b]])]
            w.append(f"*RIGID BODY, ELSET={b.upper()}_RIGID, REF NODE={m.ref[b]}, PIN NSET={b.upper()}_BODY")
        else:  # deformable cartilage: its bone-side nodes (and the ligament ends) ride on the bone
            parts = [m.parts[t.lower()] for t in members[b]]
            deep = {int(n) for p in parts for n in p.connectivity[np.isin(p.elements, p.bone_side), :4].ravel()}
            ends = {n for s in m.springs for n in s.nodes} & set(m.body_nodes[b])
            w += _set("NSET", f"{b.upper()}_PINS", sorted(deep | ends))
            w.append(f"*RIGID BODY, ELSET={b.upper()}_SHELL, REF NODE={m.ref[b]}, PIN NSET={b.upper()}_PINS")
    for b in ("femur", "patella"):
        w += [f"*ELEMENT, TYPE=MASS, ELSET={b.upper()}_MASS", f"{eid}, {m.ref[b]}", f"*MASS, ELSET={b.upper()}_MASS", "1.0e-3",
              f"*ELEMENT, TYPE=ROTARYI, ELSET={b.upper()}_INERTIA", f"{eid + 1}, {m.ref[b]}",
              f"*ROTARY INERTIA, ELSET={b.upper()}_INERTIA", "1.0, 1.0, 1.0"]
        eid += 2
    w += _pair_lines(m, "MECHANICAL CONSTRAINT=PENALTY")
    w += ["*AMPLITUDE, NAME=SMOOTH, DEFINITION=SMOOTH STEP", "0.0, 0.0, 1.0, 1.0",
          "*STEP, NAME=SEAT", "*DYNAMIC, EXPLICIT", ", 0.2", "*FIXED MASS SCALING, DT=1.0e-5, TYPE=BELOW MIN",
          "*BOUNDARY", f"{m.ref['tibia']}, 1, 6, 0.0", f"{m.ref['femur']}, 4, 4, 0.0",
          "*CLOAD, AMPLITUDE=SMOOTH", *joint_load(m),
          "*OUTPUT, FIELD, NUMBER INTERVAL=10", "*NODE OUTPUT", "U, RF", "*CONTACT OUTPUT", "CSTRESS, CAREA",
          "*OUTPUT, HISTORY, TIME INTERVAL=0.005", "*NODE OUTPUT, NSET=REFS", "U, UR", "*ENERGY OUTPUT", "ALLKE, ALLIE",
          "*END STEP",
          "*STEP, NAME=FLEXION", "*DYNAMIC, EXPLICIT", ", 1.0",
          "*BOUNDARY, AMPLITUDE=SMOOTH", f"{m.ref['femur']}, 4, 4, {np.radians(lc.flexion_deg):.6f}", "*END STEP"]
    return "\n".join(w) + "\n"


def meta(m: Model, flexion_deg: float) -> dict:
    """What reading the results needs: node and element ids, fibres, loads (``model.json``)."""
    femur_nodes = set(m.body_nodes["femur"])
    return {
        "frame": m.frame, "side": m.side, "joint_load_n": m.load.joint_load_n,
        "joint_load_direction": (-m.tibial_axis).round(6).tolist(), "quadriceps_n": m.load.quadriceps_n,
        "flexion_deg": flexion_deg, "cartilage": m.load.cartilage, "contact_k": m.contact_k, "seating": m.seating,
        "pairs": {name: f"{slave.upper()}_ARTICULAR" for name, (slave, _) in m.pairs.items()},
        "slave_elements": {name: [int(m.parts[slave].elements[0]), int(m.parts[slave].elements[-1])]
                           for name, (slave, _) in m.pairs.items()},
        "ref": {b: m.ref[b] for b in BONES}, "rot": rot_nodes(m),
        "stabiliser_n_mm": STABILISER_N_MM, "femur_springs_n_mm": list(femur_springs()), "patella_anchor": m.patella_anchor,
        "quadriceps": {"nodes": list(m.quadriceps.nodes), "start": [m.nodes[n].tolist() for n in m.quadriceps.nodes],
                       "law": quadriceps_law(m.load.quadriceps_n, m.quadriceps.length_mm)},
        "fibres": [{"name": s.name, "bundle": s.bundle, "k": s.stiffness_n, "slack": s.slack_length_mm, "beyond": s.beyond_mm,
                    "nodes": list(s.nodes), "start": [m.nodes[s.nodes[0]].tolist(), m.nodes[s.nodes[1]].tolist()],
                    "femur_end": 0 if s.nodes[0] in femur_nodes else 1 if s.nodes[1] in femur_nodes else None}
                   for s in m.springs],
    }


def write(m: Model, folder: Path, flexion_deg: float | None = None, max_increment_deg: float | None = None,
          include: str | None = None) -> list[Path]:
    """Write the decks into ``folder``; with ``include`` (the path of an existing shared model, from
    ``folder``) only the CalculiX wrapper and ``model.json``, for a run of another flexion beside the
    job's decks.  Returns their paths."""
    import json

    folder.mkdir(parents=True, exist_ok=True)
    flex = m.load.flexion_deg if flexion_deg is None else flexion_deg
    files = {CCX_FILE: calculix(m, flex, max_increment_deg, include or MODEL_FILE),
             META_FILE: json.dumps(meta(m, flex), indent=1)}
    if include is None:
        files = {MODEL_FILE: shared(m), **files, ABAQUS_FILE: abaqus(m)}
    for name, text in files.items():
        atomic_write_text(folder / name, text)
    return [folder / n for n in files]

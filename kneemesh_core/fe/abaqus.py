"""``knee_abaqus.inp``: the Abaqus/Explicit dialect over the shared model (:mod:`.deck`).

R3D3 bone shells, rigid bodies on element sets (with pin nodes: ligament ends, deformable cartilage's bone side), masses
and inertias for the explicit integration, penalty contact pairs, the same restraint springs as the
CalculiX deck (Abaqus carries a rigid body's rotations on its reference node's dofs 4-6), and
``*DYNAMIC, EXPLICIT`` seating and flexion steps.  Not run here: no Abaqus licence.
"""

from __future__ import annotations

import numpy as np

from kneemesh_core import __version__
from kneemesh_core.fe import inp
from kneemesh_core.fe.model import Model
from kneemesh_core.fe.physics import FIXED_BODY, FLEXION, MOVING_BODIES, legs
from kneemesh_core.tissues import BONES


#: The explicit steps' durations, s: the seating, and each leg of the activity (quasi-static under the mass scaling).
SEAT_S, LEG_S = 0.2, 1.0


def deck(m: Model, include: str) -> str:
    """Seat under the joint load, then the load case's activity (the CalculiX deck's legs: :func:`.physics.legs`);
    ``include`` is the shared model's path."""
    lc = m.load

    def dof_of(body: str, kind: str, axis: int) -> tuple[int, int]:
        return m.ref[body], axis + (1 if kind == "translation" else 4)

    w = ["*HEADING", f"KneeMesh {__version__} knee, Abaqus/Explicit dialect: {lc.flexion_deg:g} deg "
         f"{'knee bend' if lc.activity == 'knee_bend' else 'flexion'} under "
         f"{lc.joint_load_n:g} N ({lc.medial_offset_mm:g} mm medial), cartilage {lc.cartilage}", f"*INCLUDE, INPUT={include}"]
    eid = m.next_element
    for b in m.bone_triangles:
        tris = m.bone_triangles[b]
        w.append(f"*ELEMENT, TYPE=R3D3, ELSET={b.upper()}_SHELL")
        w += [f"{eid + i}, {t[0]}, {t[1]}, {t[2]}" for i, t in enumerate(tris)]
        eid += len(tris)
    w += _rigid_bodies(m)
    for b in (b for b in MOVING_BODIES if b in m.ref):
        w += [f"*ELEMENT, TYPE=MASS, ELSET={b.upper()}_MASS", f"{eid}, {m.ref[b]}", f"*MASS, ELSET={b.upper()}_MASS", "1.0e-3",
              f"*ELEMENT, TYPE=ROTARYI, ELSET={b.upper()}_INERTIA", f"{eid + 1}, {m.ref[b]}",
              f"*ROTARY INERTIA, ELSET={b.upper()}_INERTIA", "1.0, 1.0, 1.0"]
        eid += 2
    springs, eid = inp.restraints(m, eid, dof_of)
    w += springs
    w += inp.contact_pairs(m, "MECHANICAL CONSTRAINT=PENALTY")
    driven, dof = dof_of(*FLEXION)
    # the same legs as the CalculiX deck (physics.legs), each SEAT_S long after the seating, through amplitudes in
    # total time: the flexion (rad) and the joint load (its fraction of the load case's) smoothly from point to point
    turns = legs(lc, lc.flexion_deg, m.frame.get("image_flexion_deg"))
    times = [SEAT_S + LEG_S * k for k in range(len(turns) + 1)]
    flexion = [0.0] + [np.radians(t.flexion_deg) for t in turns]
    load = [1.0] + [t.joint_load_n / lc.joint_load_n if lc.joint_load_n else 0.0 for t in turns]
    w += ["*AMPLITUDE, NAME=LOAD, DEFINITION=SMOOTH STEP, TIME=TOTAL TIME",
          *_pairs([0.0, *times], [0.0, *load]),
          "*STEP, NAME=SEAT", "*DYNAMIC, EXPLICIT", f", {SEAT_S:g}", "*FIXED MASS SCALING, DT=1.0e-5, TYPE=BELOW MIN",
          "*BOUNDARY", f"{m.ref[FIXED_BODY]}, 1, 6, 0.0", f"{driven}, {dof}, {dof}, 0.0",
          "*CLOAD, AMPLITUDE=LOAD", *inp.joint_load(m, dof_of),
          "*OUTPUT, FIELD, NUMBER INTERVAL=10", "*NODE OUTPUT", "U, RF", "*CONTACT OUTPUT", "CSTRESS, CAREA",
          "*OUTPUT, HISTORY, TIME INTERVAL=0.005", "*NODE OUTPUT, NSET=REFS", "U, UR", "*ENERGY OUTPUT", "ALLKE, ALLIE",
          "*END STEP"]
    if turns:
        w += ["*AMPLITUDE, NAME=FLEXION, DEFINITION=SMOOTH STEP, TIME=TOTAL TIME", *_pairs(times, flexion),
              f"** {lc.activity}: " + "; ".join(f"{t.name}: the femur to {t.flexion_deg:g} deg, the joint load to "
                                                 f"{t.joint_load_n:g} N" for t in turns),
              f"*STEP, NAME={lc.activity.upper()}", "*DYNAMIC, EXPLICIT", f", {LEG_S * len(turns):g}",
              "*BOUNDARY, AMPLITUDE=FLEXION", f"{driven}, {dof}, {dof}, 1.0", "*END STEP"]
    return "\n".join(w) + "\n"


def _pairs(times: list[float], values: list[float]) -> list[str]:
    """An ``*AMPLITUDE``'s data lines: (time, value) pairs, four to a line (Abaqus reads at most eight numbers)."""
    flat = [f"{x:.6f}" for tv in zip(times, values) for x in tv]
    return [", ".join(flat[i:i + 8]) for i in range(0, len(flat), 8)]


def _rigid_bodies(m: Model) -> list[str]:
    """Each bone a rigid body on its shell and its rigid parts (a rigid cartilage's skin, the surrogates), with
    the nodes that ride on it as pins (ligament ends, a deformable cartilage's bone-side nodes)."""
    w = []
    for b in (b for b in BONES if b in m.ref):
        rigid = [p.name.upper() for p in m.parts.values() if p.body == b and not p.deformable]
        w += [f"*ELSET, ELSET={b.upper()}_RIGID", ", ".join([f"{b.upper()}_SHELL", *rigid]),
              f"*RIGID BODY, ELSET={b.upper()}_RIGID, REF NODE={m.ref[b]}, PIN NSET={b.upper()}_BODY"]
    return w

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
from kneemesh_core.fe.physics import FIXED_BODY, FLEXION, MOVING_BODIES
from kneemesh_core.tissues import BONES


def deck(m: Model, include: str) -> str:
    """Seat under the joint load, then flex the femur ``m.load.flexion_deg`` about X; ``include`` is the
    shared model's path."""
    lc = m.load

    def dof_of(body: str, kind: str, axis: int) -> tuple[int, int]:
        return m.ref[body], axis + (1 if kind == "translation" else 4)

    w = ["*HEADING", f"KneeMesh {__version__} knee, Abaqus/Explicit dialect: {lc.flexion_deg:g} deg flexion under "
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
    w += ["*AMPLITUDE, NAME=SMOOTH, DEFINITION=SMOOTH STEP", "0.0, 0.0, 1.0, 1.0",
          "*STEP, NAME=SEAT", "*DYNAMIC, EXPLICIT", ", 0.2", "*FIXED MASS SCALING, DT=1.0e-5, TYPE=BELOW MIN",
          "*BOUNDARY", f"{m.ref[FIXED_BODY]}, 1, 6, 0.0", f"{driven}, {dof}, {dof}, 0.0",
          "*CLOAD, AMPLITUDE=SMOOTH", *inp.joint_load(m, dof_of),
          "*OUTPUT, FIELD, NUMBER INTERVAL=10", "*NODE OUTPUT", "U, RF", "*CONTACT OUTPUT", "CSTRESS, CAREA",
          "*OUTPUT, HISTORY, TIME INTERVAL=0.005", "*NODE OUTPUT, NSET=REFS", "U, UR", "*ENERGY OUTPUT", "ALLKE, ALLIE",
          "*END STEP",
          "*STEP, NAME=FLEXION", "*DYNAMIC, EXPLICIT", ", 1.0",
          "*BOUNDARY, AMPLITUDE=SMOOTH", f"{driven}, {dof}, {dof}, {np.radians(lc.flexion_deg):.6f}", "*END STEP"]
    return "\n".join(w) + "\n"


def _rigid_bodies(m: Model) -> list[str]:
    """Each bone a rigid body on its shell and its rigid parts (a rigid cartilage's skin, the surrogates), with
    the nodes that ride on it as pins (ligament ends, a deformable cartilage's bone-side nodes)."""
    w = []
    for b in (b for b in BONES if b in m.ref):
        rigid = [p.name.upper() for p in m.parts.values() if p.body == b and not p.deformable]
        w += [f"*ELSET, ELSET={b.upper()}_RIGID", ", ".join([f"{b.upper()}_SHELL", *rigid]),
              f"*RIGID BODY, ELSET={b.upper()}_RIGID, REF NODE={m.ref[b]}, PIN NSET={b.upper()}_BODY"]
    return w

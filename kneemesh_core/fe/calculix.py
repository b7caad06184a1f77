"""``knee_ccx.inp``: the CalculiX dialect over the shared model (:mod:`.deck`), static and implicit.

Rigid bodies as node sets with REF and ROT nodes (ccx carries a rigid body's rotations on its ROT
node's dofs 1-3), face-to-face contact pairs, the restraint springs, a ``*STATIC`` seating step under
the joint load and a flexion step, print requests for the results reader (:mod:`.results`).  No
keyword or parameter ccx skips: no ``*PART``, no ``NAME=`` on steps, no ``ENCASTRE``.
"""

from __future__ import annotations

import numpy as np

from kneemesh_core import __version__
from kneemesh_core.fe import inp
from kneemesh_core.fe.model import Model
from kneemesh_core.fe.physics import (DEFORMABLE_MAX_INCREMENT_DEG, FIXED_BODY, FLEXION,
                                      MOVING_BODIES, legs)

#: ccx's equilibrium check: residual forces below 0.5 % of a reference force of 100 N (0.5 N, on a
#: joint load of hundreds to thousands of N).  ccx's default reference is the average force over
#: every node, which thousands of unloaded rigid-body nodes drive to 1e-2 N, and the default
#: tolerance to 1e-5 N: far more iterations for no better answer.
CONTROLS = ("*CONTROLS, PARAMETERS=FIELD", "0.005, 0.01, 100.0, 100.0")
#: Rigid cartilage: an iteration may converge while up to 1 % of the contact elements change status (ccx's
#: delcon; default 0.1 %).  Each 3-deg increment of a rigid flexion then needs 3-4 Newton iterations, not 4-5: the
#: full flexion of three OAI knees took 129-130 iterations against 144-154, and sits as close to the same deck
#: converged ten times tighter in 1.5-deg increments (median over every increment: plates' forces 1.1-2.0 %,
#: areas 1.9-4.1 %, as with the default).  Deformable cartilage keeps the default: its increments are tuned to it.
RIGID_CONTACT_CONTROLS = ("*CONTROLS, PARAMETERS=CONTACT", "0.01")


def rot_nodes(m: Model) -> dict[str, int]:
    """The ROT node of each moving rigid body (the held body is no rigid body: its nodes are held)."""
    return {b: m.next_id + i for i, b in enumerate(b for b in MOVING_BODIES if b in m.ref)}


#: The node set whose displacement, stress and strain a run with deformable cartilage writes to the .frd.
CARTILAGE_NODES = "CARTILAGE_NODES"


def deformable_nodes(m: Model) -> np.ndarray:
    """The nodes (sorted ids) of the model's deformable cartilage; empty where the cartilage is rigid."""
    parts = [p.connectivity.ravel() for p in m.parts.values() if p.deformable]
    return np.unique(np.concatenate(parts)) if parts else np.zeros(0, int)


#: A start pose: per moving body, its reference node's displacement (3,), mm, and its ROT node's rotation
#: (3,), rad, from the seated pose of the deck (:func:`kneemesh_core.fe.run.rigid_start_pose`).
StartPose = dict[str, tuple[np.ndarray, np.ndarray]]


def loaded_at(start_pose: StartPose | None) -> float:
    """The total time (ccx's) from which a run carries its loads with its bodies free: the end of the
    seating step, or with a start pose the end of the step that releases the bodies there."""
    return 1.0 if start_pose is None else 2.0


def deck(m: Model, flexion_deg: float, max_increment_deg: float, include: str, start_pose: StartPose | None = None) -> str:
    """Seat under the joint load and the quadriceps force, then flex the femur ``flexion_deg`` about X,
    at most ``max_increment_deg`` an increment (no flexion step at 0); ``include`` is the shared model's path.

    With ``start_pose`` (deformable cartilage) the femur and the patella are first carried there with their
    rotations, the loads on, while the cartilage deforms under the prescribed poses; the next step releases
    them.  A deforming model started from the seated pose diverges: its patella, far from the rotational
    balance of quadriceps, patellar tendon and contact, tilted about a radian in the first iteration."""
    rot = rot_nodes(m)
    flex, step = flexion_deg, max_increment_deg

    def dof_of(body: str, kind: str, axis: int) -> tuple[int, int]:
        return (m.ref[body] if kind == "translation" else rot[body]), axis + 1

    w = ["*HEADING", f"KneeMesh {__version__} knee, CalculiX dialect: rigid bones, {m.load.cartilage} cartilage, "
         f"{flex:g} deg {'knee bend' if m.load.activity == 'knee_bend' else 'flexion'} under {m.load.joint_load_n:g} N "
         f"({m.load.medial_offset_mm:g} mm medial)",
         f"*INCLUDE, INPUT={include}", "*NODE"]
    w += [f"{n}, " + ", ".join(f"{c:.6f}" for c in m.nodes[m.ref[b]]) for b, n in rot.items()]
    for b, n in rot.items():
        w.append(f"*RIGID BODY, NSET={b.upper()}_BODY, REF NODE={m.ref[b]}, ROT NODE={n}")
    w += inp.contact_pairs(m, "TYPE=SURFACE TO SURFACE")
    w += inp.restraints(m, m.next_element, dof_of)[0]
    w += [f"*NSET, NSET=FEMUR_REF\n{m.ref['femur']}", f"*NSET, NSET=ROTS\n{', '.join(str(n) for n in rot.values())}"]
    outputs = ["*NODE PRINT, NSET=REFS", "U", "*NODE PRINT, NSET=ROTS", "U",
               f"*NODE PRINT, NSET={FIXED_BODY.upper()}_BODY, TOTALS=ONLY", "RF", "*NODE PRINT, NSET=LIGAMENT_ENDS", "U"]
    for name, (slave, master) in m.pairs.items():
        outputs += [f"*CONTACT PRINT, SLAVE={slave.upper()}_ARTICULAR, MASTER={master.upper()}_ARTICULAR", "CF"]
    outputs += ["*CONTACT PRINT", "CSTR"]
    solid = deformable_nodes(m)
    if len(solid):  # the deforming cartilage's fields, to the .frd (fe/cartilage_fields.py)
        w += inp.set_lines("NSET", CARTILAGE_NODES, solid)
        outputs += [f"*NODE FILE, NSET={CARTILAGE_NODES}", "U", f"*EL FILE, NSET={CARTILAGE_NODES}", "S, E"]
    controls = CONTROLS if len(solid) else (*CONTROLS, *RIGID_CONTACT_CONTROLS)
    driven, dof = dof_of(FLEXION[0], FLEXION[1], FLEXION[2])
    held = [f"{FIXED_BODY.upper()}_BODY, 1, 3, 0.0", f"{m.ref[FIXED_BODY]}, 1, 3, 0.0", f"{driven}, {dof}, {dof}, 0.0"]
    if start_pose is None:
        # step 1: the femur, seated at the depth that carries the joint load (model.seat_femur), takes the whole
        # load and the quadriceps force at once; flexion held at the image pose.  The held body's nodes are held
        # (a rigid body held still, without ccx's three MPCs a node)
        w += ["** step 1: settle under the joint load and the quadriceps force from the seated pose",
              "*STEP, NLGEOM, INC=200", "*STATIC", "1.0, 1.0, 1e-6, 1.0", *controls, "*BOUNDARY", *held,
              "*CLOAD, AMPLITUDE=HOLD", *inp.joint_load(m, dof_of), *outputs, "*END STEP"]
    else:
        carried = [f"{node}, {d}, {d}, {value:.6e}" for b, (u, r) in start_pose.items()
                   for node, values in ((m.ref[b], u), (rot[b], r))
                   for d, value in enumerate(values, start=1) if (node, d) != (driven, dof)]
        w += ["** step 1: carry the femur and the patella to the rigid model's seated equilibrium, the loads on: the",
              "** cartilage deforms under the prescribed poses",
              "*STEP, NLGEOM, INC=200", "*STATIC", "1.0, 1.0, 1e-6, 1.0", *controls, "*BOUNDARY", *held,
              "*BOUNDARY, AMPLITUDE=RAMP", *carried,
              "*CLOAD, AMPLITUDE=HOLD", *inp.joint_load(m, dof_of), *outputs, "*END STEP",
              "** step 2: release them to settle under the loads",
              "*STEP, NLGEOM, INC=200", "*STATIC", "1.0, 1.0, 1e-6, 1.0", *controls, "*BOUNDARY, OP=NEW", *held,
              *outputs, "*END STEP"]
    # the legs (physics.legs): each turns the femur about X, the joint load going linearly to the leg's (a *BOUNDARY
    # and a *CLOAD without an amplitude ramp from the previous step's values in ccx's static steps); whole increments
    # (rounded up, so that ccx adds no sliver of an increment at the end), deformable cartilage's smaller
    if len(solid):
        step = min(step, DEFORMABLE_MAX_INCREMENT_DEG)
    at, load_n = 0.0, m.load.joint_load_n
    for k, leg in enumerate(legs(m.load, flex, m.frame.get("image_flexion_deg")), start=2 if start_pose is None else 3):
        turn = abs(leg.flexion_deg - at)
        n = max(1, int(np.ceil(turn / min(step, turn) - 1e-9))) if turn > 0 else 1
        dt = np.ceil(1e10 / n) / 1e10
        loads = [] if leg.joint_load_n == load_n else ["*CLOAD", *inp.joint_load(m, dof_of, leg.joint_load_n)]
        w += [f"** step {k}: {leg.name}: the femur to {leg.flexion_deg:g} deg about the flexion axis (X) from the image "
              f"pose, at most {step:g} deg an increment, the joint load to {leg.joint_load_n:g} N",
              "*STEP, NLGEOM, INC=1000", "*STATIC", f"{dt:.10f}, 1.0, 1e-6, {dt:.10f}", *controls,
              "*BOUNDARY", f"{driven}, {dof}, {dof}, {np.radians(leg.flexion_deg):.6f}", *loads, *outputs, "*END STEP"]
        at, load_n = leg.flexion_deg, leg.joint_load_n
    return "\n".join(w) + "\n"

"""The keyword lines both deck dialects write, and the data-line rules they share.

Rules kept (each a silent trap of ccx, ``../shared/docs/fe-calculix-reference.md``): at most 16
entries a data line; numeric degrees of freedom only; a blank first data line for each nonlinear
``*SPRING``.  Hand-written on purpose: no Python library writes Abaqus/CalculiX decks with surfaces,
springs, rigid bodies and contact (meshio drops surfaces and renumbers).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from kneemesh_core.fe.model import Model
from kneemesh_core.fe.physics import RESTRAINTS

#: ccx and Abaqus read at most 16 entries on a data line.
PER_LINE = 16

#: Where a dialect puts a body's degree of freedom: (body, "translation" or "rotation", axis 0-2) ->
#: (node, dof).  ccx carries a rigid body's rotations on its ROT node's dofs 1-3, Abaqus on its
#: reference node's dofs 4-6.
DofOf = Callable[[str, str, int], tuple[int, int]]


def id_lines(ids) -> list[str]:
    """Integers, :data:`PER_LINE` to a data line."""
    ids = [int(i) for i in ids]
    return [", ".join(str(i) for i in ids[k:k + PER_LINE]) for k in range(0, len(ids), PER_LINE)]


def set_lines(kind: str, name: str, ids) -> list[str]:
    """An ``*NSET`` or ``*ELSET`` (``kind``) of ids."""
    return [f"*{kind}, {kind}={name}", *id_lines(ids)]


def joint_load(m: Model, dof_of: DofOf, load_n: float | None = None) -> list[str]:
    """``*CLOAD`` data lines: the joint load on the femur's reference node, ``load_n`` (default the load
    case's ``joint_load_n``) down the tibial axis, and its moment about that node where its line of action
    passes ``medial_offset_mm`` medial of it (:func:`load_moment`)."""
    load_n = m.load.joint_load_n if load_n is None else load_n
    force = -load_n * m.tibial_axis
    lines = [f"{m.ref['femur']}, {dof}, {f:.3f}" for dof, f in enumerate(force, 1) if abs(f) > 1e-3]
    for axis, moment in enumerate(load_moment(m) * (load_n / m.load.joint_load_n if m.load.joint_load_n else 0.0)):
        if abs(moment) > 1e-3:
            node, dof = dof_of("femur", "rotation", axis)
            lines.append(f"{node}, {dof}, {moment:.3f}")
    return lines


def load_moment(m: Model) -> np.ndarray:
    """The joint load's moment about the femur's reference node (3,), N mm, deck frame: its line of
    action ``medial_offset_mm`` medial of the node (:attr:`Model.medial`)."""
    return np.cross(m.load.medial_offset_mm * m.medial, -m.load.joint_load_n * m.tibial_axis)


def contact_pairs(m: Model, contact_keyword: str) -> list[str]:
    """One ``*CONTACT PAIR`` per pair of the model (slave, then master surface)."""
    out = []
    for name, (slave, master) in m.pairs.items():
        out += [f"*CONTACT PAIR, INTERACTION=CONTACT_{name.upper()}, {contact_keyword}",
                f"{slave.upper()}_ARTICULAR, {master.upper()}_ARTICULAR"]
    return out


def restraints(m: Model, first_element: int, dof_of: DofOf) -> tuple[list[str], int]:
    """The linear springs of :data:`kneemesh_core.fe.physics.RESTRAINTS`: a ``SPRING1`` to the ground or a
    ``SPRING2`` to another body (a translation's to the node of that body where the moving body's
    reference node starts, :attr:`Model.anchors`), element ids from ``first_element``.  Returns the
    lines and the next free element id."""
    lines, eid = [], first_element
    for r in RESTRAINTS:
        if r.body not in m.ref or (r.to is not None and r.to not in m.ref):
            continue  # a tibiofemoral model has no patella
        node, dof = dof_of(r.body, r.kind, r.axis)
        if r.to is None:
            kind, nodes, dofs = "SPRING1", (node,), str(dof)
        else:
            other = m.anchors[r.body] if r.kind == "translation" else dof_of(r.to, r.kind, r.axis)[0]
            kind, nodes, dofs = "SPRING2", (node, other), f"{dof}, {dof}"
        lines += [f"*ELEMENT, TYPE={kind}, ELSET=STAB_{eid}", f"{eid}, " + ", ".join(map(str, nodes)),
                  f"*SPRING, ELSET=STAB_{eid}", dofs, f"{r.stiffness:.6e}"]
        eid += 1
    return lines, eid

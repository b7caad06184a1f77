"""Let the bone give way where a fused cartilage still dips into it.

Fusion (:mod:`.blend`) moves the cartilage onto the bone wherever its elements allow.
Where the bone and cartilage labels overlap (the bone's smoothed surface bulges over
the cartilage rim, or the segmentations disagree by a voxel), some cartilage nodes
stay inside the bone: moving them out would crush their elements.  There the bone
surface is the less certain of the two, so it gives way instead: the corners of the
bone triangle nearest each such node move inwards along the bone normal, a little
past the node, round after round until no node is deeper than the fusion tolerance
(the smallest dent that frees the node: neighbouring fused nodes stay on the bone
unless they share that triangle).  The bone keeps its topology (closed, same triangles); a
dent that would make it cross itself is not made.  The cartilage meshes are not
touched.
"""

from __future__ import annotations

import numpy as np
import pyvista as pv

from kneemesh_core.hexmesh.targets import FUSED_TOL_MM
from kneemesh_core.surfaces.distance import SurfaceDistance
from kneemesh_core.surfaces.metrics import crossing_edges


def conform_bone(bone: pv.PolyData, cartilages: dict[str, pv.UnstructuredGrid], *, clearance_mm: float = 0.02,
                 max_dent_mm: float = 2.0, rounds: int = 8) -> tuple[pv.PolyData, dict]:
    """The bone surface (closed, LPS mm) dented so that no node of ``cartilages`` (their hex meshes,
    with point data ``bone_side``) lies more than :data:`.targets.FUSED_TOL_MM` inside it.

    Returns the new surface (the input itself where nothing was inside, or the dent was refused)
    and what was done: ``applied``, ``vertices_moved``, ``max_dent_mm``, and per cartilage the
    deepest node before and after (``penetration_mm``, ``penetration_conformed_mm``) and the
    fraction of its bone-side nodes on the bone after (``fused_fraction_conformed``).
    """
    nodes = {t: np.asarray(g.points, float) for t, g in cartilages.items()}
    if not nodes:
        return bone, {"applied": False, "vertices_moved": 0, "max_dent_mm": 0.0, "cartilages": {}}
    every = np.concatenate(list(nodes.values()))
    distance = SurfaceDistance(bone)  # the surface as it stands: rebuilt after each round's dent
    start = distance.signed(every)
    normal = np.asarray(bone.compute_normals(cell_normals=False, point_normals=True, auto_orient_normals=True)
                        .point_data["Normals"], float)
    origin = np.array(bone.points, float)
    surface = pv.PolyData(origin.copy(), bone.faces.copy())  # its own points: the input is not touched
    faces = surface.faces.reshape(-1, 4)[:, 1:]
    dent = np.zeros(len(origin))
    sd = start
    for _ in range(rounds):
        deep = np.flatnonzero(sd < -0.5 * FUSED_TOL_MM)
        if not len(deep):
            break
        # the triangle over each deep node moves down past it: all three corners by its depth
        cell = distance.closest(every[deep])[1]
        extra = np.zeros(len(origin))
        np.maximum.at(extra, faces[cell].ravel(), np.repeat(-sd[deep] + clearance_mm, 3))
        dent = np.minimum(dent + extra, max_dent_mm)
        surface.points = origin - normal * dent[:, None]
        distance = SurfaceDistance(surface)
        sd = distance.signed(every)
    moved = dent > 0
    facts: dict = {"applied": False, "vertices_moved": int(moved.sum()), "max_dent_mm": round(float(dent.max(initial=0)), 3)}
    if moved.any() and crossing_edges(surface) > crossing_edges(bone):
        facts["reason"] = "the dent would make the bone surface cross itself; the bone is kept as it was"
        surface, sd = bone, start
    elif moved.any():
        facts["applied"] = True
    else:
        surface = bone
    per, k = {}, 0
    for t, g in cartilages.items():
        m = len(nodes[t])
        before, after = start[k:k + m], sd[k:k + m]
        foot = np.asarray(g.point_data["bone_side"], bool)
        per[t] = {"penetration_mm": round(float(max(0.0, -before.min())), 4),
                  "penetration_conformed_mm": round(float(max(0.0, -after.min())), 4),
                  "fused_fraction_conformed": round(float((np.abs(after[foot]) <= FUSED_TOL_MM).mean()), 4)}
        k += m
    facts["cartilages"] = per
    return surface, facts

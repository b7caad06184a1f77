"""Overlaps of a knee's final meshes that should only touch: cartilage into cartilage across a joint,
and cartilage into a bone it does not sit on.

Each is measured from the articular nodes of one cartilage (the top faces of its outermost layer)
to the closed surface of the other mesh: the deepest node inside it (mm) and the articular area
inside it (each node's share of its quads, mm^2).  The FE seating step removes a cartilage-cartilage
overlap by moving the femur (and the patella) away by its depth; beyond
:data:`MAX_SEATABLE_OVERLAP_MM` that leaves the image pose behind, and cartilage inside an opposing
bone (deeper than :data:`MAX_BONE_OVERLAP_MM`) is something no contact pair resolves: either makes
the knee ``review``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyvista as pv

from kneemesh_core.geometry import quad_node_areas
from kneemesh_core.hexmesh.quality import boundary_surface
from kneemesh_core.metrics.compare import articular_surface
from kneemesh_core.surfaces.distance import signed_distance

#: Deepest cartilage-cartilage overlap the FE seating step resolves without leaving the image pose, mm.
MAX_SEATABLE_OVERLAP_MM = 1.0
#: Deepest a cartilage may reach into a bone it does not sit on (half a DESS voxel's diagonal), mm.
MAX_BONE_OVERLAP_MM = 0.5
#: (cartilage whose articular nodes are tested, the other tissue): across the joints.
CARTILAGE_PAIRS = (("medial_tibial_cartilage", "femoral_cartilage"), ("lateral_tibial_cartilage", "femoral_cartilage"),
                   ("patellar_cartilage", "femoral_cartilage"), ("medial_tibial_cartilage", "lateral_tibial_cartilage"))
BONE_PAIRS = (("femoral_cartilage", "tibia"), ("femoral_cartilage", "patella"), ("medial_tibial_cartilage", "femur"),
              ("lateral_tibial_cartilage", "femur"), ("patellar_cartilage", "femur"))


def closed_surface(mesh: pv.DataSet) -> pv.PolyData:
    """A mesh's boundary as triangles with outward normals (a bone shell, or a hex mesh's skin)."""
    surface = mesh.triangulate() if isinstance(mesh, pv.PolyData) else boundary_surface(mesh)
    return surface.compute_normals(cell_normals=True, point_normals=False, auto_orient_normals=True,
                                                 consistent_normals=True)


def overlap(points: np.ndarray, areas: np.ndarray, other: pv.PolyData) -> dict:
    """How far the points (N, 3) reach into the closed surface ``other``: ``max_depth_mm`` (0 if
    none is inside), ``area_mm2`` (the summed ``areas`` (N,) of those inside) and ``nodes``."""
    signed = signed_distance(points, other)
    inside = signed < 0
    return {"max_depth_mm": round(float(-signed[inside].min()) if inside.any() else 0.0, 4),
            "area_mm2": round(float(areas[inside].sum()), 3), "nodes": int(inside.sum())}


def knee_overlaps(meshes_dir: Path) -> dict:
    """Every overlap of a job's final meshes (pairs whose meshes exist), with a status (ok or review)
    and the reasons: {"status", "reasons", "pairs": {"a/b": {...}}}."""
    meshes_dir = Path(meshes_dir)

    def load(tissue: str):
        f = meshes_dir / (f"{tissue}.vtu" if "cartilage" in tissue else f"{tissue}.vtp")
        return pv.read(f) if f.exists() else None

    cache: dict = {}
    pairs, reasons = {}, []
    for (a, b), limit in [*((p, MAX_SEATABLE_OVERLAP_MM) for p in CARTILAGE_PAIRS), *((p, MAX_BONE_OVERLAP_MM) for p in BONE_PAIRS)]:
        for t in (a, b):
            if t not in cache:
                cache[t] = load(t)
        if cache[a] is None or cache[b] is None:
            continue
        points, quads = articular_surface(cache[a])
        found = overlap(points, quad_node_areas(points, quads), closed_surface(cache[b]))
        pairs[f"{a}/{b}"] = found
        if found["max_depth_mm"] > limit:
            reasons.append(f"{a.replace('_', ' ')} reaches {found['max_depth_mm']:.2f} mm into the {b.replace('_', ' ')} "
                           f"over {found['area_mm2']:.0f} mm^2 (limit {limit} mm"
                           + (": more than the FE seating step resolves)" if "cartilage" in b else ")"))
    return {"status": "review" if reasons else "ok", "reasons": reasons, "pairs": pairs}

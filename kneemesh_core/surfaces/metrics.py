"""Surface checks for FE: closedness, manifoldness, self-intersections, edge lengths, accuracy."""

from __future__ import annotations

import numpy as np
import pymeshfix
import pyvista as pv

from kneemesh_core.geometry import unique_rows
from kneemesh_core.surfaces.distance import distance_to_surface


def unique_edges(surf: pv.PolyData) -> np.ndarray:
    """The unique edges (E, 2) of a triangle surface, each as its two vertex ids, sorted."""
    f = surf.faces.reshape(-1, 4)[:, 1:]
    return unique_rows(np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1))


def edges_mm(surf: pv.PolyData, edges: np.ndarray | None = None) -> np.ndarray:
    """Lengths of the unique edges of a triangle surface (or of ``edges`` (E, 2) of it), mm."""
    e = unique_edges(surf) if edges is None else edges
    return np.linalg.norm(surf.points[e[:, 0]] - surf.points[e[:, 1]], axis=1)


def topology(surf: pv.PolyData) -> dict:
    """``watertight`` (every edge in exactly two triangles, consistently wound), ``manifold``
    (no edge in three or more triangles), ``self_intersections`` (triangle count)."""
    f = surf.faces.reshape(-1, 4)[:, 1:]
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    und = np.sort(directed, axis=1)
    _, counts = unique_rows(und, return_counts=True)
    manifold = bool(np.all(counts <= 2))
    # consistent winding: each directed edge appears once
    _, dcounts = unique_rows(directed, return_counts=True)
    watertight = bool(manifold and np.all(counts == 2) and np.all(dcounts == 1))
    tm = pymeshfix.PyTMesh()
    tm.set_quiet(True)
    tm.load_array(np.asarray(surf.points, float), f.astype(np.int32))
    n_int = len(tm.select_intersecting_triangles())
    return {"watertight": watertight, "manifold": manifold, "self_intersections": n_int}


def crossing_edges(surf: pv.PolyData) -> int:
    """Edges of a triangle surface that pass through a triangle they do not belong to (a
    self-intersection always has one), by casting every edge as an Embree ray. Used for
    hexahedral boundaries, where counts of intersecting triangles from pymeshfix also flag
    vertices that merely touch."""
    return len(crossings(surf)[0])


def crossings(surf: pv.PolyData) -> tuple[np.ndarray, np.ndarray]:
    """The crossings of :func:`crossing_edges`: the crossing edges' end points (E, 2) and, for
    each, the points (E, 3) of one triangle it passes through (point indices of ``surf``)."""
    import trimesh

    f = surf.faces.reshape(-1, 4)[:, 1:]
    e = unique_edges(surf)
    p = np.asarray(surf.points, float)
    vec = p[e[:, 1]] - p[e[:, 0]]
    length = np.linalg.norm(vec, axis=1)
    tm = trimesh.Trimesh(p, f, process=False)
    tri, ray, loc = tm.ray.intersects_id(p[e[:, 0]], vec / length[:, None], multiple_hits=True, return_locations=True)
    along = np.linalg.norm(loc - p[e[ray, 0]], axis=1)
    inside = (along > 1e-6 * length[ray]) & (along < length[ray] * (1 - 1e-6))
    own = (f[tri] == e[ray, 0:1]).any(1) | (f[tri] == e[ray, 1:2]).any(1)
    hit, first = np.unique(ray[inside & ~own], return_index=True)
    return e[hit], f[tri[inside & ~own][first]]


def surface_distance(mesh: pv.PolyData, reference: pv.PolyData, max_points: int = 30000, seed: int = 0) -> dict:
    """Symmetric surface distance between a mesh and a reference surface, mm.

    Distances from mesh vertices to the reference and from (up to
    ``max_points``) reference vertices to the mesh, pooled: mean, 95th
    percentile and maximum.
    """
    rng = np.random.default_rng(seed)
    ref_pts = reference.points
    if len(ref_pts) > max_points:
        ref_pts = ref_pts[rng.choice(len(ref_pts), max_points, replace=False)]
    d = np.concatenate([distance_to_surface(mesh.points, reference), distance_to_surface(ref_pts, mesh)])
    return {"mean": float(d.mean()), "p95": float(np.percentile(d, 95)), "max": float(d.max())}

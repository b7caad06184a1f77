"""Contact skins: the articular surfaces a rigid-cartilage model's contact runs on, at the resolution the
contact needs rather than at the hexahedral mesh's.

Why.  ccx's face-to-face contact cuts every slave face by the master's triangles and puts 7 Gauss points on
each piece, one contact element each, and every contact element that touches a moving rigid body is
assembled through that body's MPCs (five terms a degree of freedom).  On the 1 mm articular faces of the
hexahedral meshes that assembly was most of a run: the sample's smoke run had 47 000-84 000 contact
elements, and contact took about 80 % of each Newton iteration (bench/RESULTS.md, "where a run's time
goes").  A rigid cartilage contributes nothing to the deck but its articular surface, and a contact patch of
hundreds of mm^2 under a smooth penalty law does not need 1 mm faces to be resolved: 3 mm triangles stray
from the 1 mm surface by its curvature's sagitta, c^2 / 8R, about 0.05 mm on a 20 mm condyle, a tenth of
the 0.5 mm the cartilage layers overlap under the joint load.

What.  The articular faces of the cartilage's articular layer of hexahedra, remeshed into near-equilateral
triangles of about :data:`SKIN_EDGE_MM` by Voronoi clustering (pyacvd), each the top face (S2) of a wedge
(C3D6) :data:`SKIN_DEPTH_MM` deep into the cartilage.  The wedges share their nodes; where the surface bends
so sharply that a wedge under shared nodes would turn inside out, that wedge stands on nodes of its own along
its face's normal.  The skin is rigid with its bone like the layer it replaces, so only its surface matters.
Deformable cartilage keeps its hexahedra (the contact then runs on their faces).
"""

from __future__ import annotations

import warnings

import numpy as np
import pyvista as pv
from scipy.spatial import cKDTree

from kneemesh_core.geometry import unique_rows
from kneemesh_core.surfaces.distance import SurfaceDistance, closest_points

#: The skin's triangle edge, mm (the sample's smoke run: 86 s of CPU on the 1 mm hexahedral faces, 35 s on
#: 2 mm skins, 19 s on 3 mm skins, forces within 3 % of each other's on the plates).
SKIN_EDGE_MM = 3.0
#: Depth of the wedges under the skin, mm (rigid: only the surface matters; shallow, so that the wedges under
#: a curved surface keep their shape).
SKIN_DEPTH_MM = 0.5
#: The most a node moves to fit the surface in the mean, mm: the sagitta of a skin edge on a 10 mm radius, the
#: tightest curvature of an articular surface; no further where the surface turns sharply, at a blended edge.
MAX_FIT_MM = SKIN_EDGE_MM ** 2 / (8 * 10.0)
#: Linear subdivisions of the surface before clustering (pyacvd needs many more points than clusters).
SUBDIVISIONS = 2


def articular_surface(points: np.ndarray, hexes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The articular surface of a layer of hexahedra (H, 8; C3D8 order, nodes 5-8 on the articular side)
    on ``points`` (P, 3), mm: the points it uses (N, 3), its triangles (2H, 3) into them, and each
    triangle's outward direction (2H, 3), from the hexahedron's bone side to its articular side."""
    hexes = np.asarray(hexes)
    top, bottom = hexes[:, [4, 5, 6, 7]], hexes[:, [0, 1, 2, 3]]
    outward = points[top].mean(1) - points[bottom].mean(1)
    used, local = np.unique(top, return_inverse=True)
    local = local.reshape(-1, 4)
    triangles = np.concatenate([local[:, [0, 1, 2]], local[:, [0, 2, 3]]])
    return points[used], triangles, np.concatenate([outward, outward])


def skin(points: np.ndarray, triangles: np.ndarray, outward: np.ndarray, edge_mm: float = SKIN_EDGE_MM,
         depth_mm: float = SKIN_DEPTH_MM) -> tuple[np.ndarray, np.ndarray]:
    """The contact skin of a triangulated articular surface: ``points`` (N, 3) mm, ``triangles`` (T, 3),
    ``outward`` (T, 3) each triangle's outward direction (any length).  Returns the nodes (M, 3) mm and the
    wedges (W, 6) in C3D6 order: nodes 1-3 ``depth_mm`` under the surface, 4-6 on it (face S2), the
    triangle 1-2-3 running counter-clockwise seen from outside."""
    import pyacvd

    surface = pv.PolyData.from_regular_faces(points, triangles)
    clusters = max(12, int(round(surface.area / (np.sqrt(3) / 2 * edge_mm ** 2))))
    if clusters >= surface.n_points:  # already as coarse as asked
        top, faces = np.asarray(points, float), np.asarray(triangles)
    else:
        with warnings.catch_warnings():  # pyacvd 0.4 calls a pyvista accessor pyvista has deprecated
            warnings.simplefilter("ignore", pv.PyVistaDeprecationWarning)
            clustering = pyacvd.Clustering(surface)
            clustering.subdivide(SUBDIVISIONS)
            clustering.cluster(clusters)
            # the clusters' centroids, put on the surface below (pyacvd moves them with pykdtree, whose OpenMP
            # deadlocks in a process forked from one that has used it: a job's pool)
            remeshed = clustering.create_mesh(moveclus=False)
        faces = np.asarray(remeshed.regular_faces)
        top = closest_points(np.asarray(remeshed.points, float), surface)
        top = _snap_outline(top, faces, points, triangles)
    normal = np.cross(top[faces[:, 1]] - top[faces[:, 0]], top[faces[:, 2]] - top[faces[:, 0]])
    area = 0.5 * np.linalg.norm(normal, axis=1)
    keep = area > 1e-3 * edge_mm ** 2  # no degenerate sliver
    faces, normal = faces[keep], normal[keep]
    # outward as the nearest original triangle's
    nearest = cKDTree(points[triangles].mean(1)).query(top[faces].mean(1))[1]
    inward = np.einsum("ij,ij->i", normal, outward[nearest]) < 0
    faces = np.where(inward[:, None], faces[:, ::-1], faces)
    normal = np.where(inward[:, None], -normal, normal)
    unit = normal / np.linalg.norm(normal, axis=1, keepdims=True)
    node_normal = np.zeros_like(top)
    for k in range(3):
        np.add.at(node_normal, faces[:, k], normal)
    node_normal /= np.linalg.norm(node_normal, axis=1, keepdims=True)
    shift = np.clip(_fit(top, faces, unit, points), -MAX_FIT_MM, MAX_FIT_MM)
    shift[np.unique(_outline(faces))] = 0.0  # the outline stays on the cartilage's edge
    top = top + shift[:, None] * node_normal
    deep = top - depth_mm * node_normal
    # a wedge whose deep face would not face the same way as its top stands on nodes of its own
    deep_normal = np.cross(deep[faces[:, 1]] - deep[faces[:, 0]], deep[faces[:, 2]] - deep[faces[:, 0]])
    own = np.einsum("ij,ij->i", deep_normal, unit) <= 0.5 * np.linalg.norm(deep_normal, axis=1)
    wedges = np.concatenate([faces + len(top), faces], axis=1)
    own_nodes = (top[faces[own]] - depth_mm * unit[own][:, None, :]).reshape(-1, 3)
    wedges[own, :3] = 2 * len(top) + np.arange(3 * own.sum()).reshape(-1, 3)
    nodes = np.concatenate([top, deep, own_nodes])
    used, wedges = np.unique(wedges, return_inverse=True)
    return nodes[used], wedges.reshape(-1, 6)


def _fit(top: np.ndarray, faces: np.ndarray, unit: np.ndarray, surface_points: np.ndarray) -> np.ndarray:
    """How far (mm, outward) each skin node (N,) must move for its facets to fit the surface in the mean
    rather than to cut through it: facets between nodes on a convex surface lie under it by up to their
    sagitta, which on a 40 mm sphere pressed 0.5 mm into a plane cost 3 mm skins 15 % of the force.  The
    mean distance outward from the skin (``top`` (N, 3), ``faces`` (F, 3), outward ``unit`` normals (F, 3))
    to the ``surface_points`` (S, 3) nearest each node."""
    _, cell, closest = SurfaceDistance(pv.PolyData.from_regular_faces(top, faces)).closest(surface_points)
    outward = np.einsum("ij,ij->i", surface_points - closest, unit[cell])
    owner = cKDTree(top).query(surface_points)[1]
    count = np.bincount(owner, minlength=len(top))
    return np.bincount(owner, outward, minlength=len(top)) / np.maximum(count, 1)


def _outline(triangles: np.ndarray) -> np.ndarray:
    """The boundary edges (B, 2) of a triangle surface: the edges of one triangle only."""
    edges = np.sort(np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]]), axis=1)
    unique, count = unique_rows(edges, return_counts=True)
    return unique[count == 1]


def _snap_outline(top: np.ndarray, faces: np.ndarray, points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """The skin's nodes ``top`` (N, 3) with those on its outline moved to the nearest point of the surface's
    own outline (``points`` (P, 3), ``triangles`` (T, 3)): clustering puts a boundary node at its cluster's
    centroid, up to half an edge inside the cartilage's edge, and a plate or a trochlea loses that strip."""
    edges = _outline(triangles)
    on_outline = np.unique(_outline(faces))
    if not len(edges) or not len(on_outline):
        return top
    a, b = points[edges[:, 0]], points[edges[:, 1]]
    # candidates: the outline segments whose ends are nearest; the nearest point on each
    near = cKDTree(np.concatenate([a, b])).query(top[on_outline], k=8)[1] % len(edges)
    p = top[on_outline][:, None, :]
    ab = (b - a)[near]
    t = np.clip(np.einsum("ijk,ijk->ij", p - a[near], ab) / np.maximum(np.einsum("ijk,ijk->ij", ab, ab), 1e-12), 0.0, 1.0)
    foot = a[near] + t[..., None] * ab
    best = np.argmin(np.linalg.norm(foot - p, axis=2), axis=1)
    out = top.copy()
    out[on_outline] = foot[np.arange(len(on_outline)), best]
    return out

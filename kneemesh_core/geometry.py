"""Small vector helpers on arrays of points, shared by the mesher, the blend, the anatomy, the FE
model and the metrics.

All take and return plain arrays in LPS mm; shapes are in each docstring.
"""

from __future__ import annotations

import numpy as np

#: Vectors shorter than this are treated as zero length when normalised.
EPS = 1e-12


def unit(v: np.ndarray) -> np.ndarray:
    """Rows of ``v`` (N, D) scaled to unit length; zero rows stay (near) zero."""
    return v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), EPS)


def unique_rows(a: np.ndarray, return_inverse: bool = False, return_counts: bool = False):
    """``np.unique(a, axis=0, ...)`` for non-negative integer rows (N, K) (edges, faces as vertex ids):
    the same rows in the same (lexicographic) order, inverse and counts, ~8x faster (each row becomes
    one integer, and numpy's 1-D unique needs no lexsort of row views)."""
    a = np.asarray(a)
    dims = tuple(int(m) + 1 for m in a.max(0)) if len(a) else (1,) * a.shape[1]
    out = np.unique(np.ravel_multi_index(tuple(a.T), dims), return_inverse=return_inverse,
                    return_counts=return_counts)
    u, rest = (out[0], out[1:]) if isinstance(out, tuple) else (out, ())
    rows = np.stack(np.unravel_index(u, dims), 1).astype(a.dtype, copy=False)
    return (rows, *rest) if rest else rows


def quad_node_normals(points: np.ndarray, quads: np.ndarray) -> np.ndarray:
    """Unnormalised node normals (P, 3) of a quad surface: the sum of the diagonal cross products of
    the quads (Q, 4) around each node of ``points`` (P, 3); they point to the side from which the
    quads run counter-clockwise."""
    p = points[quads]
    qn = np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 1])
    normal = np.zeros((len(points), 3))
    np.add.at(normal, quads.ravel(), np.repeat(qn, 4, axis=0))
    return normal


def quad_node_areas(points: np.ndarray, quads: np.ndarray) -> np.ndarray:
    """Each node's share (P,) of the area of the quads (Q, 4) around it, a quarter of each quad's
    (two triangles), in the units of ``points`` (P, 3) squared."""
    p = points[quads]
    area = 0.5 * (np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
                  + np.linalg.norm(np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]), axis=1))
    return np.bincount(quads.ravel(), np.repeat(area / 4, 4), minlength=len(points))


def triangle_areas(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """The area (T,) of each triangle (T, 3) of ``points`` (P, 3), in their units squared."""
    p = points[triangles]
    return 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)


def triangle_node_areas(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Each node's share (P,) of the area of the triangles (T, 3) around it, a third of each triangle's, in
    the units of ``points`` (P, 3) squared."""
    return np.bincount(triangles.ravel(), np.repeat(triangle_areas(points, triangles) / 3, 3), minlength=len(points))


def evenly_spread(points: np.ndarray, triangles: np.ndarray, spacing_mm: float) -> np.ndarray:
    """Points (M, 3) mm spread evenly over a triangle surface (``points`` (N, 3) mm, ``triangles`` (T, 3)),
    one per sqrt(3)/2 x ``spacing_mm``^2 of its area (a vertex's share in a mesh of that edge): the
    centroids of the triangles that each such step of the area summed in triangle order ends in.  A mesh
    finer in places (a bone shell under its cartilage) is then fitted as if it were even, and the same
    mesh moved gives the same points moved."""
    area = triangle_areas(points, triangles)
    share = np.sqrt(3) / 2 * spacing_mm**2
    picked = np.unique(np.searchsorted(np.cumsum(area), np.arange(0.5, area.sum() / share) * share))
    return points[triangles[np.minimum(picked, len(triangles) - 1)]].mean(1)


def interpolate_layers(bottom: np.ndarray, top: np.ndarray, layers: int) -> np.ndarray:
    """The nodes of ``layers`` element layers spaced evenly along straight columns from ``bottom``
    to ``top`` (both (P, 3)): ((layers + 1) * P, 3), layer by layer, bottom first."""
    frac = (np.arange(layers + 1) / layers)[:, None, None]
    return (bottom[None] + (top - bottom)[None] * frac).reshape(-1, 3)


#: How far behind its origin a ray starts when what it looks for may already overlap it (a cartilage
#: seated into another, a femur that reaches below a plate's rim), mm: farther than any overlap found.
RAY_BACKOFF_MM = 20.0


def ray_distances(origins: np.ndarray, direction: np.ndarray, points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Distance (mm) along unit ``direction`` (3,) from each origin (K, 3) to the first hit on the
    triangle surface (points (P, 3) mm, triangles (T, 3)); NaN where a ray misses (Embree, trimesh)."""
    import trimesh

    surface = trimesh.Trimesh(points, triangles, process=False)
    loc, index, _ = surface.ray.intersects_location(origins, np.tile(direction, (len(origins), 1)), multiple_hits=False)
    out = np.full(len(origins), np.nan)
    out[index] = (loc - origins[index]) @ direction
    return out


def plane_basis(axis: np.ndarray) -> np.ndarray:
    """(2, 3) orthonormal basis of the plane normal to unit ``axis`` (3,)."""
    e1 = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(axis, e1)])


def grid_quads(ni: int, nj: int) -> np.ndarray:
    """The quads (E, 4) of a structured ``ni`` x ``nj`` grid of points numbered row by row, cell
    (i, j) at row ``i * (nj - 1) + j``."""
    idx = np.arange(ni * nj).reshape(ni, nj)
    return np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], axis=-1).reshape(-1, 4)


def hex_sheet(upper: np.ndarray, quads: np.ndarray, outward: np.ndarray, depth_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """One layer of hexahedra under a quad surface: ``upper`` (N, 3) mm, ``quads`` (E, 4) indexing it,
    the layer ``depth_mm`` deep against unit ``outward`` (3,), the side the surface faces.  Returns the
    nodes (M, 3) that the hexahedra use and the hexahedra (E, 8) in C3D8 order: nodes 1-4 on the deep
    side, 5-8 on the surface (face S2), each quad turned so that its normal points ``outward``."""
    p = upper[quads]
    normal = np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 1])
    quads = np.where((normal @ outward < 0)[:, None], quads[:, ::-1], quads)
    nodes = np.concatenate([upper - depth_mm * np.asarray(outward, float), upper])
    used, hexes = np.unique(np.concatenate([quads, quads + len(upper)], axis=1), return_inverse=True)
    return nodes[used], hexes.reshape(-1, 8)

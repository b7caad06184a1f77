"""Element quality of hex meshes: Verdict scaled Jacobian plus the checks it is blind to."""

from __future__ import annotations

import numpy as np
import pyvista as pv

from kneemesh_core.hexmesh.targets import (MAX_EDGE_RATIO, MAX_FRAC_EDGE_RATIO, MIN_SCALED_JACOBIAN, USABLE_FRAC_BELOW,
                                           USABLE_FRAC_EDGE_RATIO, USABLE_MIN_SCALED_JACOBIAN)
from kneemesh_core.surfaces.metrics import crossing_edges, crossings

#: The 12 edges of a VTK / C3D8 hexahedron.
HEX_EDGES = np.array([[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4], [0, 4], [1, 5], [2, 6], [3, 7]])


#: The articular (S2) face of a C3D8 hexahedron whose nodes 5-8 lie on the articular side, in the order
#: that makes its normal point out of the element (Abaqus and ccx face S2: nodes 5, 8, 7, 6).
ARTICULAR_FACE = [4, 7, 6, 5]


def articular_quads(hexes: np.ndarray) -> np.ndarray:
    """The articular faces (H, 4) of hexahedra (H, 8) in C3D8 order, normals pointing out of them."""
    return np.asarray(hexes)[:, ARTICULAR_FACE]


def to_grid(points: np.ndarray, hexes: np.ndarray) -> pv.UnstructuredGrid:
    """VTK unstructured grid of hexahedra (points (P, 3), hexes (H, 8))."""
    cells = np.hstack([np.full((len(hexes), 1), 8), hexes]).ravel()
    return pv.UnstructuredGrid(cells, np.full(len(hexes), pv.CellType.HEXAHEDRON, np.uint8), points)


def hex_quality(points: np.ndarray, hexes: np.ndarray) -> dict[str, np.ndarray]:
    """Per-element quality arrays.

    ``scaled_jacobian`` is Verdict's (pyvista ``cell_quality``), set to -1 for
    collapsed elements where Verdict would return 1e30; ``collapsed`` flags
    repeated nodes or zero-length edges; ``max_edge_ratio`` is the longest over
    the shortest edge; ``shortest_edge`` in mm.
    """
    grid = to_grid(points, hexes)
    sj = np.asarray(grid.cell_quality("scaled_jacobian").cell_data["scaled_jacobian"], float)
    lengths = np.linalg.norm(points[hexes[:, HEX_EDGES[:, 0]]] - points[hexes[:, HEX_EDGES[:, 1]]], axis=2)
    srt = np.sort(hexes, 1)
    repeated = (srt[:, 1:] == srt[:, :-1]).any(1)
    collapsed = repeated | (lengths.min(1) < 1e-9)
    sj = np.where(collapsed | (sj > 1.5), -1.0, sj)
    ratio = lengths.max(1) / np.maximum(lengths.min(1), 1e-12)
    return {"scaled_jacobian": sj, "collapsed": collapsed, "max_edge_ratio": ratio, "shortest_edge": lengths.min(1)}


def summary(q: dict[str, np.ndarray], ring: np.ndarray | None = None) -> dict:
    """The quality figures of ``report.json`` (the key names spell the targets of :mod:`.targets`)."""
    sj = q["scaled_jacobian"]
    out = {
        "n_elements": int(len(sj)),
        "min_scaled_jacobian": round(float(sj.min()), 4),
        "frac_sj_below_0_5": round(float((sj < MIN_SCALED_JACOBIAN).mean()), 6),
        "inverted": int((sj <= 0).sum()),
        "collapsed": int(q["collapsed"].sum()),
        "max_edge_ratio": round(float(q["max_edge_ratio"].max()), 3),
        "frac_edge_ratio_above_6": round(float((q["max_edge_ratio"] > MAX_EDGE_RATIO).mean()), 6),
        "shortest_edge_mm": round(float(q["shortest_edge"].min()), 4),
    }
    if ring is not None:
        out["sj_by_ring"] = {
            str(r): {"min": round(float(sj[ring == r].min()), 4), "frac_below_0_5": round(float((sj[ring == r] < MIN_SCALED_JACOBIAN).mean()), 5)}
            for r in range(min(int(ring.max()) + 1, 3))
        }
    return out


def boundary_crossings(points: np.ndarray, hexes: np.ndarray) -> int:
    """Edges of the mesh's triangulated boundary that pass through another boundary face: a mesh
    whose elements are all fine can still fold over itself (two stretches of the cartilage edge
    projected onto overlapping bone), which no element metric sees."""
    return crossing_edges(boundary_surface(to_grid(points, hexes)))


def crossing_nodes(points: np.ndarray, hexes: np.ndarray) -> np.ndarray:
    """The nodes (indices into ``points``) of the boundary edges and faces that cross, as
    :func:`boundary_crossings` counts them."""
    surf = boundary_surface(to_grid(points, hexes))
    edges, tris = crossings(surf)
    return np.unique(np.asarray(surf.point_data["vtkOriginalPointIds"])[np.concatenate([edges.ravel(), tris.ravel()])])


def boundary_surface(grid: pv.UnstructuredGrid) -> pv.PolyData:
    """The triangulated outer boundary of a hex grid."""
    return grid.extract_surface(algorithm="dataset_surface").triangulate()


def _within(s: dict, min_sj: float, max_frac_below: float | None, max_frac_edge_ratio: float) -> bool:
    """A :func:`summary`'s mesh: every element at least ``min_sj``, at most ``max_frac_below`` of
    them below MIN_SCALED_JACOBIAN (None: implied by ``min_sj``) and ``max_frac_edge_ratio`` beyond
    the edge ratio, nothing collapsed or inverted, and (where it was measured) a boundary that does
    not cross itself."""
    return (s["min_scaled_jacobian"] >= min_sj and (max_frac_below is None or s["frac_sj_below_0_5"] <= max_frac_below)
            and s["collapsed"] == 0 and s["inverted"] == 0 and s["frac_edge_ratio_above_6"] <= max_frac_edge_ratio
            and s.get("self_intersections", 0) == 0)


def usable(s: dict) -> bool:
    """Short of the gate (perhaps) but usable for finite elements (:mod:`.targets`): shipped for review."""
    return _within(s, USABLE_MIN_SCALED_JACOBIAN, USABLE_FRAC_BELOW, USABLE_FRAC_EDGE_RATIO)


def passes_gate(s: dict) -> bool:
    """The pre-blending gate (:mod:`.targets`): every element at MIN_SCALED_JACOBIAN or better, the
    edge ratio for all but a sliver of elements, nothing collapsed, inverted or crossing."""
    return _within(s, MIN_SCALED_JACOBIAN, None, MAX_FRAC_EDGE_RATIO)

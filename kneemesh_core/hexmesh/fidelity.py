"""How faithfully a hex mesh represents its cartilage: volume, coverage, articular surface deviation."""

from __future__ import annotations

import numpy as np
import pyvista as pv
from scipy.spatial import cKDTree

from kneemesh_core.hexmesh.blend import node_rings
from kneemesh_core.hexmesh.extrude import HexMesh
from kneemesh_core.hexmesh.quality import boundary_surface, to_grid
from kneemesh_core.hexmesh.targets import (COVERAGE_TOL_MM, MAX_DEVIATION_MEDIAN_MM, MAX_DEVIATION_P95_MM,
                                           MIN_COVERAGE, VOLUME_TOL)
from kneemesh_core.surfaces.distance import distance_to_surface

#: The figures of a :func:`fidelity` result that the targets read, headline figures of a shipped mesh.
FIGURES = ("volume_ml", "volume_error", "coverage", "surface_deviation_mm")


def fidelity(hm: HexMesh, surface: pv.PolyData, label_ml: float, unblended: HexMesh | None = None,
             rings: int = 0) -> dict:
    """Volume against the label, area coverage of the reconstructed surface, articular deviation.

    Parameters
    ----------
    surface : the reconstructed cartilage surface the mesh was built from.
    label_ml : cartilage label volume, ml.
    unblended, rings : for a blended mesh, the mesh before its blend and the rings of columns from
        the edge that the blend reshapes: the result gains ``beyond_rim``, the coverage and the
        articular deviation read away from that rim (see :func:`beyond_rim_checks`).
    """
    grid = to_grid(hm.points, hm.hexes)
    volume_ml = float(grid.volume) / 1000.0
    outer = boundary_surface(grid)
    cells = surface.compute_cell_sizes(length=False, volume=False)
    area = np.asarray(cells.cell_data["Area"])
    centres = np.asarray(surface.cell_centers().points, float)
    covered = distance_to_surface(centres, outer) <= COVERAGE_TOL_MM
    coverage = float(area[covered].sum() / area.sum())
    top = hm.node_layer == hm.node_layer.max()
    dev = distance_to_surface(hm.points[top], surface)
    out = {
        "volume_ml": round(volume_ml, 4),
        "label_volume_ml": round(label_ml, 4),
        "volume_error": round((volume_ml - label_ml) / label_ml, 4),
        "coverage": round(coverage, 4),
        "surface_deviation_mm": _deviation(dev),
    }
    if unblended is not None:
        out["beyond_rim"] = _beyond_rim(hm, unblended, surface, centres, area, covered, rings)
    return out


def _deviation(dev: np.ndarray) -> dict:
    return {"median": round(float(np.median(dev)), 4), "p95": round(float(np.percentile(dev, 95)), 4),
            "max": round(float(dev.max()), 4)}


def _beyond_rim(hm: HexMesh, unblended: HexMesh, surface: pv.PolyData, centres: np.ndarray, area: np.ndarray,
                covered: np.ndarray, rings: int) -> dict:
    """The fidelity targets read on a blended mesh away from the rim its blend reshapes on purpose.

    The 45 deg edge blend (Gibbons et al. 2022, 2.4.2) brings the articular surface of the outer
    ``rings`` rings of columns down to the bone and reaches out along it: by design those columns
    leave the label's rim wall and the edge of its articular surface (and add a wedge of volume
    outside the label).  A patch of the reconstructed surface (centres (N, 3) mm, area (N,) mm^2)
    counts as covered where the blended mesh covers it (``covered``), or where the mesh before the
    blend covered it and its nearest node there lies in a rim column; the articular deviation is that
    of the top nodes of the columns beyond the rim.  What the blend must not do is what this
    catches: move the articular surface, or uncover cartilage, beyond the rim."""
    P = int((unblended.node_layer == 0).sum())
    ring = node_rings(unblended.hexes[unblended.layer == 0][:, :4], unblended.node_edge[:P])
    rim = ring < rings
    excused = np.zeros(len(centres), bool)
    rest = np.flatnonzero(~covered)
    if rest.size:
        skin = boundary_surface(to_grid(unblended.points, unblended.hexes))
        was = distance_to_surface(centres[rest], skin) <= COVERAGE_TOL_MM
        column = cKDTree(unblended.points).query(centres[rest[was]])[1] % P
        excused[rest[was]] = rim[column]
    top = np.flatnonzero(hm.node_layer == hm.node_layer.max())
    inner = top[~rim[top % P]]
    dev = distance_to_surface(hm.points[inner], surface) if inner.size else np.zeros(1)
    return {"rings": int(rings), "rim_area_fraction": round(float(area[excused].sum() / area.sum()), 4),
            "coverage": round(float(area[covered | excused].sum() / area.sum()), 4),
            "surface_deviation_mm": _deviation(dev)}


def fidelity_checks(f: dict) -> dict[str, bool]:
    """Each fidelity target of a :func:`fidelity` result, met or not."""
    return {"volume": abs(f["volume_error"]) <= VOLUME_TOL, **beyond_rim_checks(f)}


def passes_fidelity(f: dict) -> bool:
    return all(fidelity_checks(f).values())


def beyond_rim_checks(r: dict) -> dict[str, bool]:
    """The coverage and deviation targets, met or not, of a ``beyond_rim`` result (or of a
    :func:`fidelity` result: the targets but the volume)."""
    return {"coverage": r["coverage"] >= MIN_COVERAGE,
            "deviation_median": r["surface_deviation_mm"]["median"] <= MAX_DEVIATION_MEDIAN_MM,
            "deviation_p95": r["surface_deviation_mm"]["p95"] <= MAX_DEVIATION_P95_MM}


def short_of_footprint(f: dict) -> bool:
    """Whether a mesh misses fidelity by covering too little: coverage or volume too low."""
    return f["coverage"] < MIN_COVERAGE or f["volume_error"] < -VOLUME_TOL

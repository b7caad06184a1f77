"""How faithfully a hex mesh represents its cartilage: volume, coverage, articular surface deviation."""

from __future__ import annotations

import numpy as np
import pyvista as pv

from kneemesh_core.hexmesh.extrude import HexMesh
from kneemesh_core.hexmesh.quality import boundary_surface, to_grid
from kneemesh_core.hexmesh.targets import (COVERAGE_TOL_MM, MAX_DEVIATION_MEDIAN_MM, MAX_DEVIATION_P95_MM,
                                           MIN_COVERAGE, VOLUME_TOL)
from kneemesh_core.surfaces.metrics import distance_to_surface, within


def fidelity(hm: HexMesh, surface: pv.PolyData, label_ml: float) -> dict:
    """Volume against the label, area coverage of the reconstructed surface, articular deviation.

    Parameters
    ----------
    surface : the reconstructed cartilage surface the mesh was built from.
    label_ml : cartilage label volume, ml.
    """
    grid = to_grid(hm.points, hm.hexes)
    volume_ml = float(grid.volume) / 1000.0
    outer = boundary_surface(grid)
    cells = surface.compute_cell_sizes(length=False, volume=False)
    area = np.asarray(cells.cell_data["Area"])
    covered = within(np.asarray(surface.cell_centers().points, float), outer, COVERAGE_TOL_MM)
    coverage = float(area[covered].sum() / area.sum())
    top = hm.node_layer == hm.node_layer.max()
    dev = distance_to_surface(hm.points[top], surface)
    return {
        "volume_ml": round(volume_ml, 4),
        "label_volume_ml": round(label_ml, 4),
        "volume_error": round((volume_ml - label_ml) / label_ml, 4),
        "coverage": round(coverage, 4),
        "surface_deviation_mm": {"median": round(float(np.median(dev)), 4), "p95": round(float(np.percentile(dev, 95)), 4),
                                 "max": round(float(dev.max()), 4)},
    }


def fidelity_checks(f: dict) -> dict[str, bool]:
    """Each fidelity target of a :func:`fidelity` result, met or not."""
    return {"volume": abs(f["volume_error"]) <= VOLUME_TOL, "coverage": f["coverage"] >= MIN_COVERAGE,
            "deviation_median": f["surface_deviation_mm"]["median"] <= MAX_DEVIATION_MEDIAN_MM,
            "deviation_p95": f["surface_deviation_mm"]["p95"] <= MAX_DEVIATION_P95_MM}


def passes_fidelity(f: dict) -> bool:
    return all(fidelity_checks(f).values())


def short_of_footprint(f: dict) -> bool:
    """Whether a mesh misses fidelity by covering too little: coverage or volume too low."""
    return f["coverage"] < MIN_COVERAGE or f["volume_error"] < -VOLUME_TOL

"""Agreement between two results of the same knee (e.g. from manual and from predicted labels), as
the paper measures it (Gibbons et al. 2022, Figure 2 and Table 2):

* Dice of each tissue's labels (:func:`kneemesh_core.metrics.labels.dice`);
* articular surface deviation: from each articular node of mesh A to the nearest point of mesh B's
  articular surface, kept only where that direction lies within 20 deg of A's surface normal there
  (the rest are edges that do not face each other); the kept fraction is the *percent nodal coverage*;
* contact mechanics over flexion: RMS differences of medial and lateral contact area and pressure,
  also as a fraction of the min-max range of A's curve.
"""

from __future__ import annotations

import numpy as np
import pyvista as pv

from kneemesh_core.fe.results import loaded
from kneemesh_core.geometry import quad_node_normals, unit
from kneemesh_core.hexmesh.quality import articular_quads
from kneemesh_core.surfaces.distance import closest_points

#: Rays further than this from the normal are not counted (the paper's 20 deg), deg.
MAX_RAY_ANGLE_DEG = 20.0


def articular_surface(grid: pv.UnstructuredGrid) -> tuple[np.ndarray, np.ndarray]:
    """The articular surface of a KneeMesh cartilage mesh: points (P, 3) mm and quads (Q, 4) into
    them, the articular (top, S2) faces of the outermost layer of hexahedra."""
    layer = np.asarray(grid.cell_data["layer"])
    quads = articular_quads(np.asarray(grid.cells_dict[pv.CellType.HEXAHEDRON])[layer == layer.max()])
    used, local = np.unique(quads, return_inverse=True)
    return np.asarray(grid.points)[used], local.reshape(-1, 4)


def surface_deviation(a: pv.UnstructuredGrid, b: pv.UnstructuredGrid,
                      max_angle_deg: float = MAX_RAY_ANGLE_DEG) -> dict:
    """Deviation of A's articular surface from B's: ``distances_mm`` (N,) of the nodes kept, their
    ``median``/``p75``/``p95``/``max``, and ``coverage`` (the fraction kept, 0-1)."""
    pa, qa = articular_surface(a)
    pb, qb = articular_surface(b)
    normals = unit(quad_node_normals(pa, qa))
    surface = pv.PolyData(pb, np.hstack([np.full((len(qb), 1), 4), qb]).ravel()).triangulate()
    d = closest_points(pa, surface) - pa
    dist = np.linalg.norm(d, axis=1)
    cos = np.abs(np.einsum("ij,ij->i", d, normals)) / np.maximum(dist, 1e-12)
    keep = (dist < 1e-6) | (cos >= np.cos(np.radians(max_angle_deg)))
    kept = dist[keep]
    stats = {k: round(float(f(kept)), 4) if len(kept) else None
             for k, f in (("median", np.median), ("p75", lambda v: np.percentile(v, 75)),
                          ("p95", lambda v: np.percentile(v, 95)), ("max", np.max))}
    return {"nodes": int(len(pa)), "coverage": round(float(keep.mean()), 4), **stats, "distances_mm": kept}


def _curve(results: dict, side: str, key: str) -> tuple[np.ndarray, np.ndarray]:
    inc = [r for r in loaded(results["increments"]) if r.get("flexion_deg") is not None]
    return np.array([r["flexion_deg"] for r in inc]), np.array([r[side][key] for r in inc], float)


def contact_differences(a: dict, b: dict) -> dict:
    """RMS differences over the flexion both runs reached, of medial and lateral contact area
    (mm^2), mean and peak pressure (MPa), each also as a fraction of the min-max range of A's curve
    (the paper's Table 2); B is interpolated at A's flexion angles."""
    out = {}
    for side in ("medial", "lateral"):
        for key in ("area_mm2", "mean_pressure_mpa", "peak_pressure_mpa"):
            xa, ya = _curve(a, side, key)
            xb, yb = _curve(b, side, key)
            if len(xa) < 2 or len(xb) < 2:
                out[f"{side}_{key}"] = None
                continue
            order = np.argsort(xb)
            span = (xa >= xb.min() - 1e-6) & (xa <= xb.max() + 1e-6)
            diff = ya[span] - np.interp(xa[span], xb[order], yb[order])
            rms = float(np.sqrt(np.mean(diff ** 2))) if span.any() else None
            rng = float(ya.max() - ya.min())
            out[f"{side}_{key}"] = {"rms": None if rms is None else round(rms, 4),
                                    "rms_of_range": None if rms is None or rng == 0 else round(rms / rng, 4),
                                    "flexion_deg": [round(float(xa[span].min()), 2), round(float(xa[span].max()), 2)]
                                    if span.any() else None}
    return out

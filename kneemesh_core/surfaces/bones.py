"""FE-ready rigid bone shells: closed, manifold, uniform triangles (ACVD)."""

from __future__ import annotations

import warnings

import numpy as np
import pyacvd
import pymeshfix
import pyvista as pv
from pyvista.core.errors import PyVistaDeprecationWarning
from vtkmodules.vtkCommonCore import reference
from vtkmodules.vtkCommonDataModel import vtkStaticCellLocator

from kneemesh_core.errors import KneeMeshError
from kneemesh_core.surfaces.isosurface import orient_outward

#: Area per vertex of an ideal triangulation with edge e: two equilateral triangles per vertex.
_AREA_PER_VERTEX = np.sqrt(3) / 2


def _meshfix(surf: pv.PolyData) -> pv.PolyData:
    """MeshFix repair (Attene 2010): removes self-intersections, degeneracies, fills holes."""
    faces = surf.faces.reshape(-1, 4)[:, 1:]
    mf = pymeshfix.MeshFix(np.asarray(surf.points, float), faces)
    mf.repair(joincomp=False, remove_smallest_components=True)
    return pv.PolyData.from_regular_faces(mf.points, mf.faces)


def closest_points(points: np.ndarray, surface: pv.PolyData) -> np.ndarray:
    """Closest point (N, 3) on ``surface`` to each of ``points`` (N, 3), mm."""
    loc = vtkStaticCellLocator()
    loc.SetDataSet(surface)
    loc.BuildLocator()
    out = np.empty_like(points)
    cp = [0.0, 0.0, 0.0]
    cell, sub, d2 = reference(0), reference(0), reference(0.0)
    for i, p in enumerate(points):  # VTK has no batched closest-point query; ~3k points per bone
        loc.FindClosestPoint(p, cp, cell, sub, d2)
        out[i] = cp
    return out


def bone_mesh(surface: pv.PolyData, edge_mm: float = 3.0) -> pv.PolyData:
    """Uniform, closed, manifold bone shell from a reconstructed bone surface.

    Voronoi clustering (ACVD, Valette et al. 2008) of the smoothed isosurface
    to about ``edge_mm`` mean edge length (this replaces the paper's 80%
    decimation for bones: clustering is the stronger reduction), then MeshFix
    repair (Attene 2010: clustering can pinch a thin region into a
    non-manifold edge or a self-intersection), normals outward.

    Parameters
    ----------
    surface : closed triangle surface in LPS mm.
    edge_mm : target mean edge length, mm.
    """
    if edge_mm <= 0.2 or edge_mm > 20:
        raise KneeMeshError("bad_option", f"bone edge length {edge_mm} mm is outside 0.2-20 mm.")
    n_clusters = int(surface.area / (_AREA_PER_VERTEX * edge_mm**2))
    if n_clusters < 50:
        raise KneeMeshError("bone_too_small", f"bone surface of {surface.area:.0f} mm^2 is too small for {edge_mm} mm elements.")
    with warnings.catch_warnings():  # pyacvd reads a PyVista attribute PyVista has deprecated: not the user's concern
        warnings.simplefilter("ignore", PyVistaDeprecationWarning)
        clus = pyacvd.Clustering(surface)
        while clus.mesh.n_points < 8 * n_clusters:
            clus.subdivide(2)
        clus.cluster(n_clusters)
    # pyacvd's own ``moveclus`` ray-casts each centroid against its 1000 nearest
    # faces (seconds per bone); a closest-point projection onto the smooth
    # surface does the same job in ~0.1 s and cuts the mean distance to the
    # label by ~15%.
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PyVistaDeprecationWarning)
        clustered = clus.create_mesh(moveclus=False)
    clustered.points = closest_points(np.asarray(clustered.points, float), surface)
    shell = _meshfix(clustered)
    return orient_outward(shell)

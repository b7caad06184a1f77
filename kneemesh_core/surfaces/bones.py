"""FE-ready rigid bone shells: closed, manifold, uniform triangles (ACVD)."""

from __future__ import annotations

import warnings

import numpy as np
import pyacvd
import pymeshfix
import pyvista as pv
from pyvista.core.errors import PyVistaDeprecationWarning
from scipy.spatial import cKDTree

from kneemesh_core.errors import KneeMeshError
from kneemesh_core.surfaces.distance import closest_points
from kneemesh_core.surfaces.isosurface import orient_outward

#: Area per vertex of an ideal triangulation with edge e: two equilateral triangles per vertex.
_AREA_PER_VERTEX = np.sqrt(3) / 2
#: Vertices of the (subdivided) isosurface per cluster of the finest edge, at least, before a graded clustering.
_FINE_VERTICES = 4


def _meshfix(surf: pv.PolyData) -> pv.PolyData:
    """MeshFix repair (Attene 2010): removes self-intersections, degeneracies, fills holes."""
    faces = surf.faces.reshape(-1, 4)[:, 1:]
    mf = pymeshfix.MeshFix(np.asarray(surf.points, float), faces)
    mf.repair(joincomp=False, remove_smallest_components=True)
    return pv.PolyData.from_regular_faces(mf.points, mf.faces)


def bone_mesh(surface: pv.PolyData, edge_mm: float = 3.0, *, fine_edge_mm: float | None = None,
              fine_near: np.ndarray | None = None, fine_band_mm: float = 3.0) -> pv.PolyData:
    """Closed, manifold bone shell from a reconstructed bone surface.

    Voronoi clustering (ACVD, Valette et al. 2008) of the smoothed isosurface
    to about ``edge_mm`` mean edge length (this replaces the paper's 80%
    decimation for bones: clustering is the stronger reduction), then MeshFix
    repair (Attene 2010: clustering can pinch a thin region into a
    non-manifold edge or a self-intersection), normals outward.

    Within ``fine_band_mm`` of the points ``fine_near`` (the bone's cartilage) the
    edges are ``fine_edge_mm`` instead, graded back to ``edge_mm`` over as much
    again (ACVD weighted by the target density, edge^-2).  A facet spans its
    corners as a chord: a 3 mm facet over the concave corner where a cartilage
    rim meets its bone stands up to 1 mm off the smooth surface, and the rim
    then lies inside the shell although it lies on its label; at the
    cartilage's element size the chord follows the bone within ~0.1 mm.

    Parameters
    ----------
    surface : closed triangle surface in LPS mm.
    edge_mm : target mean edge length, mm.
    fine_edge_mm : target edge length near ``fine_near``, mm (None: uniform ``edge_mm``).
    fine_near : (N, 3) points in LPS mm.
    """
    if edge_mm <= 0.2 or edge_mm > 20:
        raise KneeMeshError("bad_option", f"bone edge length {edge_mm} mm is outside 0.2-20 mm.")
    fine = fine_edge_mm is not None and fine_near is not None and len(fine_near) and fine_edge_mm < edge_mm
    n_clusters = int(surface.area / (_AREA_PER_VERTEX * edge_mm**2))
    if n_clusters < 50:
        raise KneeMeshError("bone_too_small", f"bone surface of {surface.area:.0f} mm^2 is too small for {edge_mm} mm elements.")
    with warnings.catch_warnings():  # pyacvd reads a PyVista attribute PyVista has deprecated: not the user's concern
        warnings.simplefilter("ignore", PyVistaDeprecationWarning)
        density = None
        if fine:
            # enough vertices that the finest clusters still gather a few each
            fine_area = _AREA_PER_VERTEX * fine_edge_mm**2
            while surface.area / surface.n_points > fine_area / _FINE_VERTICES:
                surface = surface.subdivide(1, "linear")
            d = cKDTree(fine_near).query(np.asarray(surface.points), distance_upper_bound=2 * fine_band_mm + 1)[0]
            edge = fine_edge_mm + (edge_mm - fine_edge_mm) * np.clip((d - fine_band_mm) / fine_band_mm, 0.0, 1.0)
            density = (edge_mm / edge) ** 2
        clus = pyacvd.Clustering(surface)
        while density is None and clus.mesh.n_points < 8 * n_clusters:
            clus.subdivide(2)
        if density is not None:
            # ACVD equalises the clusters' summed vertex weights (each vertex's share of the area): weighting the
            # area by the target density gives clusters of area ~ edge^2 (pyacvd's own ``weights`` argument
            # leaves its areas as they are)
            area = clus.area.ravel() / 3  # each triangle's area counted at its 3 corners
            n_clusters = int((area / (_AREA_PER_VERTEX * edge**2)).sum())
            clus.area = clus.area * density.reshape(clus.area.shape)
            clus.wcent = clus.wcent * density[:, None]
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

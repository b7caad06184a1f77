"""Meniscus surrogates: a rigid wedge on the periphery of each tibial plate, part of the tibia.

Why.  Without menisci the femur of a quasi-static flexion slides off the convex lateral plate:
on the sample knee the femur moved 9 mm posteriorly and rotated 18 deg by 27 deg of flexion,
the lateral condyle left the plate's posterior rim and the run stopped at 30 deg, whatever the
ligament and stabiliser settings.  In a knee the menisci cup
the condyles; the paper's model left them out and calibrated its ligaments to make up for them.

What.  Each meniscus is a C-shaped ring of hexahedra (one layer, rigid with the tibia) that
follows the plate's outline from :data:`INNER_MM` inside its rim to :data:`OUTER_MM` beyond
it, open where the rim faces the other plate (the horns' insertions on the intercondylar
eminence).  Its upper surface rises from the plate at the inner edge to at most :data:`HEIGHT_MM`
above it at the rim, and nowhere comes closer than :data:`CLEARANCE_MM` to the seated femoral
cartilage in any pose of the flexion path (the femur turned about its flexion axis, every
:data:`POSE_STEP_DEG`, from anatomical extension on: :func:`kneemesh_core.fe.model.ring_path`): it
carries nothing while the condyles follow that path and takes load only
when a condyle slides or rolls off it, as a meniscus restrains the condyle it holds.  (Shaped to the
image pose alone, the ring lifted the flexed lateral condyle off its plate: the condyles' profile
under the ring changes with flexion.)  The surface is shaped to the
knee's own condyles, so it fits knees of every size without a template.

The ring's grid is built here on arrays (no meshing library makes a swept ring of a height
field; :func:`kneemesh_core.geometry.hex_sheet` gives it its layer); the heights come from Embree ray
casts (trimesh).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi
from scipy.spatial import cKDTree

from kneemesh_core.geometry import RAY_BACKOFF_MM, grid_quads, hex_sheet, plane_basis, ray_distances

#: How far the wedge reaches over the plate from its rim, and beyond the rim, mm (a meniscus
#: covers the outer third or so of a plate; its body is 8-12 mm wide).
INNER_MM, OUTER_MM = 6.0, 3.0
#: Peripheral height above the plate at most, mm (meniscal rims stand 5-7 mm).
HEIGHT_MM = 6.0
#: Gap left below the seated femoral cartilage, mm, and the flexion path's step, deg.
CLEARANCE_MM, POSE_STEP_DEG = 0.3, 10.0
#: Depth of the hexahedral layer, mm (the ring is rigid: only its upper surface matters).
LAYER_MM = 1.0
#: No wedge where the rim's outward direction is within this angle of the other plate's centre.
OPEN_DEG = 50.0
#: Spacing of the ring's nodes along the rim and across it, mm.
SPACING_MM = 1.5
#: Smoothing of the rim's outward directions along the rim, mm (Gaussian sigma).
NORMAL_SMOOTHING_MM = 4.0
#: Outline raster: pixel, and the closing radius that bridges the gaps between projected nodes, mm.
PIXEL_MM, CLOSING_MM = 0.4, 1.6


def outline(uv: np.ndarray, spacing_mm: float = SPACING_MM) -> np.ndarray:
    """The outline of a plate's projected nodes ``uv`` (P, 2), mm: a closed polygon (N, 2) running
    counter-clockwise, smoothed and resampled every ``spacing_mm`` along its length."""
    from skimage.measure import find_contours

    lo = uv.min(0) - 2 * CLOSING_MM - 1.0
    ij = np.round((uv - lo) / PIXEL_MM).astype(int)
    mask = np.zeros(ij.max(0) + int(2 * CLOSING_MM / PIXEL_MM) + 3, bool)
    mask[ij[:, 0], ij[:, 1]] = True
    r = int(np.ceil(CLOSING_MM / PIXEL_MM))
    disk = np.hypot(*np.mgrid[-r:r + 1, -r:r + 1]) <= r
    mask = ndi.binary_fill_holes(ndi.binary_erosion(ndi.binary_dilation(mask, disk), disk, border_value=0))
    labels, n = ndi.label(mask)
    if n > 1:
        mask = labels == 1 + int(np.argmax(ndi.sum(mask, labels, range(1, n + 1))))
    contour = max(find_contours(np.pad(mask, 1).astype(float), 0.5), key=len)[:-1] - 1.0
    pts = contour * PIXEL_MM + lo
    pts = ndi.gaussian_filter1d(pts, sigma=1.0 / PIXEL_MM, axis=0, mode="wrap")  # 1 mm: the pixel steps go
    closed = np.vstack([pts, pts[:1]])
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(closed, axis=0), axis=1))])
    s = np.arange(0.0, arc[-1], arc[-1] / max(8, round(arc[-1] / spacing_mm)))
    out = np.stack([np.interp(s, arc, closed[:, k]) for k in (0, 1)], axis=1)
    area = 0.5 * np.sum(out[:, 0] * np.roll(out[:, 1], -1) - np.roll(out[:, 0], -1) * out[:, 1])
    return out if area > 0 else out[::-1]


def wedge(plate: tuple[np.ndarray, np.ndarray], femoral: list[tuple[np.ndarray, np.ndarray]], axis: np.ndarray,
          other_centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A meniscus surrogate on one tibial plate.

    ``plate``: the plate's articular surface as (points (P, 3) mm, triangles (T, 3)); ``femoral``:
    the femoral cartilage's in each pose the ring must clear (the seated femur first); ``axis``: the tibia's proximal axis (3,); ``other_centre``: the other plate's centre
    (3,) mm, which the ring leaves open.  Returns nodes (N, 3) mm and C3D8 hexahedra (E, 8) indexing
    them, nodes 1-4 below and 5-8 on the upper (contact) surface; empty arrays if no rim is left.
    """
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    basis = plane_basis(axis)
    pts, tris = plate
    uv = pts @ basis.T
    ring = outline(uv)
    tangent = np.roll(ring, -1, axis=0) - np.roll(ring, 1, axis=0)
    normal = np.stack([tangent[:, 1], -tangent[:, 0]], axis=1)  # outward on a counter-clockwise outline
    normal = ndi.gaussian_filter1d(normal / np.linalg.norm(normal, axis=1, keepdims=True), NORMAL_SMOOTHING_MM / SPACING_MM,
                                   axis=0, mode="wrap")  # smoother than the outline, so that stations cross less
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    toward = (other_centre - pts.mean(0)) @ basis.T
    keep = normal @ (toward / np.linalg.norm(toward)) < np.cos(np.radians(OPEN_DEG))
    if keep.all() or not keep.any():
        start = 0
        runs = [np.arange(len(ring))] if keep.all() else []
    else:  # the longest run of kept rim points, read round the closed outline
        start = int(np.argmin(keep))
        rolled = np.roll(keep, -start)
        edges = np.flatnonzero(np.diff(np.concatenate([[0], rolled.astype(int), [0]])))
        runs = [np.arange(a, b) for a, b in zip(edges[::2], edges[1::2])]
    if not runs:
        return np.zeros((0, 3)), np.zeros((0, 8), int)
    run = (max(runs, key=len) + start) % len(ring)
    if len(run) < 4:
        return np.zeros((0, 3)), np.zeros((0, 8), int)
    stations = np.linspace(-INNER_MM, OUTER_MM, int(round((INNER_MM + OUTER_MM) / SPACING_MM)) + 1)
    q = ring[run][:, None, :] + stations[None, :, None] * normal[run][:, None, :]  # (I, J, 2)
    flat = q.reshape(-1, 2) @ basis  # on the plane through the origin, (I*J, 3)
    along = pts @ axis
    top_of_box = along.max() + 50.0
    base = top_of_box - ray_distances(flat + top_of_box * axis, -axis, pts, tris)
    miss = ~np.isfinite(base)
    if miss.any():  # beyond the plate: the height of its nearest node
        base[miss] = along[cKDTree(uv).query(q.reshape(-1, 2)[miss])[1]]
    below = RAY_BACKOFF_MM  # rays start below the plate, so a femur that overlaps it is found too
    gaps = np.stack([ray_distances(flat + (base - below)[:, None] * axis, axis, *f) for f in femoral])
    gap = np.where(np.isfinite(gaps).any(0), np.min(np.nan_to_num(gaps, nan=np.inf), axis=0), np.nan) - below
    rise = HEIGHT_MM * np.clip((stations + INNER_MM) / INNER_MM, 0.0, 1.0)
    top = base + np.minimum(np.nan_to_num(gap, nan=np.inf) - CLEARANCE_MM, np.tile(rise, len(run)))
    quad = grid_quads(*q.shape[:2])
    corners = q.reshape(-1, 2)[quad]  # (E, 4, 2)
    area = 0.5 * np.sum(corners[:, :, 0] * np.roll(corners[:, :, 1], -1, axis=1)
                        - np.roll(corners[:, :, 0], -1, axis=1) * corners[:, :, 1], axis=1)
    a, b = np.roll(corners, -1, axis=1) - corners, np.roll(corners, -2, axis=1) - np.roll(corners, -1, axis=1)
    convex = np.all((a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]) * np.sign(np.median(area)) > 0, axis=1)
    quad = quad[convex]  # where a concave rim makes the stations cross, the ring leaves a gap
    return hex_sheet(flat + top[:, None] * axis, quad, axis, LAYER_MM)

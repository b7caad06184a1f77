"""The prefemoral surrogate: a sheet over the anterior femur, above the trochlear cartilage, on
which the patella rests in extension.

Why.  In full extension the patella sits proximal to the trochlea, on the prefemoral (supratrochlear)
fat pad and synovium over the anterior femur, and slides down onto the trochlear cartilage as the knee
flexes.  A model with cartilage contact only gives that part of the patella nothing to rest on: on OAI
9357383_00m the patellar cartilage spans 13.7-46.7 mm up the femoral shaft and the trochlear cartilage
ends at 18.7 mm, so the patella touched the femur with its distal tip alone, rocked on the cartilage's
edge, and ccx cut its increments back for 25 min at 6.6 deg (115 contact elements switching on and off
at every iteration).

What.  A height field seen from the patella: rays along the patella's posterior axis find the femur's
bone and its cartilage under a grid that covers the patella's outline (and :data:`MARGIN_MM` round it);
where they meet bone and no cartilage within :data:`REACH_MM` of the patella, the sheet stands off the bone by the femoral cartilage's
median thickness (it continues the trochlear surface up the femur), rising from the bone at the
cartilage's edge over :data:`TAPER_MM` so that it meets the cartilage's blended rim without a step.
One layer of hexahedra, rigid with the femur; with the femoral cartilage it is the master of the
patellofemoral contact.  It carries nothing where the patella has left it (flexion moves
the patella down onto the trochlea).

The grid is built on arrays (no library meshes a height field into hexahedra); the heights come from
Embree ray casts (trimesh).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi

from kneemesh_core.geometry import RAY_BACKOFF_MM, grid_quads, hex_sheet, plane_basis, ray_distances

#: Grid spacing, mm.  ccx's contact cost grows with the faces whether they touch or not: a 1 mm sheet
#: (1678 faces, then in a pair of its own) took the sample's smoke run from 55 to 76 s.
SPACING_MM = 2.0
#: How far the sheet reaches beyond the patella's outline, mm.
MARGIN_MM = 3.0
#: Over this distance from the cartilage's edge the sheet rises from the bone to its full standoff, mm.
TAPER_MM = 4.0
#: Bone farther than this behind the patellar cartilage, beyond the sheet's standoff, is not under the patella, mm.
REACH_MM = 8.0
#: Depth of the hexahedral layer, mm (rigid: only its surface matters).
LAYER_MM = 1.0


def sheet(patella: tuple[np.ndarray, np.ndarray], toward: np.ndarray, bone: tuple[np.ndarray, np.ndarray],
          cartilage: tuple[np.ndarray, np.ndarray], standoff_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """The prefemoral sheet of a seated femur.

    ``patella``, ``bone`` and ``cartilage``: the patellar cartilage's articular surface, the femur's
    bone surface and its cartilage's articular surface, each (points (N, 3) mm, triangles (T, 3));
    ``toward``: unit (3,), from the patella towards the femur; ``standoff_mm``: the sheet's height
    over the bone.  Returns nodes (M, 3) mm and C3D8 hexahedra (E, 8), nodes 5-8 on the surface that
    faces the patella (empty arrays where the cartilage covers the whole outline).
    """
    toward = np.asarray(toward, float) / np.linalg.norm(toward)
    basis = plane_basis(toward)
    uv = patella[0] @ basis.T
    lo, hi = uv.min(0) - MARGIN_MM, uv.max(0) + MARGIN_MM
    u, v = (np.arange(a, b + SPACING_MM, SPACING_MM) for a, b in zip(lo, hi))
    grid = np.stack(np.meshgrid(u, v, indexing="ij"), axis=-1)  # (I, J, 2)
    start = float((patella[0] @ toward).min()) - RAY_BACKOFF_MM  # in front of the patella: no surface missed
    origins = grid.reshape(-1, 2) @ basis + start * toward
    to_bone, to_cartilage, to_patella = (ray_distances(origins, toward, *surface).reshape(grid.shape[:2])
                                         for surface in (bone, cartilage, patella))
    covered = np.isfinite(to_cartilage) & ~(to_bone < to_cartilage)
    # under the patella (or within the margin of where it is): bone within reach behind its cartilage
    near = ndi.binary_dilation(np.isfinite(to_patella) & (to_bone - standoff_mm - to_patella < REACH_MM),
                               iterations=int(np.ceil(MARGIN_MM / SPACING_MM)))
    open_bone = np.isfinite(to_bone) & near & ~covered
    # distance from the cartilage's edge, which lies between its last grid point and the sheet's first
    edge = (ndi.distance_transform_edt(~covered, sampling=SPACING_MM) - SPACING_MM / 2 if covered.any()
            else np.full(covered.shape, np.inf))
    height = to_bone - standoff_mm * np.clip(edge / TAPER_MM, 0.0, 1.0)  # along ``toward`` from the origins
    cells = open_bone[:-1, :-1] & open_bone[1:, :-1] & open_bone[1:, 1:] & open_bone[:-1, 1:]
    quads = grid_quads(*open_bone.shape)[cells.ravel()]
    if not len(quads):
        return np.zeros((0, 3)), np.zeros((0, 8), int)
    upper = origins + np.nan_to_num(height.reshape(-1))[:, None] * toward
    return hex_sheet(upper, quads, -toward, LAYER_MM)

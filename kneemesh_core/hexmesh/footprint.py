"""The cartilage footprint in the parameter plane: a cleaned mask, its signed distance, filled heights."""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass

import numpy as np
from scipy import ndimage as ndi
from skimage.morphology import remove_small_holes, remove_small_objects

from kneemesh_core.hexmesh.rays import HeightField


@dataclass
class Footprint:
    """Where the cartilage is, seen along the rays.

    Attributes
    ----------
    grid : the :class:`HeightField` grid it lives on.
    inside : (ns, nt) bool.
    sdf : (ns, nt) signed distance to the footprint contour, mm (negative inside).
    bone, joint : (ns, nt) surface heights, mm, extended outside the footprint by
        their nearest inside value so that contour nodes can be placed.
    fine : (ns, nt) bool, the footprint with its contour smoothed over a quarter of the
        distance: it keeps tails and tips too narrow for the lattice, which are meshed finer.
    """

    grid: HeightField
    inside: np.ndarray
    sdf: np.ndarray
    bone: np.ndarray
    joint: np.ndarray
    edge_thickness: float  # thickness at the contour, mm
    fine: np.ndarray

    def sample(self, field: np.ndarray, st: np.ndarray) -> np.ndarray:
        """Bilinear sample of a grid field at parameter points (N, 2)."""
        idx = self.grid.index(st).T
        return ndi.map_coordinates(field, idx, order=1, mode="nearest")

    def gradient(self, st: np.ndarray) -> np.ndarray:
        """(N, 2) gradient of the signed distance at parameter points."""
        gs, gt = self._sdf_gradient
        return np.stack([self.sample(gs, st), self.sample(gt, st)], -1)

    @functools.cached_property
    def _sdf_gradient(self) -> tuple[np.ndarray, np.ndarray]:
        """The signed distance's gradient on the grid, computed once: the extrusion's untangling
        samples it for every candidate slide of the contour nodes (over a hundred times)."""
        return tuple(np.gradient(self.sdf, self.grid.step))

    def thickness(self) -> np.ndarray:
        """(N,) cartilage thickness, mm, along the rays inside the footprint."""
        return (self.joint - self.bone)[self.inside]

    def holes(self) -> int:
        """Holes in the footprint (full-thickness defects the mesh keeps open)."""
        return len(enclosed_holes(self.inside)[1])

    def only(self, mask: np.ndarray) -> "Footprint":
        """A footprint of its own where ``mask`` (ns, nt) bool is (a piece to mesh apart), with its own
        signed distance."""
        return dataclasses.replace(self, inside=mask, sdf=signed_distance(mask, self.grid.step), fine=mask)


def signed_distance(mask: np.ndarray, step: float) -> np.ndarray:
    """Signed distance (mm, negative inside) to the contour of a 2-D mask on a grid of ``step`` mm,
    smoothed over a grid step so that bilinear samples find its zero level between the cells."""
    inside_d = ndi.distance_transform_edt(mask) * step
    outside_d = ndi.distance_transform_edt(~mask) * step
    return ndi.gaussian_filter(np.where(mask, -(inside_d - 0.5 * step), outside_d - 0.5 * step), 1.0).astype(float)


def enclosed_holes(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Holes of a 2-D mask: the labelled background (same shape) and the labels of the background
    components that do not touch the array border."""
    lab, n = ndi.label(~mask)
    border = np.r_[lab[0], lab[-1], lab[:, 0], lab[:, -1]]
    return lab, np.setdiff1d(np.arange(1, n + 1), border)


def find_footprint(hf: HeightField, *, min_thickness: float, edge_fraction: float, max_slope_deg: float,
                   fold_slope_deg: float, s_scale: np.ndarray | float = 1.0, min_area: float = 4.0,
                   min_hole: float = 1.0, smooth_mm: float = 1.0) -> Footprint:
    """Footprint of a height field.

    Rays longer than three median thicknesses graze the cartilage sheet and
    do not count either.  Rays thinner than ``min_thickness`` mm, or than ``edge_fraction`` of the
    median thickness, do not count: the rounded rim of a reconstructed
    cartilage tapers to nothing, and columns that thin make flat, sheared
    elements; the mesh edge is a short wall instead (blending slopes it later).
    Where the rim rolls over (either surface steeper than ``max_slope_deg``
    to the rays), the footprint is trimmed from the outside in: a column
    there would be sheared, and a quad stretched, beyond what a scaled
    Jacobian of 0.5 allows.  Where either surface is steeper than
    ``fold_slope_deg`` the rays jump between two sheets (a fold seen from the
    axis) or fall off a wall, and the footprint is cut there.
    ``s_scale`` converts an s-step into mm along the surface (cylinder: R0 / r).
    Islands smaller than
    ``min_area`` mm^2 are dropped; holes smaller than ``min_hole`` mm^2 are
    filled, before and after the contour is smoothed with a Gaussian of
    ``smooth_mm``: ray noise, or a pinhole smaller than the elements could
    ring with a pillow (the caller passes about twice an element's area).
    Larger holes (full-thickness defects) stay.  ``fine`` is smoothed over a quarter of
    ``smooth_mm``.  The thresholds have no defaults here: the
    mesher's :class:`.mesher.HexOptions` is their one home.
    """
    step = hf.step
    px = step * step
    thick = np.where(hf.hit, hf.joint - hf.bone, 0.0)
    max_thickness = np.inf
    if (thick > min_thickness).any():
        median = float(np.median(thick[thick > min_thickness]))
        min_thickness = max(min_thickness, edge_fraction * median)
        max_thickness = 3.0 * median  # a ray this long grazes the sheet: not a thickness
    mask = hf.hit & (thick > min_thickness) & (thick < max_thickness)
    valid = hf.hit & (thick > 0)
    _, (ii, jj) = ndi.distance_transform_edt(~valid, return_indices=True)
    joint_filled = hf.joint[ii, jj]
    bone_filled = hf.bone[ii, jj]
    steep = np.zeros_like(mask)
    jump = np.zeros_like(mask)
    for height in (joint_filled, bone_filled):
        gs, gt = np.gradient(height, step)
        slope = np.hypot(gs * s_scale, gt)
        steep |= slope > np.tan(np.deg2rad(max_slope_deg))
        jump |= slope > np.tan(np.deg2rad(fold_slope_deg))
    rim = ndi.binary_propagation(~mask, mask=~mask | steep)
    # where neighbouring rays jump between two sheets of cartilage (a fold seen from the
    # axis), the footprint is cut: each sheet ends in its own edge instead of a bridge
    mask &= ~rim & ~ndi.binary_dilation(jump, iterations=2)
    mask = remove_small_objects(mask, max_size=max(int(min_area / px), 1))
    mask = remove_small_holes(mask, max_size=max(int(min_hole / px), 1))
    smoothed = [ndi.gaussian_filter(mask.astype(np.float32), sigma / step) > 0.5 if sigma > 0 else mask
                for sigma in (smooth_mm, smooth_mm / 4)]
    mask, fine = (remove_small_holes(m, max_size=max(int(min_hole / px), 1)) for m in smoothed)
    # heights outside the hits: those of the nearest ray that hit
    return Footprint(hf, mask, signed_distance(mask, step), bone_filled, joint_filled, min_thickness, fine)

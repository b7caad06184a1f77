"""Bone-side and articular heights along every ray of a fine 2-D grid (Embree ray casting)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyvista as pv
import trimesh


@dataclass
class HeightField:
    """Heights (mm along each ray) of the two cartilage surfaces on a regular 2-D grid.

    Attributes
    ----------
    s0, t0 : parameter coordinates of grid cell (0, 0), mm.
    step : grid spacing, mm.
    bone, joint : (ns, nt) heights of the bone-side and articular surfaces (NaN where the ray misses).
    hit : (ns, nt) bool, the ray crosses the cartilage.
    """

    s0: float
    t0: float
    step: float
    bone: np.ndarray
    joint: np.ndarray
    hit: np.ndarray

    def coords(self, shape: tuple[int, int] | None = None) -> np.ndarray:
        """(ns, nt, 2) parameter coordinates of the grid points."""
        ns, nt = shape or self.hit.shape
        s = self.s0 + self.step * np.arange(ns)
        t = self.t0 + self.step * np.arange(nt)
        return np.stack(np.meshgrid(s, t, indexing="ij"), -1)

    def index(self, st: np.ndarray) -> np.ndarray:
        """Continuous grid index (N, 2) of parameter points (N, 2)."""
        return (st - np.array([self.s0, self.t0])) / self.step


def intersector(surface: pv.PolyData) -> trimesh.Trimesh:
    """A trimesh of the closed cartilage surface; its ``.ray`` uses Embree when embreex is installed."""
    faces = surface.faces.reshape(-1, 4)[:, 1:]
    return trimesh.Trimesh(np.asarray(surface.points), faces, process=False)


def crossings(tm: trimesh.Trimesh, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance along each ray (N, 3 origins and unit directions) to where it first enters the
    surface and to where it next leaves it (inf where it does not).

    One batched Embree call, no Python loop over rays.  A ray that starts
    inside the surface has no entry; its exit is then the first one.
    """
    n = len(origins)
    enter = np.full(n, np.inf)
    leave = np.full(n, np.inf)
    loc, ray, tri = tm.ray.intersects_location(origins, np.ascontiguousarray(dirs), multiple_hits=True)
    if len(ray):
        dist = np.einsum("ij,ij->i", loc - origins[ray], dirs[ray])
        entering = np.einsum("ij,ij->i", tm.face_normals[tri], dirs[ray]) < 0
        np.minimum.at(enter, ray[entering], dist[entering])
        start = np.where(np.isfinite(enter), enter, -np.inf)
        later = ~entering & (dist > start[ray])
        np.minimum.at(leave, ray[later], dist[later])
    return enter, leave


def first_crossing(tm: trimesh.Trimesh, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance along each ray (N, 3 origins and unit directions) to the first surface it meets
    (inf where none), and whether that crossing leaves the surface (N,) bool: the ray started inside.
    One batched Embree call."""
    dist = np.full(len(origins), np.inf)
    leaving = np.zeros(len(origins), bool)
    tri, ray, loc = tm.ray.intersects_id(origins, np.ascontiguousarray(dirs), multiple_hits=False, return_locations=True)
    if len(ray):
        dist[ray] = np.einsum("ij,ij->i", loc - origins[ray], dirs[ray])
        leaving[ray] = np.einsum("ij,ij->i", tm.face_normals[tri], dirs[ray]) > 0
    return dist, leaving


def cast(surface: pv.PolyData, domain, st_points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Heights where the domain's rays at ``st_points`` (N, 2) enter (bone side) and then leave
    (articular surface) the closed cartilage surface; NaN where they miss."""
    origins, dirs, h0 = domain.rays(st_points)
    enter, leave = crossings(intersector(surface), origins, np.asarray(dirs, float))
    ok = np.isfinite(enter) & np.isfinite(leave)
    return np.where(ok, enter + h0, np.nan), np.where(ok, leave + h0, np.nan)


def height_field(surface: pv.PolyData, domain, points_2d: np.ndarray, step: float, margin: float = 2.0) -> HeightField:
    """Cast a ray at every point of a ``step``-spaced grid covering ``points_2d`` (N, 2) plus ``margin`` mm."""
    lo = points_2d.min(0) - margin
    hi = points_2d.max(0) + margin
    ns, nt = (np.ceil((hi - lo) / step).astype(int) + 1).tolist()
    hf = HeightField(float(lo[0]), float(lo[1]), step, np.empty(0), np.empty(0), np.empty(0))
    st = hf.coords((ns, nt)).reshape(-1, 2)
    bone, joint = cast(surface, domain, st)
    hf.bone = bone.reshape(ns, nt)
    hf.joint = joint.reshape(ns, nt)
    hf.hit = np.isfinite(hf.bone)
    return hf

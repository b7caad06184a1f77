"""Projection domains: a 2-D parameter plane (s, t) in mm and a ray through every point of it.

A plane for each tibial plate (rays along the plane normal), a cylinder about
the femoral condylar axis for the femoral cartilage and about the patella's
superior-inferior axis for the patellar cartilage (rays radial from the axis);
an implausible cylinder fit falls back to a plane (:mod:`.mesher`).  Along a ray, ``h`` is the height above the plane
or the distance from the axis, mm; ``position(s, t, h)`` is the 3-D LPS point.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares


@dataclass
class PlaneDomain:
    """Plane through ``centre`` with in-plane axes ``e1``, ``e2`` and normal ``n`` (bone to joint)."""

    centre: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    n: np.ndarray
    start: float = -40.0  # rays start this far below the plane, inside the bone

    @classmethod
    def fit(cls, points: np.ndarray, bone_centre: np.ndarray) -> "PlaneDomain":
        """Least-squares plane of cartilage points (N, 3), normal pointing away from the bone."""
        c = points.mean(0)
        w, v = np.linalg.eigh(np.cov((points - c).T))
        n = v[:, 0]
        if np.dot(c - bone_centre, n) < 0:
            n = -n
        e1 = v[:, 2]
        e2 = np.cross(n, e1)
        return cls(c, e1, e2, n)

    def to_2d(self, p: np.ndarray) -> np.ndarray:
        """(N, 2) parameter coordinates of LPS points (N, 3)."""
        d = p - self.centre
        return np.stack([d @ self.e1, d @ self.e2], -1)

    def rays(self, st: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Origins (N, 3), unit directions (N, 3) and the height of each origin (N,)."""
        o = self.centre + st[:, :1] * self.e1 + st[:, 1:2] * self.e2 + self.start * self.n
        return o, np.broadcast_to(self.n, o.shape), np.full(len(st), self.start)

    def position(self, st: np.ndarray, h: np.ndarray) -> np.ndarray:
        return self.centre + st[..., :1] * self.e1 + st[..., 1:2] * self.e2 + h[..., None] * self.n

    def describe(self) -> dict:
        return {"kind": "plane", "centre_mm": self.centre.round(3).tolist(), "normal": self.n.round(5).tolist()}


@dataclass
class CylinderDomain:
    """Cylinder about the axis through ``origin`` along ``axis``; ``s`` is arc length at ``radius``."""

    origin: np.ndarray
    axis: np.ndarray
    e1: np.ndarray  # the seam direction (angle 0), away from the cartilage
    e2: np.ndarray
    radius: float

    @classmethod
    def fit(cls, points: np.ndarray, ml_hint: np.ndarray) -> "CylinderDomain":
        """Robust least-squares cylinder through femoral cartilage points (N, 3).

        Starts from the medial-lateral direction ``ml_hint`` and a circle fit in
        the plane across it; a soft-L1 loss keeps the trochlea (farther from the
        axis than the condyles) from pulling the fit.
        """
        a0 = ml_hint / np.linalg.norm(ml_hint)
        b1 = np.cross(a0, [0.0, 0.0, 1.0] if abs(a0[2]) < 0.9 else [0.0, 1.0, 0.0])
        b1 /= np.linalg.norm(b1)
        b2 = np.cross(a0, b1)
        c = points.mean(0)
        q = np.stack([(points - c) @ b1, (points - c) @ b2], -1)
        # algebraic circle fit (Kasa) as the starting point
        A = np.c_[2 * q, np.ones(len(q))]
        sol, *_ = np.linalg.lstsq(A, (q**2).sum(1), rcond=None)
        centre2 = sol[:2]
        r0 = float(np.sqrt(sol[2] + centre2 @ centre2))

        def unpack(x):
            d = a0 + x[0] * b1 + x[1] * b2
            d /= np.linalg.norm(d)
            o = c + x[2] * b1 + x[3] * b2
            return d, o, x[4]

        def resid(x):
            d, o, r = unpack(x)
            v = points - o
            return np.linalg.norm(v - np.outer(v @ d, d), axis=1) - r

        fit = least_squares(resid, [0.0, 0.0, centre2[0], centre2[1], r0], loss="soft_l1", f_scale=2.0)
        d, o, r = unpack(fit.x)
        if np.dot(d, a0) < 0:
            d = -d
        # seam: the middle of the widest angular gap in the cartilage
        u1 = np.cross(d, b2)
        u1 /= np.linalg.norm(u1)
        u2 = np.cross(d, u1)
        v = points - o
        ang = np.sort(np.arctan2(v @ u2, v @ u1))
        gaps = np.diff(np.r_[ang, ang[0] + 2 * np.pi])
        k = int(np.argmax(gaps))
        seam = ang[k] + gaps[k] / 2
        e1 = np.cos(seam) * u1 + np.sin(seam) * u2
        e2 = np.cross(d, e1)
        return cls(o, d, e1, e2, float(abs(r)))

    def _angle(self, st: np.ndarray) -> np.ndarray:
        return st[..., 0] / self.radius

    def to_2d(self, p: np.ndarray) -> np.ndarray:
        v = p - self.origin
        ang = np.mod(np.arctan2(v @ self.e2, v @ self.e1), 2 * np.pi)
        return np.stack([ang * self.radius, v @ self.axis], -1)

    def _direction(self, st: np.ndarray) -> np.ndarray:
        a = self._angle(st)[..., None]
        return np.cos(a) * self.e1 + np.sin(a) * self.e2

    def rays(self, st: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        o = self.origin + st[:, 1:2] * self.axis
        return o, self._direction(st), np.zeros(len(st))

    def position(self, st: np.ndarray, h: np.ndarray) -> np.ndarray:
        return self.origin + st[..., 1:2] * self.axis + h[..., None] * self._direction(st)

    def describe(self) -> dict:
        return {"kind": "cylinder", "origin_mm": self.origin.round(3).tolist(), "axis": self.axis.round(5).tolist(),
                "radius_mm": round(self.radius, 3)}

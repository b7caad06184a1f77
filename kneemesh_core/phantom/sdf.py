"""Signed distance primitives on broadcast coordinate arrays (mm, float32).

Negative inside, positive outside; exact for the simple primitives, close to
exact away from smooth-union seams.  Hand-written because no imaging library
offers implicit solids on voxel grids; each is a few array operations.
"""

from __future__ import annotations

import numpy as np


def ellipsoid(u, v, w, c, r):
    """SDF of an ellipsoid centred at ``c`` with radii ``r`` (mm), first-order accurate near the surface.

    The gradient-normalised bound ``k0 (k0 - 1) / k1`` (k0 = |p/r|, k1 = |p/r^2|):
    the plain ``(k0 - 1) min(r)`` would thicken shells on the long axes by r_max/r_min.
    """
    du, dv, dw = (u - c[0]), (v - c[1]), (w - c[2])
    k0 = np.sqrt((du / r[0]) ** 2 + (dv / r[1]) ** 2 + (dw / r[2]) ** 2)
    k1 = np.sqrt((du / r[0] ** 2) ** 2 + (dv / r[1] ** 2) ** 2 + (dw / r[2] ** 2) ** 2)
    return k0 * (k0 - 1.0) / np.maximum(k1, 1e-6)


def capsule_w(u, v, w, c, r, w0, w1):
    """Capsule along the w axis through (c[0], c[1]) from w0 to w1, radius r."""
    ww = np.clip(w, w0, w1)
    return np.sqrt((u - c[0]) ** 2 + (v - c[1]) ** 2 + (w - ww) ** 2) - r


def rounded_cylinder_u(u, v, w, c, radius, half_len, rounding):
    """Cylinder along u centred at ``c``: sagittal radius, half length in u, edge rounding (mm)."""
    dr = np.sqrt((v - c[1]) ** 2 + (w - c[2]) ** 2) - (radius - rounding)
    du = np.abs(u - c[0]) - (half_len - rounding)
    outside = np.sqrt(np.maximum(dr, 0) ** 2 + np.maximum(du, 0) ** 2)
    return outside + np.minimum(np.maximum(dr, du), 0) - rounding


def elliptic_slab_w(u, v, w, c, ru, rv, w0, w1, rounding):
    """Elliptic cylinder along w (radii ru, rv) between w0 and w1, rounded edges."""
    k0 = np.sqrt(((u - c[0]) / ru) ** 2 + ((v - c[1]) / rv) ** 2)
    dr = (k0 - 1.0) * min(ru, rv) + rounding
    dw = np.abs(w - 0.5 * (w0 + w1)) - (0.5 * (w1 - w0) - rounding)
    outside = np.sqrt(np.maximum(dr, 0) ** 2 + np.maximum(dw, 0) ** 2)
    return outside + np.minimum(np.maximum(dr, dw), 0) - rounding


def smooth_union(a, b, k):
    """Polynomial smooth minimum with blend width k (mm)."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


def subtract(a, b):
    """a minus b."""
    return np.maximum(a, -b)

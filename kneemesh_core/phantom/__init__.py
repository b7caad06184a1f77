"""Synthetic knee phantoms: OAI-like sagittal 3D DESS images with canonical labels.

A phantom is deterministic per ``(seed, side, severity)``.  Geometry is that of
OAI's SAG_3D_DESS: 384 x 384 x 160 voxels of 0.3646 x 0.3646 x 0.7 mm, index
axes pointing posterior, inferior and to the patient's right, and the knee
placed off the scanner isocentre on its own side (right knees at LPS x < 0).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from kneemesh_core.errors import KneeMeshError
from kneemesh_core.io import write_image
from kneemesh_core.phantom.anatomy import KneeParams, build_knee, sample_features
from kneemesh_core.phantom.contrast import synthesize

SIZE_IJK = (384, 384, 160)
SPACING_MM = (0.3645833, 0.3645833, 0.7)
#: Columns: i -> posterior (+y), j -> inferior (-z), k -> patient right (-x).
DIRECTION = (0.0, 0.0, -1.0, 1.0, 0.0, 0.0, 0.0, -1.0, 0.0)


class _Grid:
    """Maps voxel index positions of the phantom grid to the knee frame (u lateral, v anterior, w superior; mm)."""

    shape = (SIZE_IJK[2], SIZE_IJK[1], SIZE_IJK[0])
    spacing_zyx = (SPACING_MM[2], SPACING_MM[1], SPACING_MM[0])

    def __init__(self, origin, knee, side: str, rotation_deg: float):
        self.origin, self.knee, self.side = origin, knee, side
        t = np.deg2rad(rotation_deg)
        self.c, self.s = np.float32(np.cos(t)), np.float32(np.sin(t))

    def uvw(self, k: np.ndarray, j: np.ndarray, i: np.ndarray):
        """Broadcastable (u, v, w) of index positions along numpy axes (k, j, i)."""
        sk, sj, si = self.spacing_zyx
        x = (np.float32(self.origin[0] - self.knee[0]) - np.float32(sk) * k)[:, None, None]
        y = (np.float32(self.origin[1] - self.knee[1]) + np.float32(si) * i)[None, None, :]
        w = (np.float32(self.origin[2] - self.knee[2]) - np.float32(sj) * j)[None, :, None]
        u0 = -x if self.side == "right" else x  # lateral: patient's right in a right knee
        v0 = -y  # anterior
        return self.c * u0 + self.s * v0, -self.s * u0 + self.c * v0, w


def make_phantom(seed: int, side: str = "right", severity: int = 0,
                 features: bool = True) -> tuple[sitk.Image, sitk.Image, KneeParams]:
    """Build one phantom knee; ``features=False`` leaves out the OA and habitus features of
    :func:`.anatomy.sample_features` (the knee as it was before they were added).

    Returns
    -------
    image : SimpleITK.Image, int16 DESS-like intensities.
    labels : SimpleITK.Image, uint8 canonical labels 1..7, same geometry.
    params : the sampled :class:`KneeParams`.
    """
    if side not in ("left", "right"):
        raise KneeMeshError("bad_side", f"side {side!r} is not one of left, right.")
    if severity not in (0, 1, 2, 3):
        raise KneeMeshError("bad_severity", f"severity {severity!r} is not one of 0, 1, 2, 3.")
    rng = np.random.default_rng([seed, 0 if side == "right" else 1, severity])
    p = KneeParams.sample(rng, severity)
    if features:
        p = sample_features(p, np.random.default_rng([seed, 0 if side == "right" else 1, severity, 1]))
    I, J, K = SIZE_IJK
    si, sj, sk = SPACING_MM
    # knee joint centre in LPS mm, and the FOV centred near it
    knee = np.array([(-1 if side == "right" else 1) * rng.uniform(55, 85), rng.uniform(-10, 30), rng.uniform(-20, 20)])
    fov_c = knee + rng.uniform(-4, 4, size=3)
    origin = (fov_c[0] + sk * (K - 1) / 2, fov_c[1] - si * (I - 1) / 2, fov_c[2] + sj * (J - 1) / 2)
    grid = _Grid(origin, knee, side, p.rotation_deg)
    fields = build_knee(grid, p, rng)
    intensity = synthesize(fields, (sk, sj, si), rng)

    def to_image(arr: np.ndarray) -> sitk.Image:
        im = sitk.GetImageFromArray(arr)
        im.SetSpacing(SPACING_MM)
        im.SetOrigin(tuple(float(o) for o in origin))
        im.SetDirection(DIRECTION)
        return im

    image = to_image(np.clip(intensity, 0, 32767).astype(np.int16))
    labels = to_image(fields.labels)
    return image, labels, p


def write_phantom(out_dir: str | os.PathLike, seed: int, side: str = "right", severity: int = 0) -> dict[str, Path]:
    """Write ``image.nii.gz`` and ``labels.nii.gz`` for one phantom into ``out_dir``."""
    image, labels, _ = make_phantom(seed, side, severity)
    out = Path(out_dir)
    return {
        "image": write_image(image, out / "image.nii.gz"),
        "labels": write_image(labels, out / "labels.nii.gz"),
    }

"""Shared fixtures: real label maps from ../shared, phantoms built once per session."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT.parent / "shared" / "data" / "real"
PYMSKT_RIGHT = REAL / "pymskt" / "labels" / "right_knee_example.nrrd"
PYMSKT_LEFT = REAL / "pymskt" / "labels" / "Par_Rec_T2_Test_T2-label.nrrd"
OAI = REAL / "oai_labels"
SAMPLE = ROOT / "kneemesh" / "data" / "right_knee_example.nrrd"


def real(path: Path) -> Path:
    if not path.exists():
        pytest.skip(f"real data not available: {path}")
    return path


def mirror_lr(image: sitk.Image) -> sitk.Image:
    """Mirror a volume through the patient's sagittal plane (LPS x -> -x), keeping a right-handed grid.

    The voxel axis closest to LPS x is flipped and origin/direction are set so
    that every voxel lands at its mirrored physical position.
    """
    d = np.asarray(image.GetDirection()).reshape(3, 3)
    s = np.asarray(image.GetSpacing())
    o = np.asarray(image.GetOrigin())
    n = np.asarray(image.GetSize())
    a = int(np.argmax(np.abs(d[0])))  # ITK axis along x
    m = np.diag([-1.0, 1.0, 1.0])
    f = np.eye(3)
    f[a, a] = -1
    c = np.zeros(3)
    c[a] = n[a] - 1
    arr = sitk.GetArrayFromImage(image)
    arr = np.flip(arr, axis=2 - a).copy()
    out = sitk.GetImageFromArray(arr)
    out.SetSpacing(tuple(s))
    out.SetDirection(tuple((m @ d @ f).ravel()))
    out.SetOrigin(tuple(m @ o + m @ d @ (s * c)))
    return out


@pytest.fixture(scope="session")
def phantoms():
    """(side, severity, seed, features) -> (image, labels) built on first use; ``features=False``
    is the knee before the OA and habitus features (the geometry a regression case was found on)."""
    from kneemesh_core.phantom import make_phantom

    cache: dict = {}

    def get(side: str = "right", severity: int = 0, seed: int = 7, features: bool = True):
        key = (seed, side, severity, features)
        if key not in cache:
            image, labels, _ = make_phantom(seed, side, severity, features=features)
            cache[key] = (image, labels)
        return cache[key]

    return get

"""DESS-like contrast for a phantom knee: tissue intensities, partial volume, bias, Rician noise.

OAI's sagittal 3D DESS uses water excitation: fluid is brightest, cartilage
bright, muscle intermediate, fat and marrow dark, cortex, menisci and tendons
darkest.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi

from kneemesh_core.phantom.anatomy import KneeFields
from kneemesh_core.tissues import BONES, CARTILAGES, LABEL

#: Mean relative intensities (water-excitation DESS, echo sum).
INTENSITY = {
    "air": 0.0,
    "fat": 0.09,
    "muscle": 0.27,
    "marrow": 0.11,
    "cortex": 0.02,
    "cartilage": 0.58,
    "fluid": 0.95,
    "meniscus": 0.05,
}


def synthesize(f: KneeFields, spacing_zyx: tuple[float, float, float], rng: np.random.Generator) -> np.ndarray:
    """Intensity volume (float32, about 0..1000) on the labels' grid.

    Parameters
    ----------
    spacing_zyx : voxel spacing in numpy axis order, mm.
    """
    level = {k: v * rng.uniform(0.9, 1.1) for k, v in INTENSITY.items()}
    img = np.zeros(f.labels.shape, dtype=np.float32)
    leg = f.envelope_sdf < 0
    img[leg] = level["muscle"]
    img[leg & (f.envelope_sdf > -6.0)] = level["fat"]
    for bone in BONES:
        d = f.bone_sdf[bone]
        inside = f.labels == LABEL[bone]
        img[inside] = level["marrow"]
        img[inside & (d > -1.3)] = level["cortex"]
    img[f.fibula] = level["marrow"]
    cart = np.isin(f.labels, [LABEL[c] for c in CARTILAGES])
    img[cart] = level["cartilage"]
    # synovial fluid: a film around the cartilage, in the joint only
    film = ndi.binary_dilation(cart, iterations=2) & (f.labels == 0) & ~f.fibula & leg
    img[film] = level["fluid"]
    img[f.meniscus] = level["meniscus"]
    # partial volume at the tissue borders
    sigma = [0.35 / s for s in spacing_zyx]
    img = ndi.gaussian_filter(img, sigma)
    # multiplicative bias field: a smooth low-order polynomial
    zz, yy, xx = (np.linspace(-1, 1, n, dtype=np.float32) for n in img.shape)
    a = rng.uniform(-0.15, 0.15, size=4)
    bias = np.exp(a[0] * zz[:, None, None] + a[1] * yy[None, :, None] + a[2] * xx[None, None, :]
                  + a[3] * yy[None, :, None] * xx[None, None, :])
    img *= bias.astype(np.float32)
    # Rician noise: magnitude of a complex signal with Gaussian noise
    sd = np.float32(rng.uniform(0.015, 0.035))
    n1 = rng.standard_normal(img.shape, dtype=np.float32) * sd
    n2 = rng.standard_normal(img.shape, dtype=np.float32) * sd
    img = np.sqrt((img + n1) ** 2 + n2**2)
    return img * np.float32(1000.0)

"""Training slices synthesised from label maps: random contrast, DESS-like contrast, the paper's augmentation.

No real DESS image with labels is reachable, so the network learns from real
anatomy (manual OAI label maps, pymskt maps, phantoms) dressed in randomised
contrast, after SynthSeg (Billot et al. 2023): a network that never sees one
contrast twice has to learn the shapes.  Most slices (:func:`random_contrast`)
give every sub-tissue (marrow, cortex, cartilage, fluid film, subcutaneous
fat, air, soft tissue around the bones, random pseudo-tissues) a uniformly
random grey; the rest (:data:`P_DESS`, :func:`dess_like`) draw tissue
intensities around water-excitation DESS contrast (fluid brightest, cartilage
bright, muscle intermediate, marrow and fat dark, cortex darkest, grainy or
flat marrow, a background tissue often as dark as marrow).  In either, the
bones' cortex is a rim of its own grey only part of the time (:data:`P_CORTEX`):
a bone must be found by its shape, not by its outline.  Both then pass
through one acquisition (:func:`acquire`): texture, partial-volume blur, a
bias field, a coarser acquisition along one axis and Rician noise.  The
geometry is augmented before the contrast is drawn, as in the paper: rotation
up to 30 deg half the time, elastic and grid distortion and
brightness/contrast/gamma changes up to 30 % of the time.

All functions work on one 2-D slice (H, W) in the network's classes
(:data:`.preprocess.NET_CLASSES`) and return float32 intensities; :func:`synthesize`
and :func:`acquire` normalise them as at inference (:func:`.preprocess.normalise`).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi

from kneemesh_core.segmentation.preprocess import normalise

BONES, CARTILAGES = (1, 2, 3), (4, 5, 6)
#: (low, high) of each tissue's mean relative intensity: DESS-like, widened.
RANGES = {"marrow": (0.04, 0.3), "cortex": (0.0, 0.08), "cartilage": (0.35, 0.8), "fluid": (0.65, 1.0),
          "background": (0.0, 0.5)}
#: Probability that a slice's bones get a cortex rim of their own grey.  Always drawing one
#: (the model of 2026-12-01) taught the network to find a bone by its rim: on a rendering with one
#: grey per tissue it left a tenth of the femur and tibia as background, and the same image with a
#: one-voxel dark rim drawn on the bones gave femur 0.962 -> 0.980, tibia 0.842 -> 0.980.
P_CORTEX = 0.6


def _smooth_noise(shape, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """Gaussian-smoothed white noise (H, W) scaled to unit SD; wide kernels are drawn on a
    coarse grid and interpolated up (the same field statistics at a fraction of the cost)."""
    f = max(1, int(sigma / 2))
    small = tuple(-(-n // f) + 2 for n in shape)
    n = ndi.gaussian_filter(rng.standard_normal(small).astype(np.float32), sigma / f, mode="reflect")
    if f > 1:
        n = ndi.zoom(n, f, order=1)
    n = n[f:f + shape[0], f:f + shape[1]]
    return n / max(float(n.std()), 1e-6)


def _rim(mask: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The outer 1-3 pixels (H, W) bool of a bone's mask: its cortex, one draw of thickness."""
    return mask & ~ndi.binary_erosion(mask, iterations=int(rng.integers(1, 4)))


def _depth_below_skin(labels: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Depth (H, W) float32 in pixels below a wavy skin line drawn 25-110 px (about 9-40 mm at
    DESS resolution) out from the joint's tissues: negative outside the leg; a crop holding no
    tissue lies inside or outside the leg as a whole."""
    fg = labels > 0
    if not fg.any():
        return np.full(labels.shape, 1e3 if rng.random() < 0.5 else -1e3, np.float32)
    margin = rng.uniform(25, 110) + rng.uniform(0, 15) * _smooth_noise(labels.shape, 20.0, rng)
    return (margin - ndi.distance_transform_edt(~fg)).astype(np.float32)


def augment_geometry(labels: np.ndarray, rng: np.random.Generator, p_rotate: float = 0.5,
                     p_elastic: float = 0.3, p_grid: float = 0.3) -> np.ndarray:
    """The paper's geometric augmentation of a label slice (H, W): rotation up to 30 deg,
    elastic distortion and grid distortion, each with its probability (nearest-neighbour)."""
    h, w = labels.shape
    yy, xx = np.meshgrid(np.arange(h, dtype=np.float32), np.arange(w, dtype=np.float32), indexing="ij")
    cy, cx = (h - 1) / 2, (w - 1) / 2
    y, x = yy - cy, xx - cx
    changed = False
    if rng.random() < p_rotate:
        t = np.deg2rad(rng.uniform(-30, 30))
        y, x = np.cos(t) * y - np.sin(t) * x, np.sin(t) * y + np.cos(t) * x
        changed = True
    if rng.random() < p_elastic:  # smooth random displacement, a few pixels
        alpha = rng.uniform(2.0, 6.0)
        y = y + alpha * _smooth_noise((h, w), 12.0, rng)
        x = x + alpha * _smooth_noise((h, w), 12.0, rng)
        changed = True
    if rng.random() < p_grid:  # grid distortion: each band of rows/columns stretched or squeezed
        for axis, size in ((0, h), (1, w)):
            knots = 1.0 + rng.uniform(-0.3, 0.3, 6)
            steps = np.interp(np.linspace(0, 5, size), np.arange(6), knots)
            warped = np.cumsum(steps) - steps[0]
            warped = warped * (size - 1) / warped[-1] - (size - 1) / 2
            if axis == 0:
                y = np.interp(y + cy, np.arange(h), warped)
            else:
                x = np.interp(x + cx, np.arange(w), warped)
        changed = True
    if not changed:
        return labels
    return ndi.map_coordinates(labels, [y + cy, x + cx], order=0, mode="constant", cval=0)


#: The share of training slices drawn in DESS-like contrast (:func:`dess_like`); the rest get a
#: random contrast (:func:`random_contrast`), so that the network learns shapes, not one contrast.
P_DESS = 0.3


def synthesize(labels: np.ndarray, rng: np.random.Generator, p_intensity: float = 0.3,
               p_dess: float = P_DESS) -> np.ndarray:
    """A training image (H, W) float32 (normalised) of a label slice in network classes: DESS-like
    with probability ``p_dess``, else in random contrast; then the acquisition (:func:`acquire`)."""
    layout = dess_like if rng.random() < p_dess else random_contrast
    return acquire(layout(labels, rng), rng, p_intensity)


def dess_like(labels: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Tissue intensities (H, W) float32 around water-excitation DESS contrast (:data:`RANGES`); the
    cortex darkest when drawn (:data:`P_CORTEX`), else the bone's marrow to its edge."""
    shape = labels.shape
    img = np.zeros(shape, np.float32)
    # background: 2-5 random tissue classes (fat, muscle, tendon, vessels...) with soft borders
    k = int(rng.integers(2, 6))
    fields = np.stack([_smooth_noise(shape, rng.uniform(6, 25), rng) for _ in range(k)])
    cls = fields.argmax(0)
    levels = rng.uniform(*RANGES["background"], k).astype(np.float32)
    marrow = rng.uniform(*RANGES["marrow"])
    if rng.random() < 0.35:  # a background tissue as dark as marrow (fat, tendon): no bone contrast
        levels[rng.integers(k)] = marrow * rng.uniform(0.8, 1.2)
    img[:] = levels[cls]
    if rng.random() < 0.5:  # air outside the leg, often under a band of dark subcutaneous fat
        depth = _depth_below_skin(labels, rng)
        if rng.random() < 0.6:
            img[(depth >= 0) & (depth < rng.uniform(6, 25))] = rng.uniform(0.0, 0.15)
        img[depth < 0] = 0.0
    cart = np.isin(labels, CARTILAGES)
    if rng.random() < 0.8:  # synovial fluid lining the cartilage
        film = ndi.binary_dilation(cart, iterations=int(rng.integers(1, 4))) & (labels == 0)
        film &= _smooth_noise(shape, 4.0, rng) > rng.uniform(-1.0, 0.5)
        img[film] = rng.uniform(*RANGES["fluid"])
    cortex = rng.uniform(*RANGES["cortex"])
    draw_cortex = rng.random() < P_CORTEX
    base = rng.uniform(*RANGES["cartilage"])
    for c in BONES:
        m = labels == c
        if not m.any():
            continue
        img[m] = marrow * rng.uniform(0.8, 1.2)
        if rng.random() < 0.5:  # trabecular texture half the time: marrow may be flat or grainy
            img[m] *= np.clip(1.0 + rng.uniform(0.1, 0.5) * _smooth_noise(shape, rng.uniform(0.6, 2.0), rng)[m], 0.0, None)
        if draw_cortex:
            img[_rim(m, rng)] = cortex
    for c in CARTILAGES:
        img[labels == c] = base * rng.uniform(0.85, 1.15)
    return img


def random_contrast(labels: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Tissue intensities (H, W) float32 in a random contrast, after SynthSeg (Billot et al. 2023).

    The slice is cut into sub-tissues (each bone's marrow and, :data:`P_CORTEX` of the time, its
    cortex, each cartilage, a fluid film on the cartilage, subcutaneous fat under a skin line, air
    beyond it, a band of soft tissue around the bones, and 1-6 random smooth pseudo-tissues
    elsewhere: one gives a uniform background), and every sub-tissue gets
    its own mean intensity drawn uniformly in [0, 1] and its own grain.  The bones share one
    marrow and the cartilages one grey 60 % of the time (as in any real contrast), else each draws
    its own, so that neither bone nor cartilage can be told by its grey alone.
    """
    shape = labels.shape
    k = int(rng.integers(1, 7))
    fields = np.stack([_smooth_noise(shape, rng.uniform(4, 30), rng) for _ in range(k)])
    sub = fields.argmax(0).astype(np.int32) + 20  # background pseudo-tissues 20..
    bone = np.isin(labels, BONES)
    if bone.any() and rng.random() < 0.5:  # soft tissue hugging the bones (periosteum, muscle insertions)
        band = ndi.binary_dilation(bone, iterations=int(rng.integers(3, 15))) & (labels == 0)
        sub[band] = 10
    if rng.random() < 0.6:  # skin line, subcutaneous fat, air
        depth = _depth_below_skin(labels, rng)
        sub[(depth >= 0) & (depth < rng.uniform(4, 25)) & (labels == 0)] = 11
        sub[depth < 0] = 12
    cart = np.isin(labels, CARTILAGES)
    if rng.random() < 0.7:
        film = ndi.binary_dilation(cart, iterations=int(rng.integers(1, 4))) & (labels == 0)
        sub[film & (_smooth_noise(shape, 4.0, rng) > rng.uniform(-1.0, 0.5))] = 13
    shared = rng.random() < 0.6
    draw_cortex = rng.random() < P_CORTEX
    for c in BONES:
        m = labels == c
        sub[m] = 1 if shared else c
        if draw_cortex:
            sub[_rim(m, rng)] = 4 if shared else c + 3
    for c in CARTILAGES:
        sub[labels == c] = 7 if shared else c + 3
    means = rng.uniform(0.0, 1.0, sub.max() + 1).astype(np.float32)
    grain = rng.uniform(0.0, 0.12, sub.max() + 1).astype(np.float32)
    noise = _smooth_noise(shape, rng.uniform(0.5, 2.0), rng)
    return np.clip(means[sub] + grain[sub] * noise, 0.0, None)


def acquire(img: np.ndarray, rng: np.random.Generator, p_intensity: float = 0.3) -> np.ndarray:
    """What a scanner does to tissue intensities (H, W): texture, partial-volume blur, a bias field,
    a coarser acquisition along one axis 30 % of the time, Rician noise; normalised as at inference,
    then brightness, contrast and gamma with probability ``p_intensity``."""
    shape = img.shape
    img = img * (1.0 + rng.uniform(0.0, 0.15) * _smooth_noise(shape, rng.uniform(1.0, 4.0), rng))
    img = ndi.gaussian_filter(img, rng.uniform(0.3, 1.0))
    yy, xx = np.meshgrid(np.linspace(-1, 1, shape[0], dtype=np.float32), np.linspace(-1, 1, shape[1], dtype=np.float32),
                         indexing="ij")
    a = rng.uniform(-0.3, 0.3, 5)
    img *= np.exp(a[0] * yy + a[1] * xx + a[2] * yy * xx + a[3] * yy * yy + a[4] * xx * xx)
    if rng.random() < 0.3:  # a coarser acquisition along one axis (slice thickness, lower matrix)
        axis, f = int(rng.integers(0, 2)), rng.uniform(1.2, 2.5)
        sig = [0.0, 0.0]
        sig[axis] = f / 2.0
        img = ndi.gaussian_filter(img, sig)
    sd = rng.uniform(0.005, 0.05)
    img = np.sqrt((img + sd * rng.standard_normal(shape, dtype=np.float32)) ** 2
                  + (sd * rng.standard_normal(shape, dtype=np.float32)) ** 2)
    img = normalise(img)
    if rng.random() < p_intensity:  # brightness and contrast
        img = img * rng.uniform(0.7, 1.3) + rng.uniform(-0.2, 0.2)
        img = np.sign(img) * np.abs(img) ** rng.uniform(0.7, 1.4)
    return img.astype(np.float32)

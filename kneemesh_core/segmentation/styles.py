"""Evaluation images of a label map in fixed MRI contrasts that training never draws from.

Training (:mod:`.synth`) draws 2-D slices in random or DESS-like contrast.  To
measure how the network does on contrasts it has not learned, this module
dresses a whole label volume, in 3-D and by separate code, in one of
:data:`STYLES`: a T1-weighted spin echo (fat and fatty marrow bright, fluid
dark), a fat-suppressed T2 (fluid bright, fat and marrow dark), a proton-density
scan without fat suppression (fat and marrow bright, fluid and cartilage
intermediate) and a plain DESS without marrow texture.  The anatomy around the
bones is laid out as in a knee: subcutaneous fat under the skin, air beyond
it, muscle with streaks of intermuscular fat elsewhere, a film of joint fluid
on the cartilage.  Beside them the plainest renderings there are (:data:`PLAIN`):
one grey per tissue and nothing else, the bones dark or bright, with or without
a fluid film.  Then a 3-D partial-volume blur, a smooth bias field and Rician
noise.  Grey levels are typical relative signal intensities of each sequence
(their ratios, not any scanner's numbers).
"""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk
from scipy import ndimage as ndi

from kneemesh_core.tissues import BONES, CARTILAGES, LABEL

#: Relative signal of each tissue per style (0 black, 1 brightest), and the marrow's grain (relative SD).
STYLES: dict[str, dict[str, float]] = {
    "t1": {"marrow": 0.85, "cortex": 0.03, "cartilage": 0.40, "fluid": 0.12, "fat": 0.95, "muscle": 0.30,
           "air": 0.0, "grain": 0.08},
    "t2_fat_sat": {"marrow": 0.12, "cortex": 0.02, "cartilage": 0.38, "fluid": 1.0, "fat": 0.08, "muscle": 0.22,
                   "air": 0.0, "grain": 0.10},
    "pd": {"marrow": 0.80, "cortex": 0.03, "cartilage": 0.55, "fluid": 0.70, "fat": 0.90, "muscle": 0.35,
           "air": 0.0, "grain": 0.08},
    "plain_dess": {"marrow": 0.15, "cortex": 0.03, "cartilage": 0.62, "fluid": 0.90, "fat": 0.10, "muscle": 0.30,
                   "air": 0.0, "grain": 0.0},
}


#: The plainest renderings there are: one grey per tissue (each bone, each cartilage and everything else), no
#: texture, no cortex, no fat or air, nothing of the layout above.  ``plain``: bones dark, cartilage bright;
#: ``plain_rim`` adds a bright film of fluid on the cartilage; ``plain_bright_bone`` turns the bones brightest.
PLAIN: dict[str, dict[str, float]] = {
    "plain": {"background": 0.30, "femur": 0.15, "tibia": 0.17, "patella": 0.19, "femoral_cartilage": 0.60,
              "medial_tibial_cartilage": 0.62, "lateral_tibial_cartilage": 0.64, "patellar_cartilage": 0.66},
}
PLAIN["plain_rim"] = {**PLAIN["plain"], "fluid": 0.95}
PLAIN["plain_bright_bone"] = {**PLAIN["plain"], "femur": 0.80, "tibia": 0.82, "patella": 0.84}


def _field(shape: tuple[int, ...], sigma_vox: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Smooth 3-D noise of unit SD (shape (Z, Y, X)), drawn on a grid 4x coarser and interpolated up."""
    coarse = tuple(max(2, -(-n // 4)) for n in shape)
    f = ndi.gaussian_filter(rng.standard_normal(coarse).astype(np.float32), np.maximum(sigma_vox / 4.0, 0.5))
    f = ndi.zoom(f, [n / c for n, c in zip(shape, coarse)], order=1)[tuple(slice(0, n) for n in shape)]
    return (f - f.mean()) / max(float(f.std()), 1e-6)


def style_image(labels: sitk.Image, style: str, seed: int) -> sitk.Image:
    """An image (float32, on the grid of ``labels``) of canonical labels (0..7) in one of :data:`STYLES` or
    :data:`PLAIN`."""
    rng = np.random.default_rng(seed)
    lab = sitk.GetArrayFromImage(labels)
    spacing = np.array(labels.GetSpacing()[::-1])  # (z, y, x) mm
    img = _plain(lab, PLAIN[style]) if style in PLAIN else _layout(lab, labels, STYLES[style], spacing, rng)
    img = ndi.gaussian_filter(img, 0.4 * spacing.min() / spacing)  # partial volume, finer on the coarse axis
    img *= np.exp(0.25 * _field(lab.shape, 80.0 / spacing, rng))  # receive-coil bias
    sd = 0.02
    img = np.sqrt((img + sd * rng.standard_normal(lab.shape, dtype=np.float32)) ** 2
                  + (sd * rng.standard_normal(lab.shape, dtype=np.float32)) ** 2)
    out = sitk.GetImageFromArray((1000.0 * img).astype(np.float32))
    out.CopyInformation(labels)
    return out


def _plain(lab: np.ndarray, tone: dict[str, float]) -> np.ndarray:
    """Tissue greys (Z, Y, X) float32 of a :data:`PLAIN` style: one per tissue, the fluid film where it has one."""
    img = np.full(lab.shape, tone["background"], np.float32)
    if "fluid" in tone:
        cart = np.isin(lab, [LABEL[c] for c in CARTILAGES])
        img[ndi.binary_dilation(cart, iterations=1) & (lab == 0)] = tone["fluid"]
    for tissue in (*BONES, *CARTILAGES):
        img[lab == LABEL[tissue]] = tone[tissue]
    return img


def _layout(lab: np.ndarray, labels: sitk.Image, tone: dict[str, float], spacing: np.ndarray,
            rng: np.random.Generator) -> np.ndarray:
    """Tissue greys (Z, Y, X) float32 of one of :data:`STYLES`: the anatomy around the bones laid out as in a knee."""
    bone = np.isin(lab, [LABEL[b] for b in BONES])
    cart = np.isin(lab, [LABEL[c] for c in CARTILAGES])
    # distance outside the knee's tissues, mm: the skin 20-35 mm out, 5-12 mm of fat beneath it
    outside = sitk.GetArrayFromImage(sitk.SignedMaurerDistanceMap(sitk.Cast(labels > 0, sitk.sitkUInt8),
                                                                  insideIsPositive=False, useImageSpacing=True,
                                                                  squaredDistance=False))
    skin = rng.uniform(20, 35) + 4.0 * _field(lab.shape, 20.0 / spacing, rng)
    img = np.full(lab.shape, tone["muscle"], np.float32)
    img[_field(lab.shape, 6.0 / spacing, rng) > 1.2] = tone["fat"]  # intermuscular fat
    img[outside > skin - rng.uniform(5, 12)] = tone["fat"]
    img[outside > skin] = tone["air"]
    film = ndi.binary_dilation(cart, iterations=1) & (lab == 0) & (_field(lab.shape, 3.0 / spacing, rng) > -0.3)
    img[film] = tone["fluid"]
    marrow = tone["marrow"] * (1.0 + tone["grain"] * _field(lab.shape, 1.0 / spacing, rng))
    img[bone] = marrow[bone]
    img[bone & ~ndi.binary_erosion(bone, iterations=1)] = tone["cortex"]
    img[cart] = tone["cartilage"]
    return img

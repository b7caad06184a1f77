"""Training and evaluation data: label maps in the network's orientation and classes, split by subject.

A label map of any supported convention (``kneemesh_core.tissues``) is read
and canonicalised as for meshing, reoriented like the network's slices
(:data:`.preprocess.NET_ORIENTATION`) and mapped to the network's classes.
Training slices come from :func:`sample`: a random slice of a random subject
(mostly slices with cartilage), a random crop (around cartilage, on bone, so the
shafts far from the joint and cut by the field of view are seen too, or anywhere),
the paper's geometric augmentation, then a random or DESS-like contrast (:mod:`.synth`).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from kneemesh_core.knee import load_knee
from kneemesh_core.segmentation.preprocess import CANONICAL_TO_NET, NET_ORIENTATION, reorient_like
from kneemesh_core.segmentation.synth import BONES, CARTILAGES, augment_geometry, synthesize


@dataclass
class Subject:
    """One label map in network classes, (S, H, W) uint8 in ``NET_ORIENTATION``, and its in-plane spacing (mm)."""

    name: str
    subject: str
    labels: np.ndarray
    pixel_mm: float

    def __post_init__(self):
        self.cartilage_slices = np.flatnonzero((self.labels >= min(CARTILAGES)).any((1, 2)))


def subject_id(path: str | Path) -> str:
    """The subject a file belongs to: the 7-digit OAI participant id (9xxxxxx) wherever the name
    carries one (``OAI_AKOA_<id>_<visit>``, ``OAI_ZIB-UQ_<id>``), else the file stem."""
    name = Path(path).name
    m = re.search(r"(?<!\d)(9\d{6})(?!\d)", name)
    return m.group(1) if m else name.split(".")[0]


def subject_from_labels(canonical: sitk.Image, name: str, subject: str) -> Subject:
    """A :class:`Subject` from canonical labels (0..7) on any grid."""
    oriented = sitk.DICOMOrient(canonical, NET_ORIENTATION)
    arr = CANONICAL_TO_NET[sitk.GetArrayFromImage(oriented)]
    sx, sy, _ = oriented.GetSpacing()
    return Subject(name, subject, arr, float(np.sqrt(sx * sy)))


def load_subject(path: str | Path) -> Subject:
    """A label map file of any supported convention as a :class:`Subject`."""
    return subject_from_labels(load_knee(path).labels, Path(path).name, subject_id(path))


def phantom_subject(seed: int) -> Subject:
    """A phantom knee (alternating sides, severities 0-3) as a training :class:`Subject`."""
    from kneemesh_core.phantom import make_phantom

    side = "left" if seed % 2 else "right"
    _, labels, _ = make_phantom(seed, side, seed % 4)
    return subject_from_labels(labels, f"phantom_{seed}_{side}", f"phantom-{seed}")


def split_by_subject(paths: list[str], fractions: tuple[float, float] = (0.15, 0.15),
                     seed: int = 0) -> tuple[list[str], list[str], list[str]]:
    """(train, validation, test) paths; every subject's files land in one of them only."""
    subjects = sorted({subject_id(p) for p in paths})
    order = np.random.default_rng(seed).permutation(len(subjects))
    n_val = max(1, round(fractions[0] * len(subjects)))
    n_test = max(1, round(fractions[1] * len(subjects))) if fractions[1] > 0 else 0
    val = {subjects[i] for i in order[:n_val]}
    test = {subjects[i] for i in order[n_val:n_val + n_test]}
    pick = lambda s: [p for p in paths if subject_id(p) in s]  # noqa: E731
    return pick(set(subjects) - val - test), pick(val), pick(test)


#: Where a training crop is centred: near a cartilage pixel, on a bone pixel (the bone shafts far
#: from the joint, cut by the field of view), or anywhere.  0.8 near cartilage left the tibial
#: shaft under-seen; at 0.6 near cartilage and 0.4 anywhere, the distal 20 mm of a long tibial
#: shaft was still read as background under unseen contrasts (held-out pymskt T2 map, Dice 0.87).
CROP_CENTRES = {"cartilage": 0.45, "bone": 0.25, "anywhere": 0.30}


def _crop_corner(labels: np.ndarray, size: int, rng: np.random.Generator) -> tuple[int, int]:
    """The top-left pixel (y0, x0) of a size x size crop of a slice (H, W), centred as
    :data:`CROP_CENTRES` draws."""
    h, w = labels.shape
    where = rng.choice(list(CROP_CENTRES), p=list(CROP_CENTRES.values()))
    pixels = np.argwhere(np.isin(labels, CARTILAGES if where == "cartilage" else BONES)) if where != "anywhere" else ()
    if len(pixels):
        cy, cx = pixels[rng.integers(len(pixels))] + rng.integers(-size // 4, size // 4 + 1, 2)
    else:
        cy, cx = rng.integers(0, h), rng.integers(0, w)
    return int(np.clip(cy - size // 2, 0, max(h - size, 0))), int(np.clip(cx - size // 2, 0, max(w - size, 0)))


def _crop(labels: np.ndarray, size: int, rng: np.random.Generator) -> np.ndarray:
    """A size x size crop of a slice (H, W) (:func:`_crop_corner`; zero-padded)."""
    y0, x0 = _crop_corner(labels, size, rng)
    out = np.zeros((size, size), labels.dtype)
    piece = labels[y0:y0 + size, x0:x0 + size]
    out[:piece.shape[0], :piece.shape[1]] = piece
    return out


def sample(subjects: list[Subject], rng: np.random.Generator, size: int = 256) -> tuple[np.ndarray, np.ndarray]:
    """One training pair: a synthetic image (size, size) float32 and its classes (size, size) int64."""
    s = subjects[rng.integers(len(subjects))]
    with_cartilage = s.cartilage_slices
    if len(with_cartilage) and rng.random() < 0.85:
        k = with_cartilage[rng.integers(len(with_cartilage))]
    else:
        k = rng.integers(len(s.labels))
    lab = augment_geometry(_crop(s.labels[k], size, rng), rng)
    return synthesize(lab, rng), lab.astype(np.int64)


def synthetic_image(path: str | Path, seed: int) -> tuple[sitk.Image, sitk.Image]:
    """A synthetic DESS-like image of a label map on the map's own grid (one contrast draw for the
    whole volume, no geometric augmentation), and the map's canonical labels: an evaluation pair."""
    from kneemesh_core.segmentation.synth import synthesize

    labels = load_knee(path).labels
    classes = subject_from_labels(labels, Path(path).name, subject_id(path)).labels
    arr = np.stack([synthesize(sl, np.random.default_rng(seed), p_intensity=0.0, p_dess=1.0) for sl in classes])
    img = sitk.GetImageFromArray((arr * 1000).astype(np.float32))
    img.CopyInformation(sitk.DICOMOrient(labels, NET_ORIENTATION))
    return reorient_like(img, labels), labels

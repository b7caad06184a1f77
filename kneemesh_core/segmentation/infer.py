"""``kneemesh segment``: an image to canonical labels with the ONNX network on the CPU.

Slices in the network's orientation and spacing (:mod:`.preprocess`), batched
through onnxruntime, arg-max, cleaned (:mod:`.postprocess`), put back on the
input's exact grid, and the tibial class split into medial and lateral plates
with the side decided as for any label map (:func:`kneemesh_core.knee.canonicalise`).
Nothing is downloaded: the default model ships in the package.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import SimpleITK as sitk

from kneemesh_core.errors import KneeMeshError
from kneemesh_core.io import Volume
from kneemesh_core.knee import Knee, canonicalise
from kneemesh_core.segmentation.postprocess import clean_classes
from kneemesh_core.segmentation.preprocess import NET_CLASSES, from_slices, to_slices
from kneemesh_core.tissues import PRESETS

#: The models shipped with the package, and the default one (see its model card beside it).
MODELS_DIR = Path(__file__).resolve().parent / "models"
DEFAULT_MODEL = MODELS_DIR / "kneemesh-seg.onnx"
#: Network class -> value in the oai-zib convention, whose merged tibial label canonicalise splits.
_NET_TO_OAI_ZIB = np.array([0, 1, 3, 5, 2, 4, 6], dtype=np.uint8)


@dataclass
class SegmentationModel:
    """An ONNX segmentation network and the preprocessing its metadata asks for."""

    path: Path
    session: object
    pixel_mm: float
    classes: tuple[str, ...]
    meta: dict = field(default_factory=dict)

    @classmethod
    def load(cls, path: str | os.PathLike | None = None, threads: int = 0) -> "SegmentationModel":
        import onnxruntime as ort

        p = Path(path) if path else DEFAULT_MODEL
        if not p.is_file():
            raise KneeMeshError("model_missing", f"{p}: no such segmentation model (an .onnx file from `kneemesh train`).")
        so = ort.SessionOptions()
        so.intra_op_num_threads = threads or (os.cpu_count() or 1)
        so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        try:
            sess = ort.InferenceSession(str(p), so, providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own types for a corrupt or foreign file
            raise KneeMeshError("bad_model", f"{p}: not a loadable ONNX model ({exc}).") from exc
        meta = dict(sess.get_modelmeta().custom_metadata_map)
        classes = tuple(json.loads(meta.get("classes", "[]")))
        if classes != NET_CLASSES:
            raise KneeMeshError("bad_model", f"{p}: its classes {classes} are not KneeMesh's {NET_CLASSES}.")
        return cls(p, sess, float(meta["pixel_mm"]), classes, meta)


def predict_classes(slices: np.ndarray, model: SegmentationModel, batch: int = 8,
                    progress: Callable[[int, int], None] | None = None,
                    probabilities: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
    """Arg-max classes (S, H, W) uint8 of normalised slices (S, H, W), and optionally the softmax
    as uint8 (C, S, H, W; 255 = 1.0)."""
    n = len(slices)
    classes = np.empty(slices.shape, np.uint8)
    probs = np.empty((len(model.classes),) + slices.shape, np.uint8) if probabilities else None
    for i in range(0, n, batch):
        logits = model.session.run(None, {"image": slices[i:i + batch, None]})[0]
        classes[i:i + batch] = logits.argmax(1)
        if probs is not None:
            e = np.exp(logits - logits.max(1, keepdims=True))
            probs[:, i:i + batch] = np.round(255 * e / e.sum(1, keepdims=True)).astype(np.uint8).transpose(1, 0, 2, 3)
        if progress:
            progress(min(i + batch, n), n)
    return classes, probs


@dataclass
class Segmentation:
    knee: Knee  # canonical labels on the input's grid, with the side decided
    probabilities: sitk.Image | None  # vector image (one uint8 component per network class) or None
    seconds: dict


def segment(volume: Volume, model: SegmentationModel, *, side: str | None = None, batch: int = 8,
            probabilities: bool = False, progress: Callable[[int, int], None] | None = None) -> Segmentation:
    """Segment a DESS volume into canonical labels on its own grid (spacing, origin, direction kept)."""
    t0 = time.perf_counter()
    slices, geo = to_slices(volume.image, model.pixel_mm)
    t1 = time.perf_counter()
    classes, probs = predict_classes(slices, model, batch, progress, probabilities)
    t2 = time.perf_counter()
    h, w = geo.shape
    spacing = (geo.oriented.GetSpacing()[2], model.pixel_mm, model.pixel_mm) if geo.resampled else geo.oriented.GetSpacing()[::-1]
    classes[:, :h, :w] = clean_classes(classes[:, :h, :w], spacing)
    labels = from_slices(_NET_TO_OAI_ZIB[classes], geo)
    try:
        knee = canonicalise(Volume(labels, volume.source, volume.meta), PRESETS["oai-zib"], side)
    except KneeMeshError as exc:
        if exc.code in ("empty_labels", "unknown_labels"):
            raise KneeMeshError("segmentation_empty", f"{Path(volume.source).name}: the network found no knee tissue; "
                                "is this a sagittal knee MRI?") from exc
        raise KneeMeshError(exc.code, f"{Path(volume.source).name}, segmented: {exc.message}") from exc
    prob_img = sitk.Compose([from_slices(p, geo) for p in probs]) if probs is not None else None
    t3 = time.perf_counter()
    return Segmentation(knee, prob_img, {"preprocess": round(t1 - t0, 3), "inference": round(t2 - t1, 3),
                                         "postprocess": round(t3 - t2, 3), "total": round(t3 - t0, 3)})

"""``kneemesh train``: fit the residual U-Net on synthetic slices of label maps (random and DESS-like contrast), export ONNX.

Needs the ``train`` extra (PyTorch).  Steps: load every label map of the data
folders, split them by subject into training, validation and test sets (the
split is written beside the model), draw training slices on the fly
(:func:`.dataset.sample`, in a background worker), minimise cross-entropy plus
soft Dice with AdamW and a one-cycle schedule (over the steps, or over the
clock when a time budget is given), score whole validation slices
after each epoch (mean Dice over the six tissues), stop early when it stops
improving, export the best weights to ONNX with their metadata, and check that
onnxruntime and PyTorch agree on validation slices.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from torch.nn import functional as F

from kneemesh_core import __version__
from kneemesh_core.errors import KneeMeshError
from kneemesh_core.segmentation.dataset import Subject, load_subject, phantom_subject, sample, split_by_subject
from kneemesh_core.segmentation.model import ResUNet2D
from kneemesh_core.segmentation.options import TrainOptions
from kneemesh_core.segmentation.preprocess import NET_CLASSES, NET_ORIENTATION, PERCENTILES
from kneemesh_core.segmentation.synth import synthesize

LABEL_SUFFIXES = (".nii.gz", ".nii", ".nrrd", ".mha")


def find_label_maps(folders: list[Path]) -> list[str]:
    """Label map files under the folders (recursively), sorted."""
    out = [str(p) for f in folders for p in sorted(Path(f).rglob("*")) if p.name.lower().endswith(LABEL_SUFFIXES)]
    if not out:
        raise KneeMeshError("no_training_data", f"no label maps ({', '.join(LABEL_SUFFIXES)}) under {', '.join(map(str, folders))}.")
    return out


class _Slices(torch.utils.data.IterableDataset):
    def __init__(self, subjects: list[Subject], crop: int, seed: int):
        self.subjects, self.crop, self.seed = subjects, crop, seed

    def __iter__(self):
        info = torch.utils.data.get_worker_info()
        rng = np.random.default_rng([self.seed, info.id if info else 0, int(time.time_ns() % 2**31)])
        while True:
            img, lab = sample(self.subjects, rng, self.crop)
            yield torch.from_numpy(img[None]), torch.from_numpy(lab)


def _validation_set(subjects: list[Subject], n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Whole slices with cartilage from the validation subjects, in fixed synthetic contrasts drawn as in training."""
    rng = np.random.default_rng(seed)
    imgs, labs = [], []
    for i in range(n):
        s = subjects[i % len(subjects)]
        k = s.cartilage_slices[rng.integers(len(s.cartilage_slices))]
        lab = s.labels[k]
        h, w = lab.shape
        lab = np.pad(lab, ((0, -h % 32), (0, -w % 32)))
        imgs.append(synthesize(lab, rng, p_intensity=0.0)[None])
        labs.append(lab.astype(np.int64))
    shapes = {a.shape for a in labs}
    if len(shapes) > 1:  # mixed geometries: crop to the smallest
        hh, ww = min(s[0] for s in shapes), min(s[1] for s in shapes)
        imgs, labs = [a[:, :hh, :ww] for a in imgs], [a[:hh, :ww] for a in labs]
    return np.stack(imgs), np.stack(labs)


def dice_per_class(pred: np.ndarray, truth: np.ndarray, n_classes: int) -> np.ndarray:
    """Dice (C-1,) of each foreground class over the whole arrays (NaN where absent from both)."""
    out = np.full(n_classes - 1, np.nan)
    for c in range(1, n_classes):
        p, t = pred == c, truth == c
        denom = p.sum() + t.sum()
        if denom:
            out[c - 1] = 2.0 * (p & t).sum() / denom
    return out


def one_cycle(frac: float, peak: float) -> float:
    """Learning rate at a fraction of training: a linear warm-up over the first 5 %, then a
    cosine decay to 1 % of ``peak`` (the one-cycle shape, driven by the step count or the
    clock, so a time-limited run still anneals)."""
    if frac < 0.05:
        return peak * (0.1 + 0.9 * frac / 0.05)
    t = min(1.0, (frac - 0.05) / 0.95)
    return peak * (0.01 + 0.99 * 0.5 * (1 + np.cos(np.pi * t)))


#: Early stopping looks only at the epochs past this fraction of the schedule, where the learning rate has
#: fallen under a quarter of its peak: before, the validation Dice swings with the rate (a 90-min run, 2026-12-07,
#: stopped at epoch 70 on 15 epochs without a better Dice, its rate still a third of its peak, and scored 0.839
#: where an annealed run scores 0.854).
EARLY_STOP_FROM = 0.7


def stops_early(ends: list[float], best_epoch: int, patience: int) -> bool:
    """Whether a run stops after its latest epoch: ``ends`` holds how far through the schedule (0..1) each epoch
    so far ended, ``best_epoch`` (1-based) gave the best validation Dice; it stops when the last ``patience``
    epochs brought no better one and all of them ran past :data:`EARLY_STOP_FROM`."""
    done = len(ends)
    return done - best_epoch >= patience and ends[done - patience - 1] >= EARLY_STOP_FROM


def _loss(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Cross-entropy plus soft Dice over the foreground classes (thin cartilage is a small share of pixels)."""
    ce = F.cross_entropy(logits, target)
    prob = logits.softmax(1)
    onehot = F.one_hot(target, logits.shape[1]).permute(0, 3, 1, 2).float()
    inter = (prob * onehot).sum((0, 2, 3))
    denom = prob.sum((0, 2, 3)) + onehot.sum((0, 2, 3))
    dice = (2 * inter + 1.0) / (denom + 1.0)
    return ce + (1.0 - dice[1:]).mean()


def _predict(model: torch.nn.Module, imgs: np.ndarray, batch: int = 8) -> np.ndarray:
    model.eval()
    with torch.no_grad():
        out = [model(torch.from_numpy(imgs[i:i + batch])).argmax(1).numpy() for i in range(0, len(imgs), batch)]
    return np.concatenate(out)


def train(data: list[Path], out: Path, opts: TrainOptions = TrainOptions(), phantoms: int = 0,
          log: Callable[[str], None] = print) -> dict:
    """Train, export ``out`` (ONNX) and ``out.with_suffix('.json')`` (the run: split, history, metrics)."""
    torch.manual_seed(opts.seed)
    if opts.threads:
        torch.set_num_threads(opts.threads)
    paths = find_label_maps(data) if data else []
    if len(paths) < 3:
        raise KneeMeshError("no_training_data", "training needs at least three label maps (train, validation, test).")
    train_p, val_p, test_p = split_by_subject(paths, seed=opts.seed)
    log(f"{len(train_p)} training (+{phantoms} phantoms), {len(val_p)} validation, {len(test_p)} test label maps "
        "(split by subject)")
    subjects = [load_subject(p) for p in train_p] + [phantom_subject(i) for i in range(phantoms)]
    val_subjects = [load_subject(p) for p in val_p]
    pixel_mm = float(np.median([s.pixel_mm for s in subjects]))
    v_img, v_lab = _validation_set(val_subjects, opts.val_slices, opts.seed + 1)

    model = ResUNet2D(len(NET_CLASSES), opts.widths, opts.head)
    optim = torch.optim.AdamW(model.parameters(), lr=opts.lr, weight_decay=1e-4)
    total = opts.epochs * opts.steps_per_epoch

    def progress(step: int) -> float:
        """How far through training (0..1): by steps, or by the clock when there is a time limit."""
        by_steps = step / total
        return max(by_steps, (time.perf_counter() - t0) / 60 / opts.max_minutes) if opts.max_minutes else by_steps
    loader = iter(torch.utils.data.DataLoader(_Slices(subjects, opts.crop, opts.seed), batch_size=opts.batch,
                                              num_workers=1, persistent_workers=True))
    best = {"score": -1.0}
    history = []
    t0 = time.perf_counter()
    step = 0
    ends: list[float] = []  # how far through the schedule each epoch ended
    for epoch in range(opts.epochs):
        model.train()
        losses = []
        for _ in range(opts.steps_per_epoch):
            for g in optim.param_groups:
                g["lr"] = one_cycle(progress(step), opts.lr)
            x, y = next(loader)
            loss = _loss(model(x), y)
            optim.zero_grad()
            loss.backward()
            optim.step()
            step += 1
            losses.append(loss.item())
        dice = dice_per_class(_predict(model, v_img), v_lab, len(NET_CLASSES))
        score = float(np.nanmean(dice))
        history.append({"epoch": epoch + 1, "loss": round(float(np.mean(losses)), 4), "val_dice": dict(
            zip(NET_CLASSES[1:], np.round(dice, 4).tolist())), "val_mean_dice": round(score, 4),
            "minutes": round((time.perf_counter() - t0) / 60, 2)})
        log(f"epoch {epoch + 1}/{opts.epochs}: loss {np.mean(losses):.4f}, validation Dice "
            + " ".join(f"{n[:6]} {d:.3f}" for n, d in zip(NET_CLASSES[1:], dice)) + f" (mean {score:.4f})")
        ends.append(progress(step))
        if score > best["score"]:
            best = {"score": score, "epoch": epoch + 1, "state": {k: v.clone() for k, v in model.state_dict().items()}}
        elif stops_early(ends, best["epoch"], opts.patience):
            log(f"no improvement for {opts.patience} epochs with the learning rate down: stopping")
            break
        if progress(step) >= 1.0:
            if opts.max_minutes:
                log(f"time limit of {opts.max_minutes} min reached: stopping")
            break
    model.load_state_dict(best["state"])
    model.eval()
    run = {"version": __version__, "options": dataclasses.asdict(opts), "train": train_p, "validation": val_p,
           "test": test_p, "phantoms": phantoms, "best_epoch": best["epoch"], "best_val_mean_dice": round(best["score"], 4),
           "history": history, "minutes": round((time.perf_counter() - t0) / 60, 2)}
    meta = {"classes": json.dumps(list(NET_CLASSES)), "orientation": NET_ORIENTATION, "pixel_mm": f"{pixel_mm:.6f}",
            "percentiles": json.dumps(list(PERCENTILES)), "version": __version__,
            "val_mean_dice": f"{best['score']:.4f}", "best_epoch": str(best["epoch"])}
    export_onnx(model, out, meta)
    run["onnx_agreement"] = check_agreement(model, out, v_img[:8])
    out.with_suffix(".json").write_text(json.dumps(run, indent=1))
    log(f"wrote {out} (best epoch {best['epoch']}, validation mean Dice {best['score']:.4f}); "
        f"ONNX vs PyTorch: {run['onnx_agreement']}")
    return run


def export_onnx(model: torch.nn.Module, out: Path, meta: dict[str, str]) -> None:
    """ONNX (opset 17, dynamic batch and slice size) with ``meta`` in its metadata properties."""
    import onnx

    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".tmp.onnx")
    x = torch.zeros(1, 1, 64, 64)
    torch.onnx.export(model.eval(), x, tmp, input_names=["image"], output_names=["logits"], opset_version=17,
                      dynamic_axes={"image": {0: "n", 2: "h", 3: "w"}, "logits": {0: "n", 2: "h", 3: "w"}}, dynamo=False)
    m = onnx.load(tmp)
    for k, v in meta.items():
        m.metadata_props.add(key=k, value=v)
    onnx.save(m, out)
    tmp.unlink()


def check_agreement(model: torch.nn.Module, path: Path, imgs: np.ndarray) -> dict:
    """onnxruntime against PyTorch on the same slices: largest probability difference, label agreement.

    Raises ``KneeMeshError("onnx_mismatch")`` past 1e-3 or below 99.99 % agreement.
    """
    import onnxruntime as ort

    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    with torch.no_grad():
        ref = model.eval()(torch.from_numpy(imgs)).softmax(1).numpy()
    got = torch.from_numpy(sess.run(None, {"image": imgs})[0]).softmax(1).numpy()
    diff = float(np.abs(ref - got).max())
    agree = float((ref.argmax(1) == got.argmax(1)).mean())
    if diff > 1e-3 or agree < 0.9999:
        raise KneeMeshError("onnx_mismatch", f"ONNX and PyTorch disagree: max probability difference {diff:.2e}, "
                            f"label agreement {agree:.5f}.")
    return {"max_probability_difference": diff, "label_agreement": agree}

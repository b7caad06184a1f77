"""Segmentation accuracy and speed of an ONNX model on held-out anatomy, and a look at a real DESS scan.

    .venv/bin/python bench/segmentation.py [--model PATH] [--out DIR] [--maps ...] [--styles dess t1 ...]

Accuracy: every test label map of the model's training run (subjects it never saw; the split
is in the model's .json) gets an image in each style, is segmented through the whole inference
path (reorientation, batching, post-processing, plate split) and compared with its labels: Dice,
ASSD and HD95 per tissue, a table per style.  Styles: ``dess`` is the training's own DESS-like
synthesis (one contrast draw per volume, no geometric augmentation); the others are the fixed
contrasts of :mod:`kneemesh_core.segmentation.styles` (T1, fat-suppressed T2, proton density,
plain DESS, and the plainest renderings: one grey per tissue, bones dark or bright, with and without a
fluid film), made in 3-D by code that training never calls.  Speed: wall time and peak memory per volume on this
machine.
Real DESS: the pyKNEEr qDESS series in ../shared is segmented and overlay PNGs of a few
slices are written to --out, with the tissue volumes printed.
"""

from __future__ import annotations

import argparse
import json
import resource
import time
import warnings
from pathlib import Path

import numpy as np
from rich.table import Table

from kneemesh.console import console as make_console

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"
console = make_console()


def main() -> None:
    warnings.filterwarnings("ignore")
    from kneemesh_core.io import Volume, read_volume
    from kneemesh_core.knee import load_knee
    from kneemesh_core.segmentation.dataset import synthetic_image
    from kneemesh_core.segmentation.evaluate import compare
    from kneemesh_core.segmentation.infer import DEFAULT_MODEL, SegmentationModel, segment
    from kneemesh_core.segmentation.plausibility import check as plausibility_check
    from kneemesh_core.segmentation.plausibility import figures as plausibility_figures
    from kneemesh_core.segmentation.styles import PLAIN, STYLES, style_image
    from kneemesh_core.tissues import TISSUES

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", type=Path, default=DEFAULT_MODEL)
    ap.add_argument("--maps", nargs="*", help="label maps to test on (default: the model run's test split)")
    ap.add_argument("--out", type=Path, default=Path("seg-bench"))
    ap.add_argument("--threads", type=int, default=0)
    ap.add_argument("--styles", nargs="+", default=["dess", *STYLES, *PLAIN], choices=["dess", *STYLES, *PLAIN],
                    help="image styles to test under (default: all)")
    args = ap.parse_args()
    net = SegmentationModel.load(args.model, args.threads)
    maps = args.maps or json.loads(args.model.with_suffix(".json").read_text())["test"]
    args.out.mkdir(parents=True, exist_ok=True)
    results: dict[str, dict] = {}
    times = []
    truths: dict[str, object] = {}  # each map's canonical labels, read once for every style
    for style in args.styles:
        rows = []
        for i, path in enumerate(maps):
            if style == "dess":
                image, truth = synthetic_image(path, seed=1000 + i)
            else:
                if path not in truths:
                    truths[path] = load_knee(path).labels
                truth = truths[path]
                image = style_image(truth, style, seed=1000 + i)
            t0 = time.perf_counter()
            result = segment(Volume(image, Path(path).name), net)
            times.append((time.perf_counter() - t0, image.GetSize()))
            scores = compare(result.knee.labels, truth)
            rows.append(scores)
            console.print(f"{style} {Path(path).name}: {image.GetSize()} in {times[-1][0]:.1f} s ({result.seconds}); "
                          + " ".join(f"{t[:8]} {s['dice']:.3f}" for t, s in scores.items()))
        results[style] = {Path(p).name: r for p, r in zip(maps, rows)}
        table = Table(title=f"{args.model.name} on {len(rows)} held-out label maps, {style} images")
        for col in ("tissue", "Dice mean", "Dice min", "ASSD mm mean", "HD95 mm mean"):
            table.add_column(col)
        for t in TISSUES:
            vals = [r[t] for r in rows if t in r]
            if not vals:
                continue
            dice = np.array([v["dice"] for v in vals])
            assd = [v["assd_mm"] for v in vals if v["assd_mm"] is not None]
            hd = [v["hd95_mm"] for v in vals if v["hd95_mm"] is not None]
            table.add_row(t, f"{dice.mean():.3f}", f"{dice.min():.3f}", f"{np.mean(assd):.3f}" if assd else "-",
                          f"{np.mean(hd):.2f}" if hd else "-")
        console.print(table)
    full = [s for s, size in times if tuple(size) == (384, 384, 160)]
    console.print(f"time per volume: median {np.median([s for s, _ in times]):.1f} s"
                  + (f"; 384x384x160 volumes: median {np.median(full):.1f} s, max {max(full):.1f} s" if full else "")
                  + f"; peak memory {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")
    (args.out / "accuracy.json").write_text(json.dumps(results, indent=1))

    dess = REAL / "pykneer_demo" / "DESS_echo1"
    if dess.exists():
        vol = read_volume(dess)
        t0 = time.perf_counter()
        result = segment(vol, net)
        console.print(f"real DESS {vol.image.GetSize()} {tuple(round(s, 3) for s in vol.image.GetSpacing())} mm: "
                      f"{time.perf_counter() - t0:.1f} s, {result.knee.side} knee ({result.knee.side_method}); "
                      + ", ".join(f"{t} {v:.1f} ml" for t, v in result.knee.volumes_ml().items()))
        f = plausibility_figures(result.knee.labels)
        status, reasons = plausibility_check(f)
        console.print(f"real DESS plausibility: {status}; " + ("; ".join(reasons) or "every check passed")
                      + f"; cartilage on its bone {f['on_bone']}; bones' largest piece {f['largest_component']}; "
                      f"patella {f.get('patella_anterior_mm')} mm in front of the femoral cartilage")
        overlays(vol.image, result.knee.labels, args.out)


def overlays(image, labels, out: Path, n: int = 4) -> None:
    """PNGs of ``n`` sagittal slices through the knee: the image, and the labels over it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import SimpleITK as sitk
    from matplotlib.colors import ListedColormap

    from kneemesh_core.segmentation.preprocess import NET_ORIENTATION

    img = sitk.GetArrayFromImage(sitk.DICOMOrient(image, NET_ORIENTATION)).astype(np.float32)
    lab = sitk.GetArrayFromImage(sitk.DICOMOrient(labels, NET_ORIENTATION))
    with_tissue = np.flatnonzero(lab.reshape(len(lab), -1).max(1) > 3)  # slices with cartilage
    picks = with_tissue[np.linspace(0, len(with_tissue) - 1, n + 2).astype(int)[1:-1]] if len(with_tissue) else \
        np.linspace(0, len(lab) - 1, n + 2).astype(int)[1:-1]
    colours = ListedColormap(["none", "#e6b800", "#4d94ff", "#b366ff", "#ff3333", "#33cc33", "#00e6e6", "#ff66cc"])
    hi = np.percentile(img, 99.5)
    for k in picks:
        fig, ax = plt.subplots(1, 2, figsize=(10, 5))
        for a in ax:
            a.imshow(img[k], cmap="gray", vmin=0, vmax=hi)
            a.axis("off")
        ax[1].imshow(np.ma.masked_equal(lab[k], 0), cmap=colours, vmin=0, vmax=7, alpha=0.45, interpolation="nearest")
        ax[0].set_title(f"real DESS, slice {k}")
        ax[1].set_title("femur, tibia, patella; FC red, MTC green, LTC cyan, PC pink")
        fig.tight_layout()
        fig.savefig(out / f"dess_slice_{k:03d}.png", dpi=80)
        plt.close(fig)
    console.print(f"overlays: {', '.join(str(out / f'dess_slice_{k:03d}.png') for k in picks)}")


if __name__ == "__main__":
    main()

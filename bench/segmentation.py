"""Segmentation accuracy and speed of an ONNX model on held-out anatomy, and a look at a real DESS scan.

    .venv/bin/python bench/segmentation.py [--model PATH] [--out DIR] [--maps ...]

Accuracy: every test label map of the model's training run (subjects it never saw; the split
is in the model's .json) gets a synthetic DESS-like image (one contrast draw per volume, as in
training but without geometric augmentation), is segmented through the whole inference path
(reorientation, batching, post-processing, plate split) and compared with its labels: Dice,
ASSD and HD95 per tissue.  Speed: wall time and peak memory per volume on this machine.
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
    from kneemesh_core.segmentation.dataset import synthetic_image
    from kneemesh_core.segmentation.evaluate import compare
    from kneemesh_core.segmentation.infer import DEFAULT_MODEL, SegmentationModel, segment
    from kneemesh_core.tissues import TISSUES

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", type=Path, default=DEFAULT_MODEL)
    ap.add_argument("--maps", nargs="*", help="label maps to test on (default: the model run's test split)")
    ap.add_argument("--out", type=Path, default=Path("seg-bench"))
    ap.add_argument("--threads", type=int, default=0)
    args = ap.parse_args()
    net = SegmentationModel.load(args.model, args.threads)
    maps = args.maps or json.loads(args.model.with_suffix(".json").read_text())["test"]
    args.out.mkdir(parents=True, exist_ok=True)
    rows, times = [], []
    for i, path in enumerate(maps):
        image, truth = synthetic_image(path, seed=1000 + i)
        t0 = time.perf_counter()
        result = segment(Volume(image, Path(path).name), net)
        times.append((time.perf_counter() - t0, image.GetSize()))
        scores = compare(result.knee.labels, truth)
        rows.append(scores)
        console.print(f"{Path(path).name}: {image.GetSize()} in {times[-1][0]:.1f} s ({result.seconds}); "
                      + " ".join(f"{t[:8]} {s['dice']:.3f}" for t, s in scores.items()))
    table = Table(title=f"{args.model.name} on {len(rows)} held-out label maps (synthetic DESS-like images)")
    for col in ("tissue", "Dice mean", "Dice min", "ASSD mm mean", "HD95 mm mean"):
        table.add_column(col)
    for t in TISSUES:
        vals = [r[t] for r in rows if t in r]
        if not vals:
            continue
        dice = np.array([v["dice"] for v in vals])
        assd = [v["assd_mm"] for v in vals if v["assd_mm"] is not None]
        hd = [v["hd95_mm"] for v in vals if v["hd95_mm"] is not None]
        table.add_row(t, f"{dice.mean():.3f}", f"{dice.min():.3f}", f"{np.mean(assd):.3f}", f"{np.mean(hd):.2f}")
    console.print(table)
    full = [s for s, size in times if tuple(size) == (384, 384, 160)]
    console.print(f"time per volume: median {np.median([s for s, _ in times]):.1f} s"
                  + (f"; 384x384x160 volumes: median {np.median(full):.1f} s, max {max(full):.1f} s" if full else "")
                  + f"; peak memory {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")
    (args.out / "accuracy.json").write_text(json.dumps({Path(p).name: r for p, r in zip(maps, rows)}, indent=1))

    dess = REAL / "pykneer_demo" / "DESS_echo1"
    if dess.exists():
        vol = read_volume(dess)
        t0 = time.perf_counter()
        result = segment(vol, net)
        console.print(f"real DESS {vol.image.GetSize()} {tuple(round(s, 3) for s in vol.image.GetSpacing())} mm: "
                      f"{time.perf_counter() - t0:.1f} s, {result.knee.side} knee ({result.knee.side_method}); "
                      + ", ".join(f"{t} {v:.1f} ml" for t, v in result.knee.volumes_ml().items()))
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

"""Anatomy benchmark: frames, attachment sites and side by shape on every real map and its mirror image.

    .venv/bin/python bench/anatomy.py [MAPS_OR_GLOBS ...] [--no-mirror] [--workers 2] [--json F]
    .venv/bin/python bench/anatomy.py --stability [MAPS_OR_GLOBS ...]

Default maps: every real label map in ../shared/data/real (pymskt, oai_labels, gibbons_imorphics).
For each knee (and its mirror image through the sagittal plane, with a name that says nothing of the
side): the side decided without --side and how, the bones meshed as a job does, then the anatomy step
timed (registration, frames, sites, figure); prints the registration residuals per bone, the sites
placed and any that break the anatomy rules, the side-by-shape gap, the time per knee, the image pose's
anatomical flexion and how far the tibia moves along its axis on its way to extension
(:func:`kneemesh_core.anatomy.attachments.extension_motion`).

``--stability``: how far each site moves between two segmentations of one knee: every label map
(default: the OAI maps) against the same map with each bone opened, and closed, by one voxel.
"""

from __future__ import annotations

import argparse
import glob
import json
import tempfile
import time
import warnings
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np
from rich.table import Table

from kneemesh.console import console as make_console

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"
console = make_console()


def one(path: str, mirrored: bool) -> dict:
    warnings.filterwarnings("ignore")
    import SimpleITK as sitk

    from kneemesh_core.anatomy.attachments import place
    from kneemesh_core.anatomy.figure import draw
    from kneemesh_core.io import Volume, read_label_map, voxel_to_lps
    from kneemesh_core.knee import canonicalise
    from kneemesh_core.surfaces.tissue import SurfaceOptions, reconstruct_bone
    from kneemesh_core.tissues import LABEL

    vol = read_label_map(path)
    if mirrored:
        from conftest import mirror_lr

        vol = Volume(mirror_lr(vol.image), "knee.nrrd")
    vol.source = "knee.nrrd"
    t0 = time.perf_counter()
    try:
        knee = canonicalise(vol)
    except Exception as exc:  # noqa: BLE001 - the benchmark records every failure
        return {"knee": Path(path).name, "mirrored": mirrored, "error": f"{type(exc).__name__}: {exc}"}
    ingest_s = time.perf_counter() - t0
    bones = {b: reconstruct_bone(knee.labels, b, SurfaceOptions())[0] for b in ("femur", "tibia", "patella")}
    arr = sitk.GetArrayViewFromImage(knee.labels)
    t0 = time.perf_counter()
    plates = tuple(voxel_to_lps(knee.labels, np.argwhere(arr == LABEL[t])[:, ::-1])
                   for t in ("medial_tibial_cartilage", "lateral_tibial_cartilage"))
    anatomy = place(bones, knee.side, plates)
    with tempfile.TemporaryDirectory() as tmp:
        draw(anatomy.document, anatomy.bones, anatomy.frames, Path(tmp) / "a.png")
    seconds = time.perf_counter() - t0
    r = anatomy.report
    tilt = anterior_cortex_tilt(np.asarray(bones["femur"].points), anatomy.frames["femur"])
    return {"knee": Path(path).name, "mirrored": mirrored, "side": knee.side, "side_method": knee.side_method,
            "shape": knee.side_evidence.get("shape") or r["shape_side"], "residuals": r["residuals_mm"],
            "sites": r["sites_placed"], "violations": r["site_rule_violations"], "status": r["status"],
            "reasons": r["reasons"], "angles": r["angles_deg"], "extension": anatomy.document["extension"],
            "cortex_tilt": tilt, "seconds": seconds,
            "ingest_seconds": ingest_s}


def anterior_cortex_tilt(femur: np.ndarray, frame, above_mm: float = 35.0, slab_mm: float = 2.0,
                         half_width_mm: float = 8.0) -> float | None:
    """How far the anterior cortex of the femoral shaft in view leans posterior of the femoral frame's
    long axis, deg: a line through the most anterior surface point (N, 3 points, LPS mm) of each
    ``slab_mm`` slab, within ``half_width_mm`` of the shaft's middle, from ``above_mm`` above the flexion
    axis to 3 mm short of the field of view's edge; None where fewer than 5 slabs show it.  The
    template's :data:`~kneemesh_core.anatomy.template.FEMUR_ANTERIOR_CORTEX_TILT_DEG` is where it came
    from: 0 over a cohort means the template's axis is the cortex's."""
    rel = femur - frame.origin
    h, a, lat = rel @ frame.proximal, rel @ frame.anterior, rel @ frame.lateral
    up = h > above_mm
    if up.sum() < 20:
        return None
    sel = up & (np.abs(lat - np.median(lat[up])) < half_width_mm) & (a > 0)
    rows = [(z + slab_mm / 2, a[m].max()) for z in np.arange(above_mm, h[sel].max() - 3.0, slab_mm)
            if (m := sel & (h >= z) & (h < z + slab_mm)).sum() >= 2]
    if len(rows) < 5:
        return None
    slope = np.polyfit(*np.asarray(rows).T, 1)[0]
    return round(float(-np.degrees(np.arctan(slope))), 2)


def stability(path: str) -> dict:
    """Site displacements (mm) between a knee and its bones opened, and closed, by one voxel."""
    warnings.filterwarnings("ignore")
    import SimpleITK as sitk
    from scipy import ndimage as ndi

    from kneemesh_core.anatomy.attachments import place
    from kneemesh_core.knee import load_knee
    from kneemesh_core.surfaces.tissue import SurfaceOptions, reconstruct_bone
    from kneemesh_core.tissues import LABEL

    knee = load_knee(path)

    def sites(labels) -> np.ndarray:
        bones = {b: reconstruct_bone(labels, b, SurfaceOptions())[0] for b in ("femur", "tibia", "patella")}
        doc = place(bones, knee.side).document
        return np.array([e["lps_mm"] for f in doc["fibres"] for e in f["ends"]], float)

    base = sites(knee.labels)
    out = {"knee": Path(path).name}
    for name, op in (("opened", ndi.binary_opening), ("closed", ndi.binary_closing)):
        arr = sitk.GetArrayFromImage(knee.labels)
        for b in ("femur", "tibia", "patella"):
            mask = arr == LABEL[b]
            changed = op(mask)
            arr[mask & ~changed] = 0
            arr[changed & (arr == 0)] = LABEL[b]
        im = sitk.GetImageFromArray(arr)
        im.CopyInformation(knee.labels)
        out[name] = np.linalg.norm(sites(im) - base, axis=1).tolist()
    return out


def flexion_summary(ok: list[dict]) -> str:
    """The image poses' anatomical flexion: its range, how far two visits of one OAI knee differ (the
    files' subject ids, ``OAI_AKOA_<id>_<visit>``) and how far a knee and its mirror image differ."""
    flex = np.array([r["angles"]["flexion"] for r in ok])
    by = {}
    for r in ok:
        by.setdefault(r["knee"], {})[r["mirrored"]] = r["angles"]["flexion"]
    mirror = [abs(v[True] - v[False]) for v in by.values() if len(v) == 2]
    visits = {}
    for r in ok:
        parts = r["knee"].split("_")
        if r["knee"].startswith("OAI_AKOA_") and not r["mirrored"]:
            visits.setdefault(parts[2], []).append(r["angles"]["flexion"])
    between = [abs(v[0] - v[1]) for v in visits.values() if len(v) == 2]
    text = f"anatomical flexion of the image pose: min {flex.min():.1f}, median {np.median(flex):.1f}, max {flex.max():.1f} deg"
    if between:
        text += f"; two visits of one knee ({len(between)}) differ median {np.median(between):.1f}, max {max(between):.1f} deg"
    if mirror:
        text += f"; a knee and its mirror image differ median {np.median(mirror):.1f}, max {max(mirror):.1f} deg"
    drop = np.array([r["extension"]["tibia_moved_distally_mm"] for r in ok])
    text += (f"; to reach anatomical extension (the ligaments' reference pose) the tibia moves distally min "
             f"{drop.min():.1f}, median {np.median(drop):.1f}, max {drop.max():.1f} mm")
    return text


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("maps", nargs="*")
    ap.add_argument("--no-mirror", action="store_true")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--stability", action="store_true", help="site movement between two segmentations of one knee")
    args = ap.parse_args()
    if args.stability:
        maps = [p for m in args.maps for p in sorted(glob.glob(m))] or [str(p) for p in sorted((REAL / "oai_labels").glob("*.nii.gz"))]
        with ProcessPoolExecutor(args.workers) as pool:
            rows = list(pool.map(stability, maps))
        for key in ("opened", "closed"):
            d = np.concatenate([r[key] for r in rows])
            console.print(f"sites moved, bones {key} by one voxel ({len(rows)} knees, {len(d)} sites): median {np.median(d):.2f} mm, "
                          f"p95 {np.percentile(d, 95):.2f} mm, max {d.max():.2f} mm; per knee median of medians "
                          f"{np.median([np.median(r[key]) for r in rows]):.2f} mm")
        return
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # mirror_lr
    maps = [p for m in args.maps for p in sorted(glob.glob(m))] or [
        str(p) for p in sorted((REAL / "pymskt" / "labels").glob("*.nrrd")) + sorted((REAL / "oai_labels").glob("*.nii.gz"))
        + sorted((REAL / "gibbons_imorphics" / "labels").glob("*.nii.gz"))]
    jobs = [(m, False) for m in maps] + ([] if args.no_mirror else [(m, True) for m in maps])
    rows = []
    with ProcessPoolExecutor(args.workers) as pool:
        futures = [pool.submit(one, m, mir) for m, mir in jobs]
        for fut in as_completed(futures):
            r = fut.result()
            rows.append(r)
            tag = f"{r['knee']}{' (mirror)' if r['mirrored'] else ''}"
            if "error" in r:
                console.print(f"[{len(rows)}/{len(jobs)}] {tag}: [red]{r['error']}[/]", highlight=False)
                continue
            console.print(f"[{len(rows)}/{len(jobs)}] {tag}: {r['side']} by {r['side_method']}, residuals {r['residuals']}, "
                          f"{r['sites']} sites, {len(r['violations'])} off anatomy, {r['seconds']:.2f} s", highlight=False)
            if args.json:
                args.json.write_text(json.dumps(rows, indent=1, default=float))
    ok = [r for r in rows if "error" not in r]
    table = Table(title=f"anatomy on {len(ok)} knees ({len(maps)} maps{'' if args.no_mirror else ' and their mirror images'})")
    for col in ("bone", "residual mm: median", "p90", "max"):
        table.add_column(col)
    for bone in ("femur", "tibia", "patella"):
        v = np.array([r["residuals"][bone] for r in ok if bone in r["residuals"]])
        table.add_row(bone, f"{np.median(v):.3f}", f"{np.percentile(v, 90):.3f}", f"{v.max():.3f}")
    console.print(table)
    expected = {}
    for r in ok:  # a knee's mirror image must be the other side
        expected.setdefault(r["knee"], {})[r["mirrored"]] = r["side"]
    flipped = sum(1 for v in expected.values() if len(v) == 2 and v[True] != v[False])
    gaps = [r["shape"]["relative_gap"] for r in ok if r["shape"].get("relative_gap") is not None]
    secs = np.array([r["seconds"] for r in ok])
    console.print(f"errors: {len(rows) - len(ok)}; all 152 sites placed: {sum(r['sites'] == 152 for r in ok)}/{len(ok)}; "
                  f"knees with a site off its anatomy: {sum(bool(r['violations']) for r in ok)}; status ok: "
                  f"{sum(r['status'] == 'ok' for r in ok)}/{len(ok)}; mirror images decided the other side: {flipped}/"
                  f"{sum(len(v) == 2 for v in expected.values())}; shape gap min {min(gaps):.3f} median {np.median(gaps):.3f}; "
                  f"shape agrees with the side: {sum(r['shape'].get('side') == r['side'] for r in ok)}/{len(ok)}; "
                  f"anatomy step (one process) median {np.median(secs):.2f} s, max {secs.max():.2f} s; "
                  f"side decision at ingest median {np.median([r['ingest_seconds'] for r in ok]):.2f} s")
    console.print(flexion_summary(ok), highlight=False)
    tilts = np.array([r["cortex_tilt"] for r in ok if r.get("cortex_tilt") is not None])
    if len(tilts):
        console.print(f"the femoral shaft's anterior cortex in view leans posterior of the femoral long axis ({len(tilts)} knees): "
                      f"median {np.median(tilts):.1f} deg, 10th-90th percentile {np.percentile(tilts, 10):.1f} to "
                      f"{np.percentile(tilts, 90):.1f}", highlight=False)
    for r in ok:
        if r["violations"] or r["status"] != "ok":
            console.print(f"{r['knee']}{' (mirror)' if r['mirrored'] else ''}: {'; '.join(r['reasons'])}", highlight=False)


if __name__ == "__main__":
    main()

"""What the commands print: tables and lines built from reports, apart from the commands themselves."""

from __future__ import annotations

from pathlib import Path

from rich.table import Table

from kneemesh_core.hexmesh.targets import ELEMENT_SIZE_TOL
from kneemesh_core.job import STAGES
from kneemesh_core.job.stages import TISSUES_SECTION
from kneemesh_core.tissues import TISSUES

STATUS = {"ok": "[green]ok[/]", "review": "[yellow]review[/]", "failed": "[red]failed[/]"}


def inspect_table(title: str, info: dict) -> Table:
    """A label map's description (:func:`kneemesh_core.knee.describe`)."""
    t = Table(title=title, show_header=False)
    t.add_row("size (voxels)", " x ".join(map(str, info["shape"])))
    t.add_row("spacing (mm)", " x ".join(f"{s:.4f}" for s in info["spacing_mm"]))
    t.add_row("origin (LPS mm)", ", ".join(f"{o:.2f}" for o in info["origin_mm"]))
    t.add_row("axes point toward", info["orientation"])
    t.add_row("label convention", info["preset"])
    t.add_row("side", f"{info['side']} (by {info['side_method']})")
    for tissue, ml in info["tissues"].items():
        t.add_row(tissue, f"{ml:.2f} ml" if ml > 0 else "[yellow]not labelled[/]")
    return t


def tissue_table(title: str, report: dict) -> Table:
    """One row per tissue of a job's report: status, time, size, volume and the figures of the file that ships."""
    t = Table(title=title, caption="elements, volume, quality and fidelity: the file in meshes/ (a cartilage's mesh before "
                                   "its edge blend, which the quality gate judged, is under 'gate' in report.json)")
    for col in ("tissue", "status", "s", "elements", "element mm", "volume ml", "label ml", "quality", "fidelity"):
        t.add_column(col)
    for tissue, e in report[TISSUES_SECTION].items():
        if "n_elements" not in e and "n_cells" not in e:  # no mesh at all: failed, or not labelled
            t.add_row(tissue, STATUS.get(e["status"], e["status"]), f"{e['seconds']:.1f}", "", "", "", "", "",
                      e.get("reason") or "; ".join(e.get("reasons", [])))
            continue
        if "n_elements" in e:  # hex cartilage
            quality = f"min SJ {e['min_scaled_jacobian']:.2f}, {e['frac_sj_below_0_5']:.2%} < 0.5"
            fid = f"cover {e['coverage']:.1%}, dev p95 {e['surface_deviation_mm']['p95']:.2f} mm"
            if rim := e.get("blend", {}).get("beyond_rim"):  # the blended file; beyond the rim its blend reshapes
                fid += f" (beyond the blended rim {rim['coverage']:.1%}, {rim['surface_deviation_mm']['p95']:.2f} mm)"
            count = str(e["n_elements"])
            h, asked = e["element_size_mm"], e.get("element_size_asked_mm")
            size = f"{h:.2f}" + (f" [yellow](asked {asked:g})[/]" if asked and abs(h / asked - 1) > ELEMENT_SIZE_TOL else "")
        else:  # bone shell
            closed = "closed, manifold" if e["watertight"] and e["manifold"] else "[red]open[/]"
            quality = closed
            fid = f"dist {e['surface_distance_mm']['mean']:.2f}/{e['surface_distance_mm']['p95']:.2f} mm"
            count = str(e["n_cells"])
            size = f"{e['edge_mm']['mean']:.1f}"
        t.add_row(tissue, STATUS.get(e["status"], e["status"]), f"{e['seconds']:.1f}", count, size, f"{e['volume_ml']:.2f}",
                  f"{e['label_volume_ml']:.2f}", quality, fid)
    return t


def stage_table(report: dict) -> Table | None:
    """One row per other section of a job's report (the knee's stages: segmentation, anatomy, decks,
    simulation, overlaps, any new stage's), each with its status, time and the stage's own summary line."""
    rows = []
    for stage in STAGES:
        entry = report.get(stage.section) if stage.section not in (None, TISSUES_SECTION) else None
        if not isinstance(entry, dict):
            continue
        status = entry.get("status", "ok")
        line = entry.get("reason", "") if status == "failed" else stage.summary(entry) if stage.summary else ""
        seconds = entry.get("seconds")
        rows.append((stage.section, STATUS.get(status, status), "" if seconds is None else f"{seconds:.1f}", line))
    if not rows:
        return None
    t = Table(title="stages")
    for col in ("stage", "status", "s", "summary"):
        t.add_column(col)
    for row in rows:
        t.add_row(*row)
    return t


def verdict_lines(report: dict, out_dir: Path) -> str:
    """The knee's verdict with every reason, and where the report is."""
    verdict = report["verdict"]
    return (f"verdict: {STATUS.get(verdict['status'], verdict['status'])}" + "".join(f"\n  {r}" for r in verdict["reasons"])
            + f"\nreport: {out_dir / 'report.json'}")


def compare_table(title: str, s: dict) -> Table:
    """Two results of one knee (:func:`kneemesh.cohort.compare.compare`): Dice and surface deviation per tissue."""
    t = Table(title=title, caption="Dice compares the two label maps; the other columns the two meshes, A / B")
    for col in ("tissue", "Dice", "deviation median / p75 / max mm", "nodal coverage", "volume ml", "elements",
                "element mm"):
        t.add_column(col)
    dev, meshes = s["surface_deviation_mm"], s.get("meshes", {})
    for tissue, d in s.get("dice", {}).items():
        row, m = dev.get(tissue), meshes.get(tissue)

        def pair(key: str, fmt: str) -> str:
            return "" if not m else " / ".join("" if v is None else format(v, fmt) for v in m[key])

        t.add_row(tissue, "" if d is None else f"{d:.3f}",
                  "" if not row or row["median"] is None else f"{row['median']:.2f} / {row['p75']:.2f} / {row['max']:.2f}",
                  "" if not row else f"{row['coverage']:.1%}", pair("volume_ml", ".2f"), pair("n_elements", "d"),
                  pair("element_size_mm", ".2f"))
    return t


def accuracy_table(rows: dict[str, dict]) -> Table:
    """Segmentation accuracy, the mean over files of each tissue's Dice, ASSD and HD95."""
    t = Table(title=f"segmentation accuracy ({len(rows)} map{'s' if len(rows) > 1 else ''})")
    for col in ("tissue", "Dice", "ASSD mm", "HD95 mm"):
        t.add_column(col)
    for tissue in [t for t in TISSUES if any(t in r for r in rows.values())]:
        vals = [r[tissue] for r in rows.values() if tissue in r]

        def mean(key: str) -> float:
            known = [v[key] for v in vals if v[key] is not None]
            return sum(known) / max(1, len(known))

        t.add_row(tissue, f"{mean('dice'):.3f}", f"{mean('assd_mm'):.3f}", f"{mean('hd95_mm'):.3f}")
    return t

"""``kneemesh report OUT``: one self-contained HTML page over a cohort tree (every folder holding a
``report.json``; a ``kneemesh submit`` state file adds the knees that never came home).

Verdicts and success rates, per-tissue quality and fidelity distributions, timings, failures with
their reasons, contact curves across knees; figures are matplotlib PNGs embedded as data URIs, so the
file reads offline and travels as one attachment.
"""

from __future__ import annotations

import base64
import datetime as dt
import html
import io
import json
from pathlib import Path

import numpy as np

from kneemesh.cohort.submit import DONE, STATE_FILE
from kneemesh_core import __version__
from kneemesh_core.fe.results import loaded
from kneemesh_core.fe.run import RESULT_FILES
from kneemesh_core.io.files import atomic_write_text
from kneemesh_core.job import REPORT_FILE, STAGES
from kneemesh_core.job.stages import TISSUES_SECTION
from kneemesh_core.tissues import CARTILAGES, TISSUES

REPORT_HTML = "report.html"


def collect(root: Path) -> dict:
    """Every knee under ``root``: {"knees": {id: report}, "results": {id: results}, "lost": {id: record}}."""
    knees, results = {}, {}
    for f in sorted(root.rglob(REPORT_FILE)):
        if ".partial" in f.parent.name or not (f.parent / "job.json").exists():
            continue  # a download in progress, or a step record named report.json
        kid = f.parent.relative_to(root).as_posix()
        knees[kid] = json.loads(f.read_text())
        for name in RESULT_FILES:
            if (f.parent / name).exists():
                results[kid] = json.loads((f.parent / name).read_text())
                break
    lost = {}
    if (root / STATE_FILE).exists():
        state = json.loads((root / STATE_FILE).read_text())
        lost = {k: v for k, v in state.get("knees", {}).items() if v.get("state") != DONE and k not in knees}
        for k, v in state.get("knees", {}).items():
            if k in knees and v.get("job_seconds"):
                knees[k].setdefault("_timing", {})["job_seconds"] = v["job_seconds"]
    return {"knees": knees, "results": results, "lost": lost}


def _png(fig) -> str:
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=80)
    plt.close(fig)
    return f'<img alt="figure" src="data:image/png;base64,{base64.b64encode(buf.getvalue()).decode()}">'


def _quality_figure(knees: dict) -> str | None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = [("min_scaled_jacobian", "min scaled Jacobian"), ("coverage", "coverage of the labels"),
            ("volume_error", "volume error (fraction)")]
    data = {c: [[r["tissues"][t][c] for r in knees.values() if isinstance(r["tissues"].get(t, {}).get(c), (int, float))]
                for t in CARTILAGES] for c, _ in cols}
    if not any(any(v) for v in data.values()):
        return None
    fig, axs = plt.subplots(1, 3, figsize=(13, 3.6))
    for ax, (c, label) in zip(axs, cols):
        ax.boxplot([v or [np.nan] for v in data[c]], showfliers=True)
        ax.set_xticks(range(1, len(CARTILAGES) + 1), [t.split("_")[0] for t in CARTILAGES], fontsize=8)
        ax.set_title(label, fontsize=10)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    return _png(fig)


def _timing_figure(seconds: list[float]) -> str | None:
    if not seconds:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3))
    ax.hist(seconds, bins=min(30, max(5, len(seconds))))
    ax.set_xlabel("job time, s (sum of its steps)")
    ax.set_ylabel("knees")
    fig.tight_layout()
    return _png(fig)


#: Up to this many knees, every knee's contact curve has its own colour and a line in the legend; beyond, the
#: cohort's median and 10-90 % band, with the knees of the highest and lowest curves named.
MAX_KNEES_NAMED = 12
#: The colours of the knees' curves and of their legend (matplotlib's tab10, then tab20's light shades).
PALETTE = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf",
           "#aec7e8", "#ffbb78")
CONTACT_PANELS = (("medial", "medial tibiofemoral"), ("lateral", "lateral tibiofemoral"), ("patellofemoral", "patellofemoral"))


def _contact_figure(results: dict) -> tuple[str, str] | None:
    """The contact force over flexion of every knee (medial, lateral, patellofemoral), as an image, and its
    legend as HTML (knee ids beside their colour, readable in the page whatever the figure's size)."""
    if not results:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axs = plt.subplots(1, 3, figsize=(13, 3.6), sharey=True)
    curves = {kid: [(i["flexion_deg"], {k: i[k]["force_n"] for k, _ in CONTACT_PANELS if k in i}) for i in loaded(r["increments"])
                    if i.get("flexion_deg") is not None] for kid, r in results.items()}
    named = list(curves) if len(curves) <= MAX_KNEES_NAMED else []
    for ax, (key, title) in zip(axs, CONTACT_PANELS):
        if named:
            for kid, colour in zip(named, PALETTE):
                pts = [(x, v[key]) for x, v in curves[kid] if key in v]
                ax.plot([p[0] for p in pts], [p[1] for p in pts], color=colour, lw=1.5)
        else:
            grid = np.arange(0.0, 91.0, 3.0)
            table = np.array([np.interp(grid, [p[0] for p in c], [p[1][key] for p in c], left=np.nan, right=np.nan)
                              for c in curves.values() if c and all(key in p[1] for p in c)])
            if len(table):
                lo, mid, hi = np.nanpercentile(table, [10, 50, 90], axis=0)
                ax.fill_between(grid, lo, hi, color="#1f77b4", alpha=0.25, lw=0)
                ax.plot(grid, mid, color="#1f77b4", lw=2)
        ax.set_title(f"{title} contact force", fontsize=10)
        ax.set_xlabel("flexion, deg")
        ax.grid(alpha=0.3)
    axs[0].set_ylabel("N")
    fig.tight_layout()
    if named:
        legend = "".join(f'<li><span class=swatch style="background:{c}"></span>{html.escape(k)}</li>' for k, c in zip(named, PALETTE))
    else:
        peak = {kid: max((v.get("medial", 0) + v.get("lateral", 0) for _, v in c), default=0.0) for kid, c in curves.items()}
        ranked = sorted(peak, key=peak.get)
        legend = (f"<li><span class=swatch style=\"background:#1f77b4\"></span>median and 10-90 % of {len(curves)} knees</li>"
                  + "".join(f"<li>{what}: {html.escape(k)} ({peak[k]:.0f} N)</li>"
                            for what, k in (("highest tibiofemoral force", ranked[-1]), ("lowest", ranked[0]))))
    return _png(fig), f"<ul class=legend>{legend}</ul>"


#: The width of a knee's thumbnail (its attachments figure: bones, ligament sites, axes), pixels.
THUMB_PX = 220


def _thumbnail(folder: Path) -> str:
    """A small JPEG of a knee's ``attachments.png`` as an ``<img>`` (empty when it has none)."""
    from PIL import Image

    png = folder / "attachments.png"
    if not png.exists():
        return ""
    with Image.open(png) as im:
        im = im.convert("RGB")
        im.thumbnail((THUMB_PX, THUMB_PX * im.height // max(im.width, 1)))
        buf = io.BytesIO()
        im.save(buf, format="JPEG", quality=80)
    return f'<img class=thumb alt="{html.escape(folder.name)}" src="data:image/jpeg;base64,{base64.b64encode(buf.getvalue()).decode()}">'


def _table(head: list[str], rows: list[list], raw: tuple[int, ...] = ()) -> str:
    """An HTML table; the cells of the columns ``raw`` are HTML already (a thumbnail), the others escaped."""
    th = "".join(f"<th>{html.escape(h)}</th>" for h in head)
    body = "".join("<tr>" + "".join(f"<td>{c if i in raw else html.escape(str(c))}</td>" for i, c in enumerate(r)) + "</tr>"
                   for r in rows)
    return f"<table><thead><tr>{th}</tr></thead><tbody>{body}</tbody></table>"


def _median_worst(values: list, worst=min) -> str:
    """The median of the numbers among ``values`` and, in brackets, the worst knee's (``worst``: min or max)."""
    v = [x for x in values if isinstance(x, (int, float))]
    return f"{np.median(v):.3f} ({worst(v):.3f})" if v else ""


def render(root: Path, data: dict) -> str:
    knees, results, lost = data["knees"], data["results"], data["lost"]
    total = len(knees) + len(lost)
    verdicts = {s: sum(r.get("verdict", {}).get("status") == s for r in knees.values()) for s in ("ok", "review", "failed")}
    headline = [["knees", total], ["verdict ok", verdicts["ok"]], ["verdict review", verdicts["review"]],
                ["verdict failed", verdicts["failed"]], ["never came home (rejected, failed or unfinished jobs)", len(lost)],
                ["usable models (ok or review) of all knees", f"{(verdicts['ok'] + verdicts['review']) / total:.1%}" if total else ""]]
    if results:
        done = sum(bool(r.get("completed")) for r in results.values())
        headline.append(["simulations completed", f"{done}/{len(results)}"])
    tissue_rows = []
    for t in TISSUES:
        entries = [r["tissues"][t] for r in knees.values() if t in r.get("tissues", {})]
        counts = {s: sum(e.get("status") == s for e in entries) for s in ("ok", "review", "failed")}
        if t in CARTILAGES:
            q = [_median_worst([e.get("min_scaled_jacobian") for e in entries]), _median_worst([e.get("coverage") for e in entries]),
                 _median_worst([abs(e["volume_error"]) if isinstance(e.get("volume_error"), (int, float)) else None
                                for e in entries], max)]
        else:
            q = ["", "", _median_worst([(e.get("surface_distance_mm") or {}).get("p95") for e in entries], max)]
        tissue_rows.append([t, len(entries), counts["ok"], counts["review"], counts["failed"], *q])
    failures = []
    for kid, r in knees.items():
        for t, e in r.get("tissues", {}).items():
            if e.get("status") in ("failed", "review"):
                failures.append([kid, t, e["status"], "; ".join(e.get("reasons") or [e.get("reason") or ""])])
        for section in (s.section for s in STAGES if s.section not in (None, TISSUES_SECTION)):
            if isinstance(r.get(section), dict) and r[section].get("status") == "failed":
                failures.append([kid, section, "failed", r[section].get("reason", "")])
    for kid, v in lost.items():
        failures.append([kid, "job", v.get("state", "unfinished"), v.get("reason") or v.get("last_error") or ""])
    seconds = [r["_timing"]["job_seconds"] for r in knees.values() if "_timing" in r] or \
              [sum(e.get("seconds") or 0.0 for e in r.get("tissues", {}).values()) for r in knees.values()]
    per_knee = [[kid, r.get("input", {}).get("side", ""), r.get("verdict", {}).get("status", ""),
                 "; ".join(r.get("verdict", {}).get("reasons", [])), _thumbnail(root / kid)] for kid, r in knees.items()]
    figures = [("Cartilage quality and fidelity", _quality_figure(knees)), ("Timings", _timing_figure(seconds)),
               ("Contact across knees", _contact_figure(results))]
    parts = [f"<h1>KneeMesh cohort report</h1><p class=meta>{html.escape(str(root))} &middot; {total} knees &middot; "
             f"KneeMesh {__version__} &middot; {dt.datetime.now(dt.timezone.utc):%Y-%m-%d %H:%M} UTC</p>",
             "<h2>Verdicts</h2>", _table(["", "value"], headline),
             "<h2>Tissues</h2>", _table(["tissue", "knees", "ok", "review", "failed", "min SJ median (worst)",
                                         "coverage median (worst)", "|volume error| or bone p95 distance mm, median (worst)"],
                                        tissue_rows)]
    if seconds:
        parts.append(f"<p>Job time (the sum of its steps, s): median {np.median(seconds):.1f}, slowest {max(seconds):.1f}.</p>")
    for title, fig in figures:
        if fig:
            parts += [f"<h2>{title}</h2>", *((fig,) if isinstance(fig, str) else fig)]
    parts += ["<h2>Failures and reviews</h2>",
              _table(["knee", "what", "status", "reasons"], failures) if failures else "<p>None.</p>",
              "<h2>Every knee</h2>", _table(["knee", "side", "verdict", "reasons", "bones, ligament sites, axes"], per_knee,
                                            raw=(4,))]
    style = ("body{font-family:sans-serif;margin:2em;max-width:1200px}table{border-collapse:collapse;margin:1em 0}"
             "td,th{border:1px solid #ccc;padding:3px 8px;font-size:13px;text-align:left;vertical-align:top}"
             "th{background:#eee}img{max-width:100%}.meta{color:#666}.thumb{width:220px}"
             ".legend{list-style:none;padding:0;display:flex;flex-wrap:wrap;gap:4px 18px;font-size:14px}"
             ".swatch{display:inline-block;width:22px;height:12px;margin-right:6px;vertical-align:middle}")
    return (f"<!DOCTYPE html><html lang=en><head><meta charset=utf-8><title>KneeMesh cohort report</title>"
            f"<style>{style}</style></head><body>{''.join(parts)}</body></html>")


def write_report(root: Path, out_file: Path | None = None) -> Path:
    """Write the cohort's HTML report (default ``root/report.html``) and return its path."""
    root = Path(root)
    data = collect(root)
    path = Path(out_file) if out_file else root / REPORT_HTML
    atomic_write_text(path, render(root, data))
    return path

"""``report.json``: the job's description, every stage's entry in its section, and the knee's verdict.

The sections follow the stages' declarations (:mod:`.stages`): each stage with a ``section`` fills it
with its step's result (the tissue stages, one entry per tissue under ``tissues``), and a stage with a
``fold`` puts its result into the tissues' entries.  The knee's verdict judges them all
(:func:`.verdict.knee_verdict`).
"""

from __future__ import annotations

from pathlib import Path

from kneemesh_core.job.options import JobOptions
from kneemesh_core.job.outputs import JOB_FILE, REPORT_FILE, read_json, read_step, write_json
from kneemesh_core.job.verdict import FAILED, OK, REVIEW, knee_verdict


def write_report(out_dir: Path, options: JobOptions, stages) -> dict:
    """Gather the results of the stages a job with ``options`` ran (``stages``: the registry,
    :data:`.stages.STAGES`) into ``report.json``; returns the report."""
    from kneemesh_core.job.stages import TISSUES_SECTION

    out = Path(out_dir)
    report = read_json(out / JOB_FILE)
    folds = []
    for stage in stages:
        steps = stage.planned_steps(options)
        if not steps or (stage.section is None and stage.fold is None):
            continue
        results = {s: read_step(out, s)["result"] for s in steps}
        if stage.section == TISSUES_SECTION:
            report.setdefault(TISSUES_SECTION, {}).update({s: dict(e) for s, e in results.items()})
        elif stage.section is not None:
            report[stage.section] = results[stage.name]
        if stage.fold is not None:
            folds.append((stage.fold, results[stage.name]))
    tissues = report.setdefault(TISSUES_SECTION, {})
    for fold, result in folds:
        fold(tissues, result)
    report["verdict"] = knee_verdict(report)
    report["summary"] = {status: sorted(t for t, e in tissues.items() if e["status"] == status)
                         for status in (OK, REVIEW, FAILED)}
    write_json(out / REPORT_FILE, report)
    return report

"""The stage registry: a stage declared once is planned, run, reported, judged, described by the API and
shown by the command line, with nothing else changed."""

from __future__ import annotations

import json

from typer.testing import CliRunner

from conftest import SAMPLE
from kneemesh.cli import app
from kneemesh_core.job import BONE, REPORT, STAGES, JobOptions, Stage, needs, plan
from kneemesh_core.job.outputs import MESHES_DIR
from kneemesh_core.tissues import BONES
from services.api.openapi import openapi_yaml


def _count_bones(step) -> dict:
    """A trivial stage: it reads the bone meshes the bone stage wrote, and asks for review."""
    found = sorted(f.stem for f in (step.out / MESHES_DIR).glob("*.vtp"))
    return {"status": "review", "reasons": [f"{len(found)} bone shells counted"], "bones": found, "seconds": 0.0}


COUNT = Stage("count_bones", _count_bones, "counts the bone shells (a test's stage)", after=(BONE,),
              section="bone_count", summary=lambda e: f"counted {', '.join(e['bones'])}")


def test_a_stage_declared_once_is_planned_reported_judged_and_shown(tmp_path):
    with STAGES.extended(COUNT):
        options = JobOptions(only="bones")
        stages = plan(options)
        # planned after what it reads (the bones), beside the anatomy, which reads them too; the report waits for it
        assert stages[2] == ("anatomy", "count_bones") and needs(options)["count_bones"] >= set(BONES)
        assert "count_bones" in needs(options)[REPORT]
        # the API's schema names it among the step kinds, with what it does
        schema = openapi_yaml()
        assert "- count_bones" in schema and "counts the bone shells" in schema
        # a job runs it; its section is in the report, its review in the knee's verdict, its line in the table
        out = tmp_path / "knee"
        r = CliRunner().invoke(app, ["mesh", str(SAMPLE), "--out", str(out), "--only", "bones", "--workers", "1"])
        assert r.exit_code == 0, r.output
        report = json.loads((out / "report.json").read_text())
        assert report["bone_count"]["bones"] == sorted(BONES)
        assert report["verdict"]["status"] == "review"
        assert "bone_count: 3 bone shells counted" in report["verdict"]["reasons"]
        table = r.output[r.output.index("stages"):]
        assert "bone_count" in table and "counted femur, patella, tibia" in table
    # and gone with its declaration
    assert "count_bones" not in sum(plan(JobOptions(only="bones")), ())
    assert "- count_bones" not in openapi_yaml()

"""The command line: inspect, phantom, one-line errors with nothing half-written."""

from __future__ import annotations

import json
import subprocess
import sys

from conftest import OAI, PYMSKT_LEFT, SAMPLE, real

KNEEMESH = [sys.executable, "-m", "kneemesh"]


def run(*args):
    return subprocess.run([*KNEEMESH, *map(str, args)], capture_output=True, text=True, encoding="utf-8", timeout=300)


def test_version_and_help():
    r = run("--version")
    assert r.returncode == 0 and r.stdout.startswith("kneemesh ")
    assert "inspect" in run("--help").stdout


def test_inspect_json_real_left_and_sample():
    info = json.loads(run("inspect", real(PYMSKT_LEFT), "--json").stdout)
    assert info["preset"] == "pymskt" and info["side"] == "left"
    assert {"shape", "spacing_mm", "preset", "side", "side_method", "tissues"} <= set(info)
    assert 1.5 < info["tissues"]["lateral_tibial_cartilage"] < 4
    r = run("inspect", SAMPLE)
    assert r.returncode == 0 and "right" in r.stdout and "femoral_cartilage" in r.stdout


def test_inspect_oai_map():
    info = json.loads(run("inspect", real(OAI / "OAI_ZIB-UQ_9011115.nii.gz"), "--json").stdout)
    assert info["preset"] == "oai-zib" and info["side"] == "right"
    assert info["side_method"] == "shape+anatomy+scanner_position"


def test_bad_input_one_line_no_traceback(tmp_path):
    bad = tmp_path / "scan.nii.gz"
    bad.write_bytes(b"\x1f\x8b garbage")
    r = run("inspect", bad)
    assert r.returncode == 2
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert "error (not_an_image)" in r.stderr
    r = run("inspect", SAMPLE, "--preset", "nope")
    assert r.returncode == 2 and "unknown_preset" in r.stderr


def test_phantom_command_writes_image_and_labels(tmp_path):
    r = run("phantom", tmp_path / "ph", "--seed", "3", "--side", "left", "--severity", "2")
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "ph" / "image.nii.gz").exists() and (tmp_path / "ph" / "labels.nii.gz").exists()
    info = json.loads(run("inspect", tmp_path / "ph" / "labels.nii.gz", "--json").stdout)
    assert info["preset"] == "kneemesh" and info["side"] == "left"


def test_segment_and_evaluate_commands(tmp_path):
    """``segment`` with the shipped model writes labels on the image's grid (and probabilities);
    ``evaluate-seg`` scores them against the phantom's labels; a missing model is a one-line error."""
    import pytest
    import SimpleITK as sitk

    from kneemesh_core.segmentation.infer import DEFAULT_MODEL

    if not DEFAULT_MODEL.exists():
        pytest.skip("no shipped segmentation model")
    assert run("phantom", tmp_path / "ph", "--seed", "25", "--side", "right").returncode == 0
    image, truth = tmp_path / "ph" / "image.nii.gz", tmp_path / "ph" / "labels.nii.gz"
    r = run("segment", image, "--out", tmp_path / "seg.nii.gz", "--probabilities", tmp_path / "prob.nii.gz")
    assert r.returncode == 0, r.stderr
    seg, img, prob = (sitk.ReadImage(str(p)) for p in (tmp_path / "seg.nii.gz", image, tmp_path / "prob.nii.gz"))
    assert seg.GetSize() == img.GetSize() and seg.GetSpacing() == img.GetSpacing() and seg.GetOrigin() == img.GetOrigin()
    assert prob.GetNumberOfComponentsPerPixel() == 7
    r = run("evaluate-seg", "--pred", tmp_path / "seg.nii.gz", "--truth", truth, "--json")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["seg.nii.gz"]["femoral_cartilage"]["dice"] > 0.8
    r = run("segment", image, "--out", tmp_path / "x.nii.gz", "--model", tmp_path / "none.onnx")
    assert r.returncode == 2 and "model_missing" in r.stderr and not (tmp_path / "x.nii.gz").exists()


def test_every_job_option_is_a_flag_and_a_form_field():
    """One builder of job options: the command line's mesh and run flags and the API's form fields
    are the fields of JobRequest, with its defaults and bounds."""
    import typer.main

    from kneemesh.cli import app
    from kneemesh_core.job import JobRequest
    from services.api.openapi import openapi_yaml
    import yaml

    fields = set(JobRequest.model_fields)
    commands = {c.name or c.callback.__name__: c for c in app.registered_commands}
    flags = set()
    for name in ("mesh", "run"):
        params = typer.main.get_command_from_info(commands[name], pretty_exceptions_short=True,
                                                  rich_markup_mode=None).params
        flags |= {p.name for p in params}
    # input_type is the command (mesh: labels, run: image); the rest are flags of one of the two
    assert fields - {"input_type"} <= flags, fields - flags
    doc = yaml.safe_load(openapi_yaml())
    form = doc["components"]["schemas"]["JobRequest"]["properties"]
    assert set(form) == fields
    assert form["element_size"]["minimum"] == 0.2 and form["element_size"]["maximum"] == 5.0
    r = run("mesh", SAMPLE, "--out", "unused", "--element-size", "0.1")
    assert r.returncode == 2 and "element_size" in r.stderr and "0.2" in r.stderr

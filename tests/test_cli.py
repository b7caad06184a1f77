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


def test_input_that_is_no_knee_is_refused_saying_what_was_found(tmp_path):
    """A label map of a ball and two boxes, and an MRI sent as a label map: each refused before anything is
    written, with what was found and what is expected."""
    import numpy as np
    import SimpleITK as sitk

    arr = np.zeros((40, 64, 64), np.uint8)
    z, y, x = np.mgrid[:40, :64, :64]
    arr[(z - 20) ** 2 + (y - 20) ** 2 + (x - 20) ** 2 < 100] = 1
    arr[5:15, 40:60, 5:25] = 2
    arr[25:35, 40:60, 40:60] = 3
    toy = tmp_path / "toy.nrrd"
    sitk.WriteImage(sitk.GetImageFromArray(arr), str(toy))
    r = run("mesh", toy, "--out", tmp_path / "toy", "--preset", "imorphics")
    assert r.returncode == 2 and "error (not_a_knee)" in r.stderr, r.stderr
    assert "no femur and no tibia" in r.stderr and "found: femoral cartilage" in r.stderr
    assert not (tmp_path / "toy").exists()
    mri = tmp_path / "mri.nrrd"
    sitk.WriteImage(sitk.GetImageFromArray((np.random.default_rng(0).random((40, 64, 64)) * 3000).astype(np.uint16)), str(mri))
    r = run("mesh", mri, "--out", tmp_path / "mri")
    assert r.returncode == 2 and "error (unknown_labels)" in r.stderr and "input_type=image" in r.stderr, r.stderr


def test_an_implausible_segmentation_stops_before_meshing_unless_forced(tmp_path):
    """An image that is no knee (noise): its segmentation fails the plausibility checks, the job stops with
    the reasons before meshing, the labels kept for a look; forced, it goes on to mesh them."""
    import numpy as np
    import pytest
    import SimpleITK as sitk

    from kneemesh_core.segmentation.infer import DEFAULT_MODEL

    if not DEFAULT_MODEL.exists():
        pytest.skip("no shipped segmentation model")
    noise = sitk.GetImageFromArray((np.random.default_rng(1).random((48, 96, 96)) * 400).astype(np.int16))
    noise.SetSpacing((0.7, 0.7, 1.5))
    image = tmp_path / "noise.nii.gz"
    sitk.WriteImage(noise, str(image))
    r = run("run", image, "--out", tmp_path / "job", "--side", "right", "--workers", "1")
    assert r.returncode == 2 and "error (implausible_segmentation)" in r.stderr and "--force" in r.stderr, r.stderr
    assert (tmp_path / "job" / "labels.nrrd").exists() and not (tmp_path / "job" / "meshes").exists()
    r = run("run", image, "--out", tmp_path / "forced", "--side", "right", "--workers", "1", "--force", "--only", "bones")
    assert "implausible_segmentation" not in r.stderr and (tmp_path / "forced" / "report.json").exists(), r.stderr
    report = json.loads((tmp_path / "forced" / "report.json").read_text())
    assert report["segmentation"]["status"] == "review" and report["verdict"]["status"] != "ok"

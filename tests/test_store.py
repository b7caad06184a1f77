"""Job folders, artifact names, retention and the plan: no broker, no worker."""

from __future__ import annotations

import datetime as dt
import json
import os

import pytest

from kneemesh_core.job import (ANATOMY, BUNDLE, CONFORM, DECKS, HEX_STEPS, INGEST, OVERLAPS, REPORT, SEGMENT, SIMULATE,
                               JobOptions, bundle, needs, plan, start_order)
from kneemesh_core.tissues import CARTILAGES
from services.jobs import Jobs
from services.store import FileStore


def test_plan_meshes_cartilage_beside_the_bones_and_blends_it_after():
    stages = plan(JobOptions(bundle=True))
    assert stages[0] == (INGEST,) and stages[-4:] == [(CONFORM,), (DECKS, OVERLAPS), (REPORT,), (BUNDLE,)]
    assert plan(JobOptions(simulate="smoke"))[-3:] == [(DECKS, OVERLAPS), (SIMULATE,), (REPORT,)]
    # a cartilage's mesh needs only the labels: it is made beside the bones, and first
    assert set(stages[1]) == {"femur", "tibia", "patella"} | {f"hex_{c}" for c in CARTILAGES}
    assert stages[1][:5] == ("hex_femoral_cartilage", "hex_medial_tibial_cartilage", "hex_lateral_tibial_cartilage",
                             "hex_patellar_cartilage", "femur")
    assert set(HEX_STEPS) == {f"hex_{c}" for c in CARTILAGES}
    # its blend needs its bone's mesh: after them, beside the anatomy (which needs only the bones)
    assert stages[2] == ("femoral_cartilage", ANATOMY, "medial_tibial_cartilage", "lateral_tibial_cartilage",
                         "patellar_cartilage")
    assert plan(JobOptions(only="bones")) == [(INGEST,), ("femur", "tibia", "patella"), (ANATOMY,), (REPORT,)]
    only = plan(JobOptions(only="cartilage"))
    assert ANATOMY not in sum(only, ()) and only[1][0] == "hex_femoral_cartilage"  # the sites need the bone meshes
    assert only[-2:] == [(OVERLAPS,), (REPORT,)] and DECKS not in sum(only, ())  # decks need the whole knee
    assert CONFORM not in sum(plan(JobOptions(blend=None)), ())  # the bones give way only to fused cartilage


def test_a_step_waits_only_for_what_it_reads_and_the_cartilage_meshes_start_first():
    stages = plan(JobOptions())
    waits = needs(JobOptions())
    # a blend waits for its own mesh and its bone's, not for the other tissues of their stage
    assert waits["femoral_cartilage"] == {INGEST, "hex_femoral_cartilage", "femur"}
    assert waits["patellar_cartilage"] == {INGEST, "hex_patellar_cartilage", "patella"}
    assert waits[ANATOMY] == {INGEST, "femur", "tibia", "patella"}  # the bones, not the cartilages
    before = set(sum(stages[:3], ()))
    assert waits[CONFORM] == before and waits[DECKS] == waits[OVERLAPS] == before | {CONFORM}
    assert waits[REPORT] == set(sum(stages[:-1], ()))
    # an image's segmentation comes before everything else
    assert SEGMENT in needs(JobOptions(input_type="image"))["femoral_cartilage"]
    # the cartilages' meshes first (the longest, least predictable steps), then the bones, then the blend
    # of the femoral cartilage and the anatomy before the short blends
    order = start_order(stages)
    assert order[:10] == [INGEST, *HEX_STEPS, "femur", "tibia", "patella", "femoral_cartilage", ANATOMY]
    for step in order:  # a valid order to run them one by one
        assert waits[step] <= set(order[: order.index(step)])


@pytest.fixture
def job(tmp_path):
    jobs = Jobs(FileStore(tmp_path / "root"))
    rec = jobs.create("lab-a", "knee.nrrd", "labels", JobOptions(bundle=True))
    out = jobs.out_dir(rec)
    (out / "meshes").mkdir()
    (out / "meshes" / "femur.vtp").write_bytes(b"femur")
    (out / "report.json").write_text("{}")
    (tmp_path / "secret.txt").write_text("not yours")
    bundle(out)
    return jobs, rec, tmp_path


def test_artifact_names_cannot_escape_the_job_folder(job):
    jobs, rec, tmp = job
    store = jobs.store
    assert store.locate(rec.id, "meshes/femur.vtp") == (jobs.out_dir(rec) / "meshes" / "femur.vtp").resolve()
    for name in ("../record.json", "../../secret.txt", str(tmp / "secret.txt"), "/etc/passwd", "meshes/../../record.json",
                 "steps/ingest.json", ""):
        assert store.locate(rec.id, name) is None, name
    # a listed name that became a link to elsewhere is still refused
    target = jobs.out_dir(rec) / "meshes" / "femur.vtp"
    target.unlink()
    os.symlink(tmp / "secret.txt", target)
    assert store.locate(rec.id, "meshes/femur.vtp") is None
    # ids that are not ours lead nowhere
    for bad in ("..", "../root", rec.id + "/..", rec.id.upper()):
        assert store.job_dir(bad) is None and jobs.get(bad) is None


def test_manifest_sizes_and_hashes(job):
    jobs, rec, _ = job
    listed = {a["name"]: a for a in jobs.store.artifacts(rec.id)}
    assert set(listed) == {"meshes/femur.vtp", "report.json", "bundle.zip"}
    assert listed["meshes/femur.vtp"]["size"] == 5
    import hashlib

    assert listed["meshes/femur.vtp"]["sha256"] == hashlib.sha256(b"femur").hexdigest()


def test_jobs_never_share_folders_and_expire_only_when_finished(tmp_path):
    jobs = Jobs(FileStore(tmp_path))
    a = jobs.create("lab-a", "knee.nrrd", "labels", JobOptions())
    b = jobs.create("lab-a", "knee.nrrd", "labels", JobOptions())
    assert a.id != b.id and jobs.input_path(a) != jobs.input_path(b)
    assert jobs.state(a, jobs.steps(a)) == "queued" and jobs.queue_position(b) == 2
    old = (dt.datetime.now(dt.timezone.utc) - dt.timedelta(days=40)).isoformat()
    a.created_at = b.created_at = old
    b.cancelled = True
    jobs.save(a)
    jobs.save(b)
    assert jobs.expire(30) == [b.id]  # a is still queued: kept whatever its age
    assert jobs.get(b.id) is None and jobs.get(a.id) is not None
    assert json.loads((tmp_path / "jobs" / a.id / "record.json").read_text())["owner"] == "lab-a"


def test_cleanup_command_removes_expired_jobs(tmp_path):
    import subprocess
    import sys

    jobs = Jobs(FileStore(tmp_path))
    rec = jobs.create("lab-a", "knee.nrrd", "labels", JobOptions())
    rec.cancelled = True
    jobs.save(rec)
    r = subprocess.run([sys.executable, "-m", "kneemesh", "cleanup", "--data-dir", str(tmp_path), "--older-than", "0"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "removed 1 job" in r.stdout, r.stderr
    assert jobs.get(rec.id) is None


def test_an_idempotency_key_is_claimed_once_before_its_job_exists(tmp_path):
    """A client killed mid-upload and started again repeats its submission while the first is still
    being accepted: the key is claimed before the upload is read, so the repeat cannot claim it and
    finds no job yet (the route waits for it); a refused submission gives the claim back; a claim a
    dead server left behind is taken over once it is older than KEY_CLAIM_S."""
    import services.jobs as jobs_module

    jobs = Jobs(FileStore(tmp_path / "root"))
    assert jobs.claim_key("lab-a", "cohort:knee-1")
    assert not jobs.claim_key("lab-a", "cohort:knee-1") and jobs.by_key("lab-a", "cohort:knee-1") is None
    assert jobs.claim_key("lab-b", "cohort:knee-1")  # another owner's key is another key
    rec = jobs.create("lab-a", "knee.nrrd", "labels", JobOptions())
    jobs.remember_key("lab-a", "cohort:knee-1", rec.id)
    assert jobs.by_key("lab-a", "cohort:knee-1").id == rec.id and not jobs.claim_key("lab-a", "cohort:knee-1")
    jobs.release_key("lab-b", "cohort:knee-1")
    assert jobs.claim_key("lab-b", "cohort:knee-1")
    old = jobs._key_file("lab-b", "cohort:knee-1")
    os.utime(old, (old.stat().st_mtime - jobs_module.KEY_CLAIM_S - 1,) * 2)
    assert jobs.claim_key("lab-b", "cohort:knee-1")

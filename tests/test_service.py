"""The service against real components: a Redis server, Celery worker processes, the API, a served port."""

from __future__ import annotations

import hashlib
import io
import json
import os
import signal
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
import pyvista as pv
import SimpleITK as sitk
from fastapi.testclient import TestClient

from conftest import OAI, PYMSKT_RIGHT, SAMPLE, real
from kneemesh_core.hexmesh import targets as T
from kneemesh_core.knee import load_knee
from kneemesh_core.tissues import LABEL
from kneemesh_core.segmentation.infer import DEFAULT_MODEL
from service_helpers import RedisServer, Worker, free_port, poll, wait_for
from services.api import create_app
from services.settings import Settings
from services.worker.celery_app import QUEUE

pytestmark = pytest.mark.xdist_group("service")
KEYS = {"lab-a-secret-key": "lab-a", "lab-b-secret-key": "lab-b"}
A = {"X-API-Key": "lab-a-secret-key"}
B = {"X-API-Key": "lab-b-secret-key"}
TISSUES = ("femur", "tibia", "patella", "femoral_cartilage", "medial_tibial_cartilage",
           "lateral_tibial_cartilage", "patellar_cartilage")


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    """Redis, one Celery worker, and the API (in this process) configured for them."""
    tmp = tmp_path_factory.mktemp("service")
    redis = RedisServer(tmp)
    data = tmp / "data"
    # Short visibility timeout so a killed worker's tasks come back within the test; longer than any task here.
    env = {"KNEEMESH_VISIBILITY_TIMEOUT": "20"}
    settings = Settings(data_dir=data, broker_url=redis.url, api_keys=KEYS, visibility_timeout_s=20)
    worker = Worker(redis.url, data, tmp, env)
    worker.wait_ready()
    with TestClient(create_app(settings)) as client:
        wait_for(lambda: client.get("/readyz").json()["ready"], 30, "the API to see the worker")
        s = type("Stack", (), {})()
        s.redis, s.client, s.data, s.tmp, s.env, s.worker = redis, client, data, tmp, env, worker
        yield s
    s.worker.kill(signal.SIGTERM)
    redis.stop()


def upload(client, path: Path, headers=A, name: str | None = None, **form):
    with open(path, "rb") as fh:
        return client.post("/v1/jobs", files={"file": (name or path.name, fh)}, data=form, headers=headers)


def job_dirs(data: Path) -> set[str]:
    return {p.name for p in (data / "jobs").iterdir()}


def test_label_map_job_runs_every_tissue_as_its_own_celery_task(stack):
    c = stack.client
    r = upload(c, real(PYMSKT_RIGHT))
    assert r.status_code == 202, r.text
    job = r.json()
    # the answer tells the job's state when it is sent: queued, or running where the idle worker took it first
    assert job["state"] in ("queued", "running") and job["urls"]["bundle"].endswith(f"/v1/jobs/{job['id']}/bundle.zip")
    status = poll(c, job["id"], headers=A)
    assert status["state"] == "succeeded", status
    steps = {s["step"]: s for s in status["steps"]}
    assert [s["step"] for s in status["steps"]][:1] == ["ingest"] and status["progress"] == 1.0
    # every tissue ran as a separate Celery task, recorded as such by the result backend
    task_ids = {steps[t]["task_id"] for t in TISSUES}
    assert len(task_ids) == 7 and None not in task_ids
    backend = c.app.state.runner.app.backend
    assert all(backend.get_task_meta(t)["status"] == "SUCCESS" for t in task_ids)
    assert steps["femoral_cartilage"]["stage"] > steps["femur"]["stage"]  # cartilage after the bones
    assert sorted(status["tissues_ok"]) == sorted(TISSUES) and status["verdict"]["status"] == "ok"

    listing = c.get(job["urls"]["artifacts"], headers=A).json()["artifacts"]
    names = {a["name"] for a in listing}
    assert {"report.json", "labels.nrrd", "bundle.zip", "meshes/femur.vtp", "meshes/femoral_cartilage.vtu",
            "attachments.json", "attachments.png"} <= names
    assert steps["anatomy"]["state"] == "done" and steps["anatomy"]["task_id"] not in task_ids  # its own task
    assert steps["anatomy"]["stage"] == steps["femoral_cartilage"]["stage"] > steps["femur"]["stage"]  # beside the cartilages
    for a in listing:
        if a["name"] in ("report.json", "bundle.zip"):
            body = c.get(a["url"], headers=A).content
            assert len(body) == a["size"] and hashlib.sha256(body).hexdigest() == a["sha256"]
    bundle = zipfile.ZipFile(io.BytesIO(c.get(job["urls"]["bundle"], headers=A).content))
    members = set(bundle.namelist())
    assert {f"meshes/{t}.vtp" for t in TISSUES[:3]} | {f"meshes/{t}.vtu" for t in TISSUES[3:]} <= members
    report = json.loads(bundle.read("report.json"))
    assert report["summary"]["failed"] == [] and report["input"]["side"] == "right"
    assert report["anatomy"]["sites_placed"] == 152 and "attachments.json" in members
    assert {"fe/knee_model.inp", "fe/knee_ccx.inp", "fe/knee_abaqus.inp"} <= members and report["fe"]["status"] == "ok"
    hexes = pv.read(stack.data / "jobs" / job["id"] / "out" / "meshes" / "medial_tibial_cartilage.vtu")
    assert hexes.n_cells > 500 and set(np.unique(hexes.celltypes)) == {pv.CellType.HEXAHEDRON}
    blend = report["tissues"]["medial_tibial_cartilage"]["blend"]  # fused onto the bone the job meshed first
    assert blend["passed"] and report["tissues"]["medial_tibial_cartilage"]["fused_fraction"] > 0.9
    sj = hexes["scaled_jacobian"]
    assert sj.min() >= T.BLEND_MIN_SCALED_JACOBIAN and (sj >= T.MIN_SCALED_JACOBIAN).mean() >= T.BLEND_FRAC_GOOD


@pytest.mark.skipif(not DEFAULT_MODEL.exists(), reason="no shipped segmentation model")
def test_image_job_is_segmented_by_a_worker_then_meshed(stack, tmp_path):
    """A DESS-like image (a phantom the model never trained on) goes through the segment step, then the bones."""
    from kneemesh_core.phantom import write_phantom

    image = write_phantom(tmp_path, 23, "left", 0)["image"]
    c = stack.client
    r = upload(c, image, input_type="image", only="bones")
    assert r.status_code == 202, r.text
    status = poll(c, r.json()["id"], headers=A)
    assert status["state"] == "succeeded", status
    steps = [s["step"] for s in status["steps"]]
    assert steps[:2] == ["ingest", "segment"] and status["steps"][1]["task_id"]
    # every bone meshed; a segmentation's stray labels make a shell stray from its label: review, said so
    assert sorted(status["tissues_ok"] + status["tissues_review"]) == ["femur", "patella", "tibia"]
    assert status["verdict"]["status"] in ("ok", "review") and not status["tissues_failed"]
    out = stack.data / "jobs" / r.json()["id"] / "out"
    labels, source = sitk.ReadImage(str(out / "labels.nrrd")), sitk.ReadImage(str(image))
    assert labels.GetSize() == source.GetSize() and np.allclose(labels.GetOrigin(), source.GetOrigin())
    report = json.loads((out / "report.json").read_text())
    assert report["input"]["side"] == "left" and report["input"]["segmentation"]["model"] == DEFAULT_MODEL.name


def test_a_knee_whose_verdict_is_failed_ends_failed_with_its_files(stack, tmp_path):
    """A job whose every step ran but whose knee has a failed tissue (a patellar cartilage of a few voxels)
    ends in state failed, its verdict saying why, and its files can still be downloaded."""
    knee = load_knee(real(SAMPLE))
    arr = sitk.GetArrayFromImage(knee.labels)
    pc = np.argwhere(arr == LABEL["patellar_cartilage"])
    arr[arr == LABEL["patellar_cartilage"]] = LABEL["patella"]
    arr[tuple(pc[:12].T)] = LABEL["patellar_cartilage"]  # a speck
    speck = sitk.GetImageFromArray(arr)
    speck.CopyInformation(knee.labels)
    path = tmp_path / "speck_right.nrrd"
    sitk.WriteImage(speck, str(path))
    c = stack.client
    r = upload(c, path, only="cartilage", preset="kneemesh")
    assert r.status_code == 202, r.text
    status = poll(c, r.json()["id"], headers=A)
    assert status["state"] == "failed" and status["verdict"]["status"] == "failed", status
    assert status["tissues_failed"] == ["patellar_cartilage"] and status["error"] is None
    assert any(reason.startswith("patellar_cartilage: failed") for reason in status["verdict"]["reasons"])
    names = {a["name"] for a in c.get(status["urls"]["artifacts"], headers=A).json()["artifacts"]}
    assert {"report.json", "bundle.zip", "meshes/femoral_cartilage.vtu"} <= names
    assert c.get(status["urls"]["bundle"], headers=A).status_code == 200


def test_worker_killed_mid_job_loses_nothing(stack):
    c = stack.client
    job = upload(c, SAMPLE).json()
    running = wait_for(lambda: [s for s in c.get(f"/v1/jobs/{job['id']}", headers=A).json()["steps"]
                                if s["kind"] == "cartilage" and s["state"] == "running"], 120, "a cartilage step to start",
                       every=0.1)
    killed_on = {s["step"]: s["worker"] for s in running}
    stack.worker.kill(signal.SIGKILL)  # the whole worker and its pool, mid-task, no goodbye
    stack.worker = Worker(stack.redis.url, stack.data, stack.tmp, stack.env)
    stack.worker.wait_ready()
    status = poll(c, job["id"], headers=A)
    assert status["state"] == "succeeded", status
    steps = {s["step"]: s for s in status["steps"]}
    for step, old in killed_on.items():  # delivered again and finished by the new worker
        assert steps[step]["state"] == "done" and steps[step]["worker"] != old
    assert sorted(status["tissues_ok"]) == sorted(TISSUES)


def test_cancel_stops_the_job_and_deletes_its_files(stack):
    c = stack.client
    job = upload(c, SAMPLE).json()
    wait_for(lambda: c.get(f"/v1/jobs/{job['id']}", headers=A).json()["state"] == "running", 60, "the job to start", every=0.1)
    r = c.delete(f"/v1/jobs/{job['id']}", headers=A)
    assert r.status_code == 200 and r.json()["state"] == "cancelled" and r.json()["deleted"]
    folder = stack.data / "jobs" / job["id"]
    assert not (folder / "out").exists() and not (folder / "input").exists()
    wait_for(lambda: c.get("/readyz").json()["ready"], 30, "the worker to be back")
    # the rest of the chain never runs: no report, nothing recreated
    assert c.get(f"/v1/jobs/{job['id']}", headers=A).json()["state"] == "cancelled"
    assert c.get(job["urls"]["bundle"], headers=A).status_code == 404
    assert not (folder / "out").exists()


def test_keys_and_unknown_jobs(stack):
    c = stack.client
    assert c.get("/v1/jobs").status_code == 401
    r = c.get("/v1/jobs", headers={"X-API-Key": "not-a-key-we-know"})
    assert r.status_code == 401 and r.json()["code"] == "invalid_api_key"
    mine = upload(c, SAMPLE, only="bones").json()["id"]
    other = c.get(f"/v1/jobs/{mine}", headers=B)  # another lab cannot see it
    assert other.status_code == 404 and other.json()["code"] == "job_not_found"
    assert c.delete(f"/v1/jobs/{mine}", headers=B).status_code == 404
    assert mine not in {j["id"] for j in c.get("/v1/jobs", headers=B).json()["jobs"]}
    assert mine in {j["id"] for j in c.get("/v1/jobs", headers=A).json()["jobs"]}
    r = c.get("/v1/jobs/0123456789abcdef0123456789abcdef", headers=A)
    assert r.status_code == 404 and r.json()["message"]
    assert c.get("/v1/jobs/../../etc/passwd", headers=A).status_code == 404
    for path in ("/v1/nothing-here", "/v2/jobs"):  # unmatched routes answer in the service's error shape too
        r = c.get(path, headers=A)
        assert r.status_code == 404 and r.json()["code"] == "not_found" and path in r.json()["message"]
    assert poll(c, mine, headers=A)["state"] == "succeeded"


def _image(arr: np.ndarray, path: Path, spacing=(0.5, 0.5, 0.7)) -> Path:
    img = sitk.GetImageFromArray(arr)
    img.SetSpacing(spacing[: img.GetDimension()])
    sitk.WriteImage(img, str(path))
    return path


def test_bad_uploads_are_refused_clearly_and_queue_nothing(stack, tmp_path):
    c = stack.client
    before = job_dirs(stack.data)
    queued = set(stack.redis.client.lrange(QUEUE, 0, -1))
    truncated = tmp_path / "knee.nrrd"
    truncated.write_bytes(SAMPLE.read_bytes()[:60_000])
    rng = np.random.default_rng(0)
    cases = {
        "not an image": (tmp_path / "notes.nii.gz", b"these are not voxels", 422, "not_an_image"),
        "truncated": (truncated, None, 422, "corrupt"),
        "2-D": (_image(np.ones((64, 64), np.uint8), tmp_path / "slice.nrrd"), None, 422, "not_3d"),
        "wrong labels": (_image(rng.integers(0, 40, (20, 30, 30)).astype(np.uint8), tmp_path / "noise.nrrd"), None, 422, None),
        "unsupported format": (tmp_path / "scan.txt", b"hello", 415, "unsupported_format"),
    }
    for what, (path, content, status, code) in cases.items():
        if content is not None:
            path.write_bytes(content)
        r = upload(c, path)
        assert r.status_code == status, (what, r.text)
        body = r.json()
        assert body["message"] and (code is None or body["code"] == code), (what, body)
    toy = np.zeros((20, 30, 30), np.uint8)  # a ball and a box: read as cartilage labels, no bones
    toy[5:15, 5:15, 5:15], toy[2:6, 20:28, 20:28] = 1, 2
    r = upload(c, _image(toy, tmp_path / "toy.nrrd"), preset="imorphics")
    assert r.status_code == 422 and r.json()["code"] == "not_a_knee" and "no femur" in r.json()["message"]
    r = upload(c, _image(np.ones((64, 64), np.float32), tmp_path / "slice_image.nrrd"), input_type="image")
    assert r.status_code == 422 and r.json()["code"] == "not_3d"
    r = upload(c, SAMPLE, layers="0")
    assert r.status_code == 422 and r.json()["code"] == "invalid_request" and "layers" in r.json()["message"]
    r = upload(c, SAMPLE, element_size="nan")
    assert r.status_code == 422 and "element_size" in r.json()["message"] and "finite" in r.json()["message"]
    r = upload(c, SAMPLE, labels="/etc/passwd")  # a mapping, never a file on the server
    assert r.status_code == 422 and r.json()["code"] == "bad_labels_spec"
    r = upload(c, SAMPLE, input_type="image", model="../../elsewhere.onnx")  # a shipped model's name, never a path
    assert r.status_code == 422 and r.json()["code"] == "model_missing"
    # too large: a server with a small limit refuses before storing anything
    small = Settings(data_dir=stack.data, broker_url=stack.redis.url, api_keys=KEYS, max_upload_bytes=50_000)
    with TestClient(create_app(small)) as tiny:
        r = upload(tiny, SAMPLE)
        assert r.status_code == 413 and r.json()["code"] == "upload_too_large"
    assert job_dirs(stack.data) == before
    # the worker may take earlier tests' jobs meanwhile, so the queue may shrink: nothing new in it
    assert set(stack.redis.client.lrange(QUEUE, 0, -1)) <= queued


def test_batch_of_knees(stack):
    c = stack.client
    files = [("files", (SAMPLE.name, open(SAMPLE, "rb"))),
             ("files", ("OAI_ZIB-UQ_9011115.nii.gz", open(real(OAI / "OAI_ZIB-UQ_9011115.nii.gz"), "rb")))]
    r = c.post("/v1/batches", files=files, data={"only": "bones"}, headers=A)
    assert r.status_code == 202, r.text
    batch = r.json()
    assert len(batch["jobs"]) == 2
    positions = [j["queue_position"] for j in batch["jobs"]]
    assert positions[0] >= 1 and positions[1] > positions[0]  # taken together, strictly increasing
    done = wait_for(lambda: (b := c.get(batch["url"], headers=A).json())["done"] and b, 240, "the batch")
    assert done["counts"]["succeeded"] == 2
    for job in done["jobs"]:  # each knee's verdict and failed tissues, for a cohort to filter on
        assert job["verdict"]["status"] in ("ok", "review") and job["tissues_failed"] == []
    manifest = c.get(batch["url"] + "/manifest", headers=A).json()
    assert manifest["done"] and [j["id"] for j in manifest["jobs"]] == [j["id"] for j in batch["jobs"]]
    for job in manifest["jobs"]:  # every artifact's url and sha256: what a client downloads and checks
        femur = next(a for a in job["artifacts"] if a["name"] == "meshes/femur.vtp")
        assert hashlib.sha256(c.get(femur["url"], headers=A).content).hexdigest() == femur["sha256"]
    assert c.get(batch["url"] + "/manifest", headers=B).status_code == 404
    assert c.get(batch["url"], headers=B).status_code == 404
    # one bad file refuses the whole batch and queues nothing
    before = job_dirs(stack.data)
    files = [("files", (SAMPLE.name, open(SAMPLE, "rb"))), ("files", ("bad.nrrd", b"nope"))]
    r = c.post("/v1/batches", files=files, headers=A)
    assert r.status_code == 422 and "file 2" in r.json()["message"]
    assert job_dirs(stack.data) == before


def test_health_readiness_metrics(stack):
    c = stack.client
    assert c.get("/healthz").json()["status"] == "ok"
    ready = c.get("/readyz").json()
    assert ready["ready"] and ready["runner"] == "celery" and ready["workers"] >= 1
    text = c.get("/metrics").text
    assert "kneemesh_jobs_submitted_total" in text and 'kneemesh_jobs{state="succeeded"}' in text


def test_readyz_without_a_broker(tmp_path):
    settings = Settings(data_dir=tmp_path, broker_url=f"redis://127.0.0.1:{free_port()}/0")
    with TestClient(create_app(settings)) as c:
        r = c.get("/readyz")
        assert r.status_code == 503 and not r.json()["ready"] and "broker" in r.json()["detail"]
        r = upload(c, SAMPLE, headers={}, only="bones")
        assert r.status_code == 503 and r.json()["code"] == "queue_unavailable"
    assert list((tmp_path / "jobs").iterdir()) == []


def test_embedded_server_end_to_end(tmp_path):
    """``kneemesh serve`` with no broker: one process, real HTTP, upload to bundle."""
    import httpx

    port = free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("KNEEMESH_")}
    log = open(tmp_path / "serve.log", "w")
    server = subprocess.Popen([sys.executable, "-m", "kneemesh", "serve", "--port", str(port), "--data-dir",
                               str(tmp_path / "data")], stdout=log, stderr=subprocess.STDOUT, env=env)
    try:
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=30) as c:
            def ready():
                try:
                    return c.get("/readyz").json()["ready"]
                except httpx.TransportError:
                    return False

            wait_for(ready, 60, "kneemesh serve")
            assert c.get("/readyz").json()["runner"] == "embedded"
            job = upload(c, SAMPLE, headers={}).json()
            status = poll(c, job["id"])
            assert status["state"] == "succeeded" and sorted(status["tissues_ok"]) == sorted(TISSUES)
            bundle = zipfile.ZipFile(io.BytesIO(c.get(job["urls"]["bundle"]).content))
            assert "meshes/femoral_cartilage.vtu" in bundle.namelist()

            # killed mid-job with SIGKILL, the server takes its pool processes with it: no orphan meshes on
            children = _children(server.pid)
            assert len(children) >= 2, children  # the two pool processes (and a resource tracker) stay warm
            second = upload(c, SAMPLE, headers={}).json()
            wait_for(lambda: any(s["state"] == "running" and s["kind"] in ("bone", "cartilage")
                                 for s in c.get(f"/v1/jobs/{second['id']}").json()["steps"]), 120, "a tissue step to run")
            server.kill()
            server.wait(30)
            wait_for(lambda: not any(_alive(p) for p in children), 15, f"the pool processes {children} to end")
    finally:
        if server.poll() is None:
            server.terminate()
            server.wait(30)


def _children(pid: int) -> list[int]:
    """The process ids whose parent is ``pid`` (from /proc)."""
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            out.append(int(stat.parent.name))
    return out


def _alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie waiting for a reaper counts as ended)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False

"""The cohort tools against real components: ``kneemesh submit`` against a served API with a real
Redis and a real Celery worker, killed mid-run and resumed; ``kneemesh report`` opened in headless
Chromium; ``kneemesh compare`` on constructed cases with known answers; the client's retry rules
against a real HTTP server."""

from __future__ import annotations

import csv
import http.server
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
from pathlib import Path

import httpx
import numpy as np
import pytest
import pyvista as pv
import SimpleITK as sitk
import yaml

from conftest import OAI, ROOT, real
from kneemesh.cohort.client import Api, Rejected, Unreachable
from kneemesh.cohort.discover import find_knees
from kneemesh.cohort.submit import STATE_FILE, SUMMARY_FILE
from kneemesh_core.metrics.compare import contact_differences
from service_helpers import RedisServer, Worker, free_port, wait_for

pytestmark = pytest.mark.xdist_group("cohort")
KEY = "cohort-lab-secret"
KNEES = ("OAI_AKOA_9014797_00m", "OAI_AKOA_9031930_00m", "OAI_AKOA_9014797_72m")


def browser() -> str:
    exe = shutil.which("chromium-headless-shell") or shutil.which("chromium")
    assert exe, "no Chromium: `make test` installs chromium-headless-shell (apt-get install chromium-headless-shell)"
    return exe


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """Redis, a Celery worker and ``kneemesh serve`` on a port, with an API key."""
    tmp = tmp_path_factory.mktemp("cohort")
    redis = RedisServer(tmp)
    data = tmp / "data"
    worker = Worker(redis.url, data, tmp)
    worker.wait_ready()
    port = free_port()
    env = {**{k: v for k, v in os.environ.items() if not k.startswith("KNEEMESH_")}, "KNEEMESH_API_KEYS": f"lab:{KEY}"}
    log = open(tmp / "serve.log", "w")
    proc = subprocess.Popen([sys.executable, "-m", "kneemesh", "serve", "--port", str(port), "--broker", redis.url,
                             "--data-dir", str(data)], stdout=log, stderr=subprocess.STDOUT, env=env)
    url = f"http://127.0.0.1:{port}"

    def ready():
        try:
            return httpx.get(f"{url}/readyz", timeout=5).json()["ready"]
        except (httpx.TransportError, ValueError):
            return False

    wait_for(ready, 60, "kneemesh serve with a worker")
    yield type("Server", (), {"url": url, "tmp": tmp, "worker": worker, "redis": redis})()
    proc.terminate()
    proc.wait(20)
    worker.kill(signal.SIGTERM)
    redis.stop()


def _cohort(tmp: Path) -> Path:
    """Three real label maps in an OAI-style tree (subject/file) and one file that is not a volume."""
    cohort = tmp / "cohort"
    for name in KNEES:
        (cohort / name.split("_")[2]).mkdir(parents=True, exist_ok=True)
        os.symlink(real(OAI / f"{name}.nii.gz"), cohort / name.split("_")[2] / f"{name}.nii.gz")
    (cohort / "broken").mkdir()
    (cohort / "broken" / "scan.nii.gz").write_bytes(b"not a volume")
    return cohort


def test_submit_survives_a_kill_gets_every_knee_once_and_reports(server, tmp_path):
    cohort, out = _cohort(tmp_path), tmp_path / "results"
    knees = find_knees(cohort)
    assert [k.id for k in knees] == ["9014797/OAI_AKOA_9014797_00m", "9014797/OAI_AKOA_9014797_72m",
                                     "9031930/OAI_AKOA_9031930_00m", "broken/scan"]
    assert [k.visit for k in knees[:3]] == ["00m", "72m", "00m"] and knees[0].input_type == "labels"
    cmd = [sys.executable, "-m", "kneemesh", "submit", str(cohort), "--server", server.url, "--key", KEY, "--out", str(out),
           "--concurrency", "2", "--poll", "0.3", "--only", "bones"]
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    first = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env)

    def one_home():
        if first.poll() is not None:
            return True
        try:
            state = json.loads((out / STATE_FILE).read_text())
        except (FileNotFoundError, json.JSONDecodeError):
            return False
        return any(v.get("state") == "done" for v in state["knees"].values())

    wait_for(one_home, 180, "the first knee to come home", every=0.05)
    assert first.poll() is None, first.stdout.read().decode()[-2000:]  # still running: killed mid-run
    first.kill()
    first.wait(10)
    state = json.loads((out / STATE_FILE).read_text())
    assert 0 < sum(v.get("state") == "done" for v in state["knees"].values()) < 3

    second = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=400)
    assert second.returncode == 0, second.stdout[-3000:] + second.stderr[-3000:]
    # while a knee is in flight its job's state shows: its queue position, then the steps running
    said = second.stderr
    assert re.search(r"OAI_AKOA_\d+_\d+m: (queued, position \d+|running: .*\d+/\d+ steps)", said), said[-2000:]
    state = json.loads((out / STATE_FILE).read_text())["knees"]
    assert {k: v["state"] for k, v in state.items()} == {**{k.id: "done" for k in knees[:3]}, "broken/scan": "rejected"}
    assert "not_an_image" in state["broken/scan"]["reason"] or "corrupt" in state["broken/scan"]["reason"]
    # every knee exactly once on the server; the refused file queued nothing
    with httpx.Client(base_url=server.url, headers={"X-API-Key": KEY}) as c:
        names = sorted(j["input_name"] for j in c.get("/v1/jobs").json()["jobs"])
        assert names == sorted(f"{n}.nii.gz" for n in KNEES)
        # a repeated submission (a crash between upload and record) gets the job already queued
        cohort_id = json.loads((out / STATE_FILE).read_text())["cohort"]
        kid = knees[0].id
        with open(knees[0].path, "rb") as fh:
            again = c.post("/v1/jobs", files={"file": (knees[0].path.name, fh)}, data={"only": "bones"},
                           headers={"Idempotency-Key": f"{cohort_id}:{kid}"})
        assert again.status_code in (200, 202) and again.json()["id"] == state[kid]["job_id"]
        assert len(c.get("/v1/jobs").json()["jobs"]) == 3
    # results mirror the cohort, every file as the manifest says
    for k in knees[:3]:
        manifest = json.loads((out / k.id / "artifacts.json").read_text())
        assert any(a["name"] == "meshes/femur.vtp" for a in manifest)
        for a in manifest:
            assert (out / k.id / a["name"]).stat().st_size == a["size"]
    rows = list(csv.DictReader((out / SUMMARY_FILE).read_text().splitlines()))
    assert [r["knee"] for r in rows] == [k.id for k in knees]
    for r in rows[:3]:
        assert r["state"] == "done" and r["verdict"] in ("ok", "review") and r["femur_status"] == "ok" and r["visit"]
        assert r["side"] in ("left", "right") and float(r["job_seconds"]) > 0
    assert rows[3]["state"] == "rejected" and rows[3]["failure"]

    # the cohort report renders in a real browser
    rep = subprocess.run([sys.executable, "-m", "kneemesh", "report", str(out)], capture_output=True, text=True, env=env)
    assert rep.returncode == 0, rep.stderr
    html_file = out / "report.html"
    dom = subprocess.run([browser(), "--headless", "--no-sandbox", "--disable-gpu", "--dump-dom", html_file.as_uri()],
                         capture_output=True, text=True, timeout=120).stdout
    assert "KneeMesh cohort report" in dom and "broken/scan" in dom and dom.count("<img") >= 1  # bones only: the timings figure
    shot = tmp_path / "report.png"
    subprocess.run([browser(), "--headless", "--no-sandbox", "--disable-gpu", f"--screenshot={shot}", "--window-size=1200,2000",
                    html_file.as_uri()], capture_output=True, timeout=120)
    pixels = (np.asarray(sitk.GetArrayFromImage(sitk.ReadImage(str(shot))))[..., :3]).reshape(-1, 3)
    assert (pixels.min(axis=1) < 200).mean() > 0.02 and len(np.unique(pixels, axis=0)) > 50  # text and figures drawn


def test_the_compose_worker_healthcheck_pings_a_real_worker(server):
    """docker-compose.yml: one image for api and worker, Redis append-only, keys required, and a worker
    healthcheck whose command answers against a running worker."""
    compose = yaml.safe_load((ROOT / "docker-compose.yml").read_text())["services"]
    assert "build" in compose["api"] and "build" not in compose["worker"]
    assert compose["api"]["image"] == compose["worker"]["image"]
    assert "--appendonly" in compose["redis"]["command"] and "yes" in compose["redis"]["command"]
    assert compose["api"]["environment"]["KNEEMESH_AUTH"].endswith("on}")
    check = compose["worker"]["healthcheck"]["test"][1]
    node = f"{server.worker.name}@{socket.gethostname()}"
    cmd = check.replace("kneemesh@$$HOSTNAME", node).replace(">/dev/null", "").replace("celery ", f"{sys.executable} -m celery ", 1)
    env = {**os.environ, "KNEEMESH_BROKER_URL": server.redis.url}
    r = subprocess.run(cmd, shell=True, capture_output=True, text=True, env=env, timeout=60,
                       cwd=ROOT)
    assert r.returncode == 0 and "pong" in r.stdout, r.stdout + r.stderr


class _Flaky(http.server.BaseHTTPRequestHandler):
    hits: dict = {}

    def do_GET(self):  # noqa: N802 - the http.server hook
        n = _Flaky.hits[self.path] = _Flaky.hits.get(self.path, 0) + 1
        status, body = {"/v1/jobs/flaky": (503, {"code": "queue_unavailable", "message": "later"}) if n <= 2 else (200, {"id": "flaky"}),
                        "/v1/jobs/bad": (422, {"code": "not_an_image", "message": "no"})}[self.path]
        data = json.dumps(body).encode()
        self.send_response(status)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(data)))
        self.end_headers()
        self.wfile.write(data)

    def log_message(self, *args):
        pass


def test_the_client_retries_what_is_transient_and_never_a_4xx():
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _Flaky)
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    waits: list[float] = []
    try:
        api = Api(f"http://127.0.0.1:{httpd.server_port}", retries=4, backoff_s=0.01, sleep=waits.append)
        assert api.job("flaky") == {"id": "flaky"} and _Flaky.hits["/v1/jobs/flaky"] == 3 and len(waits) == 2
        with pytest.raises(Rejected) as e:
            api.job("bad")
        assert e.value.code == "not_an_image" and _Flaky.hits["/v1/jobs/bad"] == 1
    finally:
        httpd.shutdown()
    waits.clear()
    refused = Api(f"http://127.0.0.1:{free_port()}", retries=3, backoff_s=0.01, sleep=waits.append)
    with pytest.raises(Unreachable, match="4 tries"):
        refused.job("x")
    assert len(waits) == 3 and waits[2] > waits[0] * 0.9  # backoff grows (with jitter)


def _cap(radius: float, layers: int = 3, thickness: float = 2.0, n: int = 24) -> pv.UnstructuredGrid:
    """A hexahedral shell cap of a sphere (radius to radius + thickness, 80 x 80 deg), top layer
    articular, in the layout of a KneeMesh cartilage mesh (cell data ``layer``)."""
    th, ph = np.meshgrid(np.radians(np.linspace(50, 130, n + 1)), np.radians(np.linspace(-40, 40, n + 1)), indexing="ij")
    directions = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1).reshape(-1, 3)
    radii = radius + thickness * np.arange(layers + 1) / layers
    points = (radii[:, None, None] * directions[None]).reshape(-1, 3)
    per = (n + 1) ** 2
    idx = np.arange(per).reshape(n + 1, n + 1)
    quads = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1).reshape(-1, 4)
    hexes = np.concatenate([np.hstack([quads + k * per, quads + (k + 1) * per]) for k in range(layers)])
    grid = pv.UnstructuredGrid({pv.CellType.HEXAHEDRON: hexes}, points)
    grid.cell_data["layer"] = np.repeat(np.arange(layers), len(quads))
    return grid


def test_compare_reproduces_known_answers(tmp_path):
    """A cartilage against itself moved 0.5 mm along its normals: median 0.5 mm, 100 % coverage; a
    label map against itself: Dice 1; contact curves against themselves and shifted by a constant."""
    from kneemesh.cohort.compare import compare

    a, b = tmp_path / "a", tmp_path / "b"
    labels = sitk.GetImageFromArray(np.repeat(np.arange(8, dtype=np.uint8), 4).reshape(2, 4, 4))
    for folder, r, h in ((a, 32.0, 1.0), (b, 32.5, 1.13)):
        (folder / "meshes").mkdir(parents=True)
        _cap(r - 2.0).save(folder / "meshes" / "femoral_cartilage.vtu")  # articular surface at r
        sitk.WriteImage(labels, str(folder / "labels.nrrd"))
        (folder / "report.json").write_text(json.dumps({"tissues": {"femoral_cartilage": {
            "element_size_mm": h, "element_size_asked_mm": 1.0 if h == 1.0 else 1.5, "coverage": 0.99, "status": "ok"}}}))
    s = compare(a, b, tmp_path / "out")
    assert all(v == 1.0 for v in s["dice"].values())
    # the same labels, two meshes: compared as meshes (volume and elements measured on the files; size asked and shipped)
    m = s["meshes"]["femoral_cartilage"]
    assert m["n_elements"] == [24 * 24 * 3] * 2 and m["element_size_mm"] == [1.0, 1.13]
    assert m["element_size_asked_mm"] == [1.0, 1.5] and m["volume_ml"][1] > m["volume_ml"][0] > 0
    dev = s["surface_deviation_mm"]["femoral_cartilage"]
    assert dev["coverage"] == 1.0 and dev["median"] == pytest.approx(0.5, abs=0.01) and dev["max"] <= 0.5 + 1e-6
    assert (tmp_path / "out" / "deviation.png").stat().st_size > 5000

    def results(shift: float) -> dict:
        return {"increments": [{"time": 1.0 + f / 90, "flexion_deg": f,
                                **{side: {"area_mm2": 300.0 + 2 * f + shift, "mean_pressure_mpa": 2.0,
                                          "peak_pressure_mpa": 4.0 + f / 30} for side in ("medial", "lateral")}}
                               for f in np.linspace(0, 90, 31)]}

    same = contact_differences(results(0.0), results(0.0))
    assert same["medial_area_mm2"]["rms"] == 0.0
    moved = contact_differences(results(0.0), results(18.0))
    assert moved["lateral_area_mm2"]["rms"] == pytest.approx(18.0) and moved["lateral_area_mm2"]["rms_of_range"] == pytest.approx(0.1)


def test_knees_are_found_in_dicom_trees_and_manifests(tmp_path):
    """The sagittal 3D DESS series of an OAI-style tree is chosen by its headers; a CSV manifest
    names knees, sides and types, and a bad row is refused with its line and what is wrong."""
    from kneemesh_core.errors import KneeMeshError

    dess = real(ROOT.parent / "shared" / "data" / "real" / "pykneer_demo" / "DESS_echo1")
    (tmp_path / "cohort" / "9999999" / "00m").mkdir(parents=True)
    os.symlink(dess, tmp_path / "cohort" / "9999999" / "00m" / "SAG_3D_DESS")
    (knee,) = find_knees(tmp_path / "cohort")
    assert knee.id == "9999999/00m/SAG_3D_DESS" and knee.input_type == "image" and knee.visit == "00m"
    assert len(knee.files) == len([p for p in dess.iterdir() if p.is_file()])
    label = real(OAI / f"{KNEES[0]}.nii.gz")
    manifest = tmp_path / "cohort.csv"
    manifest.write_text(f"id,path,side\nsubject1/left,{label},left\nsubject1/dess,{tmp_path / 'cohort'},\n")
    knees = find_knees(manifest)
    assert [(k.id, k.side, k.input_type) for k in knees] == [("subject1/left", "left", "labels"), ("subject1/dess", None, "image")]
    from kneemesh.cohort.discover import visit_of

    assert [visit_of(t) for t in ("9003406M12", "x/V01/scan", "OAI_ZIB-UQ_9011115")] == ["12m", "V01", None]
    manifest.write_text(f"id,path,side\nsubject1,{label},up\n")
    with pytest.raises(KneeMeshError, match="line 2: side 'up' is not left or right"):
        find_knees(manifest)


def test_the_cohort_report_names_each_knee_of_its_figures_in_a_browser(tmp_path):
    """Three simulated knees: the contact figure's legend names each knee beside its colour (drawn in the
    page, seen in a screenshot), the patellofemoral curves are there, the worst knee's figure is the worst,
    and each knee has its thumbnail."""
    from kneemesh.cohort.report import PALETTE

    tree = tmp_path / "cohort"
    for i, kid in enumerate(("s1/00m", "s2/00m", "s3/12m")):
        folder = tree / kid
        (folder / "fe" / "smoke").mkdir(parents=True)
        (folder / "job.json").write_text("{}")
        (folder / "report.json").write_text(json.dumps({
            "input": {"side": "right"}, "verdict": {"status": "ok", "reasons": []},
            "tissues": {"femoral_cartilage": {"status": "ok", "min_scaled_jacobian": 0.3 + 0.1 * i, "coverage": 0.97 + 0.01 * i,
                                              "volume_error": (-0.04, 0.01, 0.02)[i], "seconds": 3.0}}}))
        incs = [{"time": 1.0 + f / 15, "flexion_deg": f, **{k: {"force_n": 400.0 + 50 * i + f, "area_mm2": 150.0,
                                                                 "mean_pressure_mpa": 3.0, "peak_pressure_mpa": 8.0}
                                                             for k in ("medial", "lateral", "patellofemoral")}}
                for f in (0.0, 7.5, 15.0)]
        (folder / "fe" / "smoke" / "results.json").write_text(json.dumps({"completed": True, "increments": incs}))
        figure = np.full((60, 90, 3), 255, np.uint8)
        figure[10:50, 10:80] = (40 * i, 120, 200)
        sitk.WriteImage(sitk.GetImageFromArray(figure, isVector=True), str(folder / "attachments.png"))
    r = subprocess.run([sys.executable, "-m", "kneemesh", "report", str(tree)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    page = tree / "report.html"
    dom = subprocess.run([browser(), "--headless", "--no-sandbox", "--disable-gpu", "--dump-dom", page.as_uri()],
                         capture_output=True, text=True, timeout=120).stdout
    legend = dom[dom.index('<ul class="legend">'):]
    legend = legend[:legend.index("</ul>")]
    assert all(kid in legend for kid in ("s1/00m", "s2/00m", "s3/12m")) and "patellofemoral contact force" not in legend
    assert dom.count('class="thumb"') == 3
    assert "0.020 (0.040)" in dom  # |volume error|: the median and the worst knee's, the largest
    shot = tmp_path / "report.png"
    subprocess.run([browser(), "--headless", "--no-sandbox", "--disable-gpu", f"--screenshot={shot}", "--window-size=1300,2600",
                    page.as_uri()], capture_output=True, timeout=120)
    pixels = np.asarray(sitk.GetArrayFromImage(sitk.ReadImage(str(shot))))[..., :3].reshape(-1, 3)
    seen = {tuple(p) for p in np.unique(pixels, axis=0)}
    for colour in PALETTE[:3]:  # the legend's swatches are drawn
        assert tuple(int(colour[k:k + 2], 16) for k in (1, 3, 5)) in seen, colour

"""The service under load: N concurrent jobs through the HTTP API with one and with two Celery worker processes.

    .venv/bin/python bench/service.py [MAPS ...] [--jobs 4] [--concurrency 1,2] [--only all]

Starts a private redis-server, `kneemesh serve --broker` and `kneemesh worker -c K` for each K,
submits every job at once over HTTP, polls to completion and downloads each bundle. The same knees
are then run in-process, one after another, as `kneemesh mesh --workers K` does. Prints per-job
latency (submission to bundle), queue wait, run time (first step start to last step end),
throughput, and the service overhead: service makespan minus in-process makespan, and per job
run time minus in-process time.
Default maps: the bundled sample and the first three OAI maps in ../shared/data/real/oai_labels.
"""

from __future__ import annotations

import argparse
import datetime as dt
import os
import statistics
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
from rich.table import Table

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT.parent / "shared" / "data" / "real"
sys.path.insert(0, str(ROOT / "tests"))
from kneemesh.console import console as make_console  # noqa: E402
from service_helpers import FINISHED, RedisServer, free_port, wait_for  # noqa: E402

console = make_console()


def _t(stamp: str) -> float:
    return dt.datetime.fromisoformat(stamp).timestamp()


def one_job(base: str, path: Path, only: str) -> dict:
    with httpx.Client(base_url=base, timeout=120) as c:
        t0 = time.time()
        with open(path, "rb") as fh:
            r = c.post("/v1/jobs", files={"file": (path.name, fh)}, data={"only": only})
        r.raise_for_status()
        job = r.json()
        status = wait_for(lambda: (s := c.get(f"/v1/jobs/{job['id']}").json())["state"] in FINISHED and s, 3600,
                          "the job", every=0.25)
        size = len(c.get(job["urls"]["bundle"]).content) if status["state"] == "succeeded" else 0
        t1 = time.time()
    started = [_t(s["started_at"]) for s in status["steps"] if s["started_at"] and s["step"] != "ingest"]
    finished = [_t(s["finished_at"]) for s in status["steps"] if s["finished_at"]]
    return {"knee": path.name, "state": status["state"], "latency": t1 - t0, "wait": min(started) - t0,
            "run": max(finished) - min(started), "bundle_mb": size / 1e6}


def service(maps: list[Path], concurrency: int, only: str, tmp: Path) -> tuple[list[dict], float]:
    redis = RedisServer(tmp)
    data = tmp / f"data{concurrency}"
    port = free_port()
    env = {**os.environ, "PYTHONWARNINGS": "ignore", "KNEEMESH_DATA_DIR": str(data), "KNEEMESH_BROKER_URL": redis.url}
    log = open(tmp / f"service{concurrency}.log", "w")
    procs = [subprocess.Popen([sys.executable, "-m", "kneemesh", "worker", "-c", str(concurrency), "--loglevel", "warning"],
                              env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True),
             subprocess.Popen([sys.executable, "-m", "kneemesh", "serve", "--port", str(port)],
                              env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)]
    base = f"http://127.0.0.1:{port}"
    try:
        def ready():
            try:
                return httpx.get(base + "/readyz").json()["ready"]
            except httpx.TransportError:
                return False

        wait_for(ready, 120, "the API and worker")
        t0 = time.time()
        with ThreadPoolExecutor(len(maps)) as pool:
            rows = list(pool.map(lambda p: one_job(base, p, only), maps))
        return rows, time.time() - t0
    finally:
        for p in procs:
            p.terminate()
            p.wait(60)
        redis.stop()


def in_process(maps: list[Path], workers: int, only: str, tmp: Path) -> tuple[dict[str, float], float]:
    from kneemesh_core.job import JobRequest, run

    times = {}
    t0 = time.time()
    for m in maps:
        t = time.time()
        run(m, tmp / f"cli{workers}" / m.name, JobRequest.build(only=only).job_options(), workers=workers)
        times[m.name] = time.time() - t
    return times, time.time() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("maps", nargs="*", type=Path)
    ap.add_argument("--jobs", type=int, default=4, help="How many of the maps to submit (default 4).")
    ap.add_argument("--concurrency", default="1,2", help="Worker process counts to try (default 1,2).")
    ap.add_argument("--only", default="all", choices=("all", "bones", "cartilage"))
    a = ap.parse_args()
    maps = a.maps or [ROOT / "kneemesh" / "data" / "right_knee_example.nrrd", *sorted((REAL / "oai_labels").glob("*.nii.gz"))[:3]]
    maps = maps[: a.jobs]
    import warnings

    warnings.filterwarnings("ignore")
    console.print(f"{len(maps)} knees, tissues: {a.only}, {os.cpu_count()} cores")
    table = Table(title="Service vs in-process, same knees")
    for col in ("worker processes", "jobs ok", "makespan s", "in-process s", "overhead s", "jobs/min",
                "latency med/max s", "queue wait med/max s", "run - in-process med s"):
        table.add_column(col, justify="right")
    with tempfile.TemporaryDirectory() as tmpdir:
        tmp = Path(tmpdir)
        for k in (int(x) for x in a.concurrency.split(",")):
            rows, span = service(maps, k, a.only, tmp)
            cli, cli_span = in_process(maps, k, a.only, tmp)
            for r in rows:
                console.print(f"  K={k} {r['knee']}: {r['state']}, latency {r['latency']:.1f} s, wait {r['wait']:.1f} s, "
                              f"run {r['run']:.1f} s (in-process {cli[r['knee']]:.1f} s), bundle {r['bundle_mb']:.1f} MB")
            lat = [r["latency"] for r in rows]
            wait = [r["wait"] for r in rows]
            extra = [r["run"] - cli[r["knee"]] for r in rows]
            table.add_row(str(k), f"{sum(r['state'] == 'succeeded' for r in rows)}/{len(rows)}", f"{span:.1f}",
                          f"{cli_span:.1f}", f"{span - cli_span:+.1f}", f"{60 * len(rows) / span:.2f}",
                          f"{statistics.median(lat):.1f}/{max(lat):.1f}", f"{statistics.median(wait):.1f}/{max(wait):.1f}",
                          f"{statistics.median(extra):+.1f}")
    console.print(table)


if __name__ == "__main__":
    main()

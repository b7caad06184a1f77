"""Real components for the service tests: a Redis server, Celery worker processes, the API over HTTP."""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

FINISHED = ("succeeded", "failed", "cancelled")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for(predicate, timeout: float, what: str, every: float = 0.3):
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        value = predicate()
        if value:
            return value
        time.sleep(every)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")


class RedisServer:
    """A private redis-server on a free port (nothing kept on disk)."""

    def __init__(self, workdir: Path):
        exe = shutil.which("redis-server")
        if exe is None:
            pytest.skip("redis-server is not installed (the service tests need a real Redis)")
        self.port = free_port()
        self.url = f"redis://127.0.0.1:{self.port}/0"
        self.proc = subprocess.Popen([exe, "--port", str(self.port), "--bind", "127.0.0.1", "--save", "",
                                      "--appendonly", "no", "--dir", str(workdir)],
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        import redis

        self.client = redis.Redis.from_url(self.url)

        def up():
            try:
                return self.client.ping()
            except redis.exceptions.ConnectionError:
                return False

        wait_for(up, 20, "redis-server to answer")

    def stop(self):
        self.proc.terminate()
        self.proc.wait(10)


class Worker:
    """``kneemesh worker`` as its own process group, so SIGKILL takes the pool children too."""

    count = 0

    def __init__(self, broker: str, data_dir: Path, log_dir: Path, env: dict | None = None):
        Worker.count += 1
        self.name = f"w{Worker.count}"
        self.log = log_dir / f"{self.name}.log"
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "kneemesh", "worker", "--broker", broker, "--data-dir", str(data_dir),
             "-c", "2", "--name", f"{self.name}@%h", "--loglevel", "info"],
            stdout=open(self.log, "w"), stderr=subprocess.STDOUT, start_new_session=True,
            env={**os.environ, "PYTHONWARNINGS": "ignore", **(env or {})})

    def wait_ready(self, timeout: float = 60):
        wait_for(lambda: "ready." in self.log.read_text() or self.proc.poll() is not None, timeout, f"{self.name} to start")
        assert self.proc.poll() is None, self.log.read_text()[-3000:]

    def kill(self, sig=signal.SIGKILL):
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, sig)
            self.proc.wait(30)


def poll(client, job_id: str, timeout: float = 240, headers=None) -> dict:
    return wait_for(lambda: (s := client.get(f"/v1/jobs/{job_id}", headers=headers).json())["state"] in FINISHED and s,
                    timeout, f"job {job_id} to finish")

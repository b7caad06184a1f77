"""The Celery application: one task, ``kneemesh.step``, and the canvas that chains a job's plan.

Each step of ``kneemesh_core.job.plan`` is one task; a stage with several
steps (the three bones, the four cartilages) is a group, so Celery chains it
into a chord with the next stage. New stages (attachment sites, FE decks, a
simulation) join the plan and appear here without any change.

Delivery is at-least-once: ``acks_late`` with ``reject_on_worker_lost``, so a
task whose worker dies is delivered again (Redis redelivers after the
visibility timeout), and every step is idempotent (a step already done returns
its record). Time limits turn a hung tissue into a failed tissue: the soft
limit raises inside the mesher, which reports it as that tissue's failure, and
the other tissues go on.

``celery -A services.worker.celery_app worker`` (or ``kneemesh worker``) reads
the ``KNEEMESH_*`` settings from the environment.
"""

from __future__ import annotations

import os
import socket

import redis.exceptions
from celery import Celery, chain, group
from celery.exceptions import Ignore
from kombu.exceptions import OperationalError

from kneemesh_core.job import JobOptions, plan, run_step
from services.jobs import Jobs
from services.settings import Settings
from services.store import FileStore

QUEUE = "kneemesh"
TRANSIENT = (redis.exceptions.ConnectionError, redis.exceptions.TimeoutError, OperationalError, ConnectionError)



def make_app(settings: Settings, main: str = "kneemesh") -> Celery:
    """A Celery app on the settings' broker with the delivery guarantees above.

    The workers use the module's ``app`` (tasks registered, settings from the
    environment); the API makes its own to send by task name, so it never shares
    connections or configuration with anything else in its process.
    """
    app = Celery(main)
    app.conf.update(
        broker_url=settings.broker_url,
        result_backend=settings.backend_url,
        # a worker scans for unacknowledged tasks to deliver again every second, under a Redis lock that
        # outlives a worker killed while holding it by kombu's default of 300 s: 30 s here, so that a
        # kill that lands inside a scan delays redelivery by 30 s, not 5 min (a scan takes milliseconds)
        broker_transport_options={"visibility_timeout": settings.visibility_timeout_s,
                                  "unacked_restore_interval": 1, "unacked_restore_throttle": 1,
                                  "unacked_mutex_expire": 30},
        result_backend_transport_options={"visibility_timeout": settings.visibility_timeout_s},
        broker_connection_retry_on_startup=True,
        broker_connection_timeout=2,
        task_serializer="json",
        result_serializer="json",
        accept_content=["json"],
        task_default_queue=QUEUE,
        task_acks_late=True,
        task_reject_on_worker_lost=True,
        task_acks_on_failure_or_timeout=True,
        task_track_started=True,
        task_soft_time_limit=settings.task_soft_time_limit_s,
        task_time_limit=settings.task_time_limit_s,
        worker_prefetch_multiplier=1,  # long tasks: one at a time per process, fair across workers
        result_expires=7 * 86400,
        result_extended=True,
    )
    app.kneemesh_settings = settings
    return app


app = make_app(Settings())


def _jobs() -> Jobs:
    return Jobs(FileStore(app.kneemesh_settings.data_dir))


@app.task(name="kneemesh.step", bind=True, autoretry_for=TRANSIENT, retry_backoff=2, retry_backoff_max=60,
          max_retries=5)
def step_task(self, job_id: str, step: str) -> dict:
    """Run one step of one job (idempotent); a cancelled or deleted job stops its chain here."""
    jobs = _jobs()
    rec = jobs.get(job_id)
    if rec is None or rec.cancelled or rec.deleted:
        raise Ignore()
    context = {"task_id": self.request.id, "worker": self.request.hostname or socket.gethostname(),
               "pid": os.getpid(), "delivery": int(self.request.retries) + 1}
    record = run_step(jobs.out_dir(rec), step, rec.options, jobs.input_path(rec), context)
    rec = jobs.get(job_id)
    if rec is None or rec.deleted:  # deleted while this step ran: what it wrote goes too
        jobs.store.delete(job_id)
        raise Ignore()
    return {"step": step, "state": record["state"], "seconds": record.get("seconds")}


def job_signature(job_id: str, options: dict):
    """The canvas of one job: its plan's stages chained, each multi-step stage a group."""
    stages = [group(step_task.si(job_id, s) for s in stage) if len(stage) > 1 else step_task.si(job_id, stage[0])
              for stage in plan(JobOptions.from_dict(options))]
    return chain(*stages)


@app.task(name="kneemesh.start", autoretry_for=TRANSIENT, retry_backoff=2, max_retries=5)
def start_task(job_id: str) -> None:
    """Lay out a job's canvas. Done by a worker, not the API, so the API only sends one message
    and never waits on the result store (a chord's publisher subscribes to its results)."""
    rec = _jobs().get(job_id)
    if rec is None or rec.cancelled or rec.deleted:
        raise Ignore()
    job_signature(job_id, rec.options).apply_async()


class CeleryRunner:
    """What the API calls to queue, cancel and check jobs when a broker is configured."""

    name = "celery"

    def __init__(self, settings: Settings):
        self.app = make_app(settings, "kneemesh-api")

    def start(self, jobs: Jobs) -> None:
        """Nothing to start: the workers are other processes."""

    def stop(self) -> None:
        self.app.close()

    def submit(self, rec) -> None:
        self.app.send_task(start_task.name, (rec.id,), queue=QUEUE, ignore_result=True, retry=True,
                           retry_policy={"max_retries": 2, "interval_start": 0, "interval_step": 0.5})

    def cancel(self, rec, steps: list[dict]) -> None:
        """Stop running steps now; queued ones see the cancelled record and stop the chain."""
        running = [s["task_id"] for s in steps if s.get("task_id") and s["state"] == "running"]
        if running:  # wait (briefly) for the workers to say they stopped them, so their files can go
            self.app.control.revoke(running, terminate=True, signal="SIGTERM", reply=True, timeout=2.0)

    def ready(self) -> dict:
        try:
            with self.app.connection_for_write() as conn:
                conn.ensure_connection(max_retries=1, timeout=2)
            replies = self.app.control.ping(timeout=1.0) or []
        except Exception as exc:  # broker down: not ready, say why
            return {"ready": False, "runner": self.name, "workers": 0, "detail": f"broker unreachable: {exc}"}
        return {"ready": bool(replies), "runner": self.name, "workers": len(replies),
                "detail": "ok" if replies else "no worker answered a ping"}

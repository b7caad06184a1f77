"""The service commands: ``serve`` the API, start a Celery ``worker``, ``cleanup`` old jobs, print the
``openapi`` document."""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Optional

import typer

from kneemesh.cli.app import app, clear_errors, err, out

DataDirOpt = typer.Option(None, "--data-dir", help="Job folders live here (default: $KNEEMESH_DATA_DIR or ./kneemesh-data).")
BrokerOpt = typer.Option(None, "--broker", help="redis://host:port/db (default: $KNEEMESH_BROKER_URL).")


def _service_env(**flags) -> None:
    """The service reads its settings from ``KNEEMESH_*`` variables (:class:`services.settings.Settings`); the
    flags given override them for this process and its children."""
    for name, value in flags.items():
        if value is not None:
            os.environ[f"KNEEMESH_{name.upper()}"] = str(value)


@app.command()
def serve(
    host: str = typer.Option("127.0.0.1", "--host", help="Address to listen on."),
    port: int = typer.Option(8000, "--port", help="Port to listen on."),
    broker: Optional[str] = BrokerOpt,
    data_dir: Optional[Path] = DataDirOpt,
    workers: Optional[int] = typer.Option(None, "--workers", min=1, help="Embedded mode: processes meshing tissues "
                                                                         "(default: $KNEEMESH_WORKERS or 2)."),
):
    """Run the HTTP API. With no broker, jobs run on an in-process pool; with --broker they go to Celery workers."""
    import uvicorn

    _service_env(data_dir=data_dir, broker_url=broker, workers=workers)
    with clear_errors():
        from services.api import create_app

        api = create_app()
        settings = api.state.settings
        settings.check_listen(host)
    mode = f"Celery on {settings.broker_url}" if settings.broker_url else f"embedded, {settings.workers} worker processes"
    err.print(f"kneemesh API on http://{host}:{port} ({mode}); jobs in {api.state.jobs.store.root}")
    uvicorn.run(api, host=host, port=port, log_level="info")


@app.command()
def worker(
    broker: Optional[str] = BrokerOpt,
    data_dir: Optional[Path] = DataDirOpt,
    concurrency: int = typer.Option(2, "--concurrency", "-c", min=1, help="Worker processes."),
    loglevel: str = typer.Option("info", "--loglevel", help="Celery log level."),
    name: Optional[str] = typer.Option(None, "--name", help="Worker node name (default: kneemesh@host)."),
):
    """Start a Celery worker for the service's jobs (needs --broker or $KNEEMESH_BROKER_URL)."""
    _service_env(data_dir=data_dir, broker_url=broker)
    from services.settings import Settings

    if not Settings().broker_url:
        err.print("[bold red]error[/] (no_broker): a worker needs a broker: --broker redis://host:6379/0 or KNEEMESH_BROKER_URL.")
        raise typer.Exit(2)
    from services.worker.celery_app import QUEUE, app as celery_app

    celery_app.worker_main(["worker", "-Q", QUEUE, "-c", str(concurrency), "-l", loglevel, "-n", name or "kneemesh@%h"])


@app.command()
def cleanup(
    data_dir: Optional[Path] = DataDirOpt,
    older_than: Optional[float] = typer.Option(None, "--older-than", help="Days (default: $KNEEMESH_RETENTION_DAYS or 30)."),
):
    """Delete finished jobs older than the retention period, with their uploads and artifacts."""
    _service_env(data_dir=data_dir)
    from services.jobs import Jobs
    from services.settings import Settings
    from services.store import FileStore

    settings = Settings()
    days = settings.retention_days if older_than is None else older_than
    gone = Jobs(FileStore(settings.data_dir)).expire(days)
    out.print(f"removed {len(gone)} job(s) older than {days:g} days from {settings.data_dir}")


@app.command()
def openapi(out_file: Optional[Path] = typer.Option(None, "--out", help="Write here instead of stdout.")):
    """Print the API's OpenAPI document (YAML), as committed in openapi.yaml."""
    from services.api.openapi import openapi_yaml

    text = openapi_yaml()
    if out_file is None:
        sys.stdout.write(text)
    else:
        out_file.write_text(text)

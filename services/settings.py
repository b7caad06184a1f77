"""Service settings, declared once: each a ``KNEEMESH_*`` environment variable (the CLI flags set the
same names), read by pydantic-settings; a test or a tool may also pass them directly."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

from pydantic import AliasChoices, Field, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from kneemesh_core.errors import KneeMeshError

GiB = 1 << 30
#: Addresses that only this machine reaches.
LOOPBACK = ("127.0.0.1", "::1", "localhost")


def _env(name: str) -> AliasChoices:
    """A setting read from ``KNEEMESH_<name>`` that may also be given by its field's name."""
    return AliasChoices(f"KNEEMESH_{name}")


class Settings(BaseSettings):
    """Everything the API and the workers need to agree on.

    ``broker_url`` None means embedded mode: the API runs jobs on an in-process pool.
    ``api_keys`` empty means no authentication (one machine, one lab); otherwise every
    request needs ``X-API-Key`` and a key sees only its own jobs.
    """

    model_config = SettingsConfigDict(env_prefix="KNEEMESH_", env_ignore_empty=True, frozen=True, populate_by_name=True,
                                      extra="ignore")

    data_dir: Path = Field(Path("kneemesh-data"), description="Where the job folders live.")
    broker_url: str | None = Field(None, description="redis://host:port/db: Celery mode; none: embedded mode.")
    result_backend: str | None = Field(None, description="Celery's result backend (default: the broker).")
    api_keys: Annotated[dict[str, str], NoDecode] = Field(
        default_factory=dict, description="'lab-a:KEY1,lab-b:KEY2' (or bare keys): key -> owner.")
    auth: bool = Field(True, description="off: listen beyond the loopback with no API keys (a closed network).")
    max_upload_bytes: int = Field(GiB, description="The largest request accepted, bytes.")
    workers: int = Field(2, description="Embedded mode: processes running a job's steps.")
    task_soft_time_limit_s: int = Field(1500, validation_alias=_env("TASK_SOFT_TIME_LIMIT"),
                                        description="A step's soft time limit, s: its tissue fails, the knee goes on.")
    task_time_limit_s: int = Field(1800, validation_alias=_env("TASK_TIME_LIMIT"), description="A step's hard time limit, s.")
    # Must exceed the longest task: Redis redelivers unacknowledged tasks after it.
    visibility_timeout_s: int = Field(7200, validation_alias=_env("VISIBILITY_TIMEOUT"),
                                      description="Redis redelivers a task unacknowledged this long, s.")
    retention_days: float = Field(30.0, description="`kneemesh cleanup` removes finished jobs older than this, days.")

    @field_validator("api_keys", mode="before")
    @classmethod
    def _parse_keys(cls, value):
        """``"alice:KEY1,bob:KEY2"`` (or bare ``"KEY1,KEY2"``) -> {key: owner name}."""
        if not isinstance(value, str):
            return value
        keys: dict[str, str] = {}
        for i, item in enumerate(filter(None, (x.strip() for x in value.split(",")))):
            name, _, key = item.rpartition(":")
            if len(key) < 8:
                raise KneeMeshError("bad_option", f"KNEEMESH_API_KEYS: key {i + 1} is shorter than 8 characters.")
            keys[key] = name or f"key{i + 1}"
        return keys

    @property
    def backend_url(self) -> str | None:
        """Celery's result backend: the broker's Redis unless set apart."""
        return self.result_backend or self.broker_url

    def check_listen(self, host: str) -> None:
        """Refuse to serve on ``host`` when the network could reach an API with no keys (``api_keys_required``),
        unless ``auth`` is off."""
        if not self.api_keys and host not in LOOPBACK and self.auth:
            raise KneeMeshError("api_keys_required", f"the API would listen on {host}, reachable from the network, with no "
                                "API keys: set KNEEMESH_API_KEYS='lab-a:a-long-secret,...', or KNEEMESH_AUTH=off to run "
                                "without keys on a closed network.")
